"""``smdinspect reconstruct``: a focal stack → height map, confidence, cloud, mesh."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def add_calibration_argument(p: argparse.ArgumentParser, where: str) -> None:
    """``--calibration CAL_JSON`` (reconstruct, inspect, batch, grr)."""
    p.add_argument("--calibration", type=Path, default=None, metavar="CAL_JSON",
                   help="rig calibration (smdinspect calibrate): its focal-plane correction "
                        f"and z scale applied {where}")


def check_calibration_argument(args: argparse.Namespace) -> None:
    """Read ``--calibration`` now: a bad file fails before any sweep is processed."""
    if getattr(args, "calibration", None) is not None:
        from ..calibrate import read_calibration

        read_calibration(args.calibration)


def add_stack_arguments(p: argparse.ArgumentParser) -> None:
    """Stack input and focus options shared by ``reconstruct`` and ``inspect``."""
    from ..sff import FitMethod, OPERATORS

    p.add_argument("stack", nargs="+", metavar="STACK",
                   help="a stack directory (with stack.json) or image files in focus order")
    p.add_argument("--step-mm", type=float, default=None,
                   help="focus step between listed images (mm); needed for image lists")
    p.add_argument("--z-from-name", default=None, metavar="REGEX",
                   help="read each listed image's z (mm) from its file name: the first group "
                        "of REGEX, e.g. 'Z(-?[0-9.]+)' for XP005_Z-020.jpg (instead of "
                        "--step-mm)")
    p.add_argument("--pixel-size-mm", type=float, default=None,
                   help="object-side pixel size (mm); overrides stack.json")
    p.add_argument("--operator", default="sml", choices=(*OPERATORS, "auto"), metavar="OP",
                   help="focus measure (default sml; one of: %(choices)s; auto, in "
                        "reconstruct: picked from the stack's texture by the texture study)")
    p.add_argument("--window-px", type=int, default=9,
                   help="focus window side, odd (default: 9 for reconstruct and calibrate; "
                        "inspect, grr and batch: about 70 µm of the board, at least 5 px)")
    p.add_argument("--fit", default="power", choices=[m.value for m in FitMethod],
                   help="peak model, fitted above the curve's floor (default power: the "
                        "power-law peak of defocused texture; gauss3: Nayar's 3-point "
                        "Gaussian; lsq: least-squares Gaussian; argmax)")
    p.add_argument("--fit-half-width", type=int, default=3,
                   help="frames kept each side of the peak for R and lsq (default 3)")
    p.add_argument("--min-confidence", type=float, default=0.5,
                   help="pixels below this confidence are unreliable (default 0.5)")
    p.add_argument("--align", action="store_true",
                   help="register frames first (ordinary, non-telecentric lenses)")
    p.add_argument("--prefilter", default=None, metavar="auto|PX",
                   help="Gaussian σ (px) smoothing each frame before the focus measure, against "
                        "sensor noise; 'auto' picks it from the sweep's noise-only frequencies, "
                        "0 turns it off (default: auto for reconstruct, 0 for inspect and grr)")
    p.add_argument("--coarse-levels", type=int, default=None, choices=(1, 2, 3), metavar="N",
                   help="coarse focus levels (4x, 16x, 64x blocks) filling what finer ones left "
                        "unreliable, on smooth, weakly textured parts (default 2; inspect and "
                        "grr use none)")
    p.add_argument("--plane-px", type=int, default=None, metavar="PX",
                   help="each reliable height becomes the least-squares plane through the "
                        "reliable heights of the PX square around it (odd; 0 off; default 5 "
                        "for reconstruct, 0 for inspect and grr)")
    p.add_argument("--band-mpixels", type=float, default=None, metavar="MPX",
                   help="frames larger than this are measured in bands of rows of at most MPX "
                        "megapixels each, margins included: memory follows the band, not the "
                        "frame (default 3.5; 0: whole frames)")
    p.add_argument("--workers", type=int, default=2, help="decode/focus threads (default 2)")
    p.add_argument("--keep-unreliable", action="store_true",
                   help="keep unreliable points in cloud.ply and the mesh")


def prefilter_value(text: str) -> float | str:
    """``--prefilter``'s value: "auto" or a σ in pixels."""
    from ..errors import InputError

    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise InputError(f"--prefilter must be 'auto' or a number of pixels; got {text!r}") from None


def focus_config_from(args: argparse.Namespace, base=None):
    """The FocusConfig the command line asks for: ``base`` (a FocusConfig; the
    reconstruction defaults when None) with the options given replaced."""
    import dataclasses

    from ..errors import InputError
    from ..sff import FocusConfig

    if args.operator == "auto":  # reconstruct resolves it first (_cli/study.py)
        raise InputError("--operator auto is only available in smdinspect reconstruct")
    given = dict(operator=args.operator, fit=args.fit,
                 fit_half_width=args.fit_half_width, min_confidence=args.min_confidence,
                 align=args.align, workers=args.workers)
    if args.window_px is not None:  # inspect and grr: else the base's (from the pixel size)
        given["window_px"] = args.window_px
    if getattr(args, "coarse_levels", None) is not None:  # else the base's (or the default)
        given["coarse_levels"] = args.coarse_levels
    if getattr(args, "plane_px", None) is not None:
        given["plane_px"] = args.plane_px
    if getattr(args, "band_mpixels", None) is not None:
        given["band_mpixels"] = args.band_mpixels
    if getattr(args, "prefilter", None) is not None:
        given["prefilter_px"] = prefilter_value(args.prefilter)
    return dataclasses.replace(base, **given) if base is not None else FocusConfig(**given)


def add_cloud_filled_argument(p: argparse.ArgumentParser) -> None:
    """``--cloud-filled`` (``reconstruct``, ``inspect``, ``batch``)."""
    p.add_argument("--cloud-filled", action="store_true",
                   help="cloud.ply also holds the filled points of the dense surface (where "
                        "no height was measured), each with filled = 1 and sigma_filled, the "
                        "fill's uncertainty (mm); not with --keep-unreliable")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="focal stack → height map, confidence, cloud, mesh",
                       description="Measure every pixel's height by shape from focus.")
    add_stack_arguments(p)
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--outputs", default="all", metavar="LIST",
                   help="comma-separated files to write (default all): height_mm.tiff, "
                        "confidence.tiff, sigma_mm.tiff, aif.png, height_filled_mm.tiff, "
                        "sigma_filled_mm.tiff, filled.png, field.png, height.png, reason.png, "
                        "view3d.png, cloud.ply, mesh.ply, mesh.stl; summary.json is always "
                        "written")
    add_cloud_filled_argument(p)
    add_calibration_argument(p, "to the heights (and its pixel size taken when the stack "
                                "has none)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from .. import _atomic
    from ..calibrate import apply_calibration_file
    from ..cli import progress_callback
    from ..sff import reconstruct, write_reconstruction
    from ..sff._export import RECONSTRUCTION_OUTPUTS, check_cloud_options
    from ..errors import InputError
    from ..stack import open_stack
    from .study import resolve_auto_operator

    outputs = None if args.outputs.strip() == "all" else \
        [name.strip() for name in args.outputs.split(",") if name.strip()]
    unknown = sorted(set(outputs or ()) - set(RECONSTRUCTION_OUTPUTS))
    if unknown:
        raise InputError(f"--outputs: unknown {', '.join(unknown)}; choose from "
                         f"{', '.join(RECONSTRUCTION_OUTPUTS)} (or all)")
    check_cloud_options(args.keep_unreliable, args.cloud_filled)
    check_calibration_argument(args)
    stack = open_stack(args.stack, step_mm=args.step_mm, pixel_size_mm=args.pixel_size_mm,
                       z_from_name=args.z_from_name)
    auto = resolve_auto_operator(args, stack)  # --operator auto: the texture study's pick
    config = focus_config_from(args)
    if stack.pixel_size_mm is None:
        log.warning("pixel size unknown (give --pixel-size-mm): x and y are written in pixels")
    with _atomic.replace_dir(args.out, replaces=RECONSTRUCTION_OUTPUTS) as tmp:
        surface = reconstruct(stack, config, progress=progress_callback(args, "focus"))
        surface = apply_calibration_file(surface, args.calibration)
        log.info("writing the height maps, previews, cloud and mesh to %s", args.out)
        write_reconstruction(surface, tmp, keep_unreliable=args.keep_unreliable,
                             cloud_filled=args.cloud_filled, outputs=outputs,
                             extra_summary=auto and {"operator_auto": auto})
    if not surface.reliable.any():
        raise nothing_measured(len(stack), args.out)
    h = surface.height_mm[surface.reliable]
    print(f"reconstructed {len(stack)} frames, {surface.shape[1]}x{surface.shape[0]} px: "
          f"coverage {100 * surface.coverage:.1f}%, heights {h.min():.3f} .. {h.max():.3f} mm, "
          f"{surface.meta['mpixel_per_s']:.0f} Mpixel/s")
    if surface.precision_mm is not None:
        p = surface.precision_mm[surface.reliable]
        known = p[np.isfinite(p)]
        share = known.size / p.size
        if share >= 0.05:
            print(f"random error (1σ, from the frames' noise) median {1000 * np.median(known):.1f} "
                  f"µm, known for {100 * share:.0f}% of the reliable pixels")
        else:
            print(f"random error known for {100 * share:.1f}% of the reliable pixels only: their "
                  "focus curves are too narrow to split (a step coarse against the depth of field)")
    reasons = surface.unreliable_reasons()
    if reasons:
        top = [f"{name.replace('_', ' ')} {100 * share:.1f}%"
               for name, share in reasons.items() if share >= 0.005][:4]
        where = " (where: reason.png)" if outputs is None or "reason.png" in outputs else ""
        print(f"unreliable {100 * sum(reasons.values()):.1f}% of the image: "
              f"{', '.join(top) or 'scattered'}{where}")
    hint = " (open view3d.png first)" if outputs is None or "view3d.png" in outputs else ""
    print(f"outputs in {args.out}/{hint}")
    return 0


def nothing_measured(n_frames: int, out: Path):
    """The error of a stack in which no pixel has a reliable focus peak."""
    from ..errors import InputError

    return InputError(
        f"nothing could be measured: no pixel of the {n_frames} frames has a reliable focus "
        "peak (no texture in focus? check the sweep's z range, the lighting, --min-confidence); "
        f"{out}/ holds the maps, aif.png and summary.json, no cloud or mesh")
