"""``smdinspect calibrate pixel-size | flat | z-scale``: rig calibration into a calibration file."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _rig_pixel_size(rig: Path | None) -> float | None:
    if rig is None:
        return None
    import tomllib

    from ..errors import InputError

    try:
        doc = tomllib.loads(rig.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"--rig {rig}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"--rig {rig}: not valid TOML: {exc}") from None
    value = (doc.get("camera") or {}).get("pixel_size_mm")
    return float(value) if isinstance(value, (int, float)) else None


def _default_out(args: argparse.Namespace) -> Path:
    from ..errors import InputError

    if args.out is not None:
        return args.out
    if args.rig is not None:
        return args.rig.with_name(args.rig.stem + ".cal.json")
    raise InputError("give --out (or --rig: the calibration then goes to RIG.cal.json)")


def register(sub: argparse._SubParsersAction) -> None:
    from ..calibrate import TargetKind

    p = sub.add_parser("calibrate", help="rig calibration: pixel size, focal-plane tilt/curvature, "
                                         "z scale",
                       description="Calibrate a rig; results go to a calibration file "
                                   "(rig.cal.json) that reconstruct --calibration applies.")
    csub = p.add_subparsers(dest="calibrate_command", metavar="ACTION", required=True)
    px = csub.add_parser("pixel-size", help="pixel size + lens distortion from a target image",
                         description="Detect a checkerboard or dot-grid target of known pitch "
                                     "and report the object-side pixel size, the fit residual "
                                     "and the radial lens distortion.")
    px.add_argument("image", type=Path, metavar="TARGET_IMAGE")
    px.add_argument("--pitch-mm", type=float, required=True,
                    help="dot pitch or checkerboard square size (mm)")
    px.add_argument("--target", default="auto", choices=[t.value for t in TargetKind],
                    help="target pattern (default auto)")
    px.add_argument("--rig", type=Path, default=None, help="rig file (TOML)")
    px.add_argument("--out", type=Path, default=None,
                    help="calibration file to write or update (default RIG.cal.json)")
    px.add_argument("--update-rig", action="store_true",
                    help="also write the pixel size into the rig file's [camera] table")
    px.add_argument("--no-distortion", action="store_true", help="fit an affine grid only")
    px.set_defaults(func=run_pixel_size)

    fl = csub.add_parser("flat", help="focal-plane tilt + field curvature from a flat-target sweep",
                         description="Reconstruct a sweep of a flat textured target, fit its "
                                     "height map with a low-order 2D polynomial and store it as "
                                     "the correction reconstruct --calibration subtracts.")
    _add_sweep_arguments(fl)
    fl.add_argument("--degree", type=int, default=2,
                    help="polynomial degree: 1 tilt only, 2 tilt + curvature (default), up to 4")
    fl.set_defaults(func=run_flat)

    zs = csub.add_parser("z-scale", help="z scale and direction from a step target of known height",
                         description="Reconstruct a sweep of a step of known height (a gauge "
                                     "block or shim on a flat base, both surfaces textured), "
                                     "read the step as two parallel planes and store the z "
                                     "scale that makes it read true; a step that reads "
                                     "downwards means z runs the wrong way (an error). The "
                                     "calibration file's focal-plane correction, if any, is "
                                     "applied before the step is read.")
    _add_sweep_arguments(zs)
    zs.add_argument("--step-height-mm", type=float, required=True,
                    help="the step's known height (mm), e.g. a gauge block's")
    zs.add_argument("--top-at", default=None, metavar="X,Y",
                    help="a pixel (column,row) on the upper surface (default: the field's "
                         "centre is on it)")
    zs.set_defaults(func=run_z_scale)


def _add_sweep_arguments(p: argparse.ArgumentParser) -> None:
    """A calibration sweep's stack and focus options, the rig and the calibration file."""
    from .reconstruct import add_stack_arguments

    add_stack_arguments(p)
    p.add_argument("--rig", type=Path, default=None,
                   help="rig file (TOML): pixel size when the stack has none")
    p.add_argument("--out", type=Path, default=None,
                   help="calibration file to write or update (default RIG.cal.json)")


def run_pixel_size(args: argparse.Namespace) -> int:
    from ..calibrate import pixel_size_from_image, set_rig_pixel_size, write_calibration
    from ..errors import InputError
    from ..stack import read_image

    if not args.image.is_file():
        raise InputError(f"target image {str(args.image)!r} does not exist")
    out = _default_out(args)
    before = _rig_pixel_size(args.rig)
    image = read_image(args.image)
    result = pixel_size_from_image(image, pitch_mm=args.pitch_mm, target=args.target,
                                   distortion=not args.no_distortion)
    print(result.summary())
    write_calibration(out, pixel_size=result)
    print(f"calibration: {out}")
    if args.update_rig:
        if args.rig is None:
            raise InputError("--update-rig needs --rig")
        set_rig_pixel_size(args.rig, result.pixel_size_mm)
        was = f"{before:g}" if before is not None else "unset"
        print(f"{args.rig.name}: [camera] pixel_size_mm {was} → {result.pixel_size_mm:.6g}")
    elif before is not None:
        change = 100.0 * (result.pixel_size_mm / before - 1.0)
        print(f"the rig file says {before:g} mm ({change:+.2f} %); --update-rig writes the "
              f"measured value")
    return 0


def _reconstruct_target(args: argparse.Namespace):
    """The calibration sweep's reconstruction (the rig's pixel size when it has none)."""
    from ..cli import progress_callback
    from ..sff import reconstruct
    from ..stack import _replace_pixel, open_stack
    from .reconstruct import focus_config_from

    stack = open_stack(args.stack, step_mm=args.step_mm, pixel_size_mm=args.pixel_size_mm,
                       z_from_name=args.z_from_name)
    if stack.pixel_size_mm is None:
        pixel = _rig_pixel_size(args.rig)
        if pixel is not None:  # the rig's, for a stack that records none
            stack = _replace_pixel(stack, pixel)
    return reconstruct(stack, focus_config_from(args), progress=progress_callback(args, "focus"))


def run_flat(args: argparse.Namespace) -> int:
    from ..calibrate import apply_calibration, calibrate_flat, write_calibration

    out = _default_out(args)
    surface = _reconstruct_target(args)
    cal = calibrate_flat(surface, degree=args.degree)
    print(cal.summary())
    check = calibrate_flat(apply_calibration(surface, cal), degree=args.degree)
    print(f"after the correction: tilt "
          + (f"{check.tilt_deg:.4f}°" if check.tilt_deg is not None else "n/a")
          + f", sag {check.curvature_sag_mm * 1000:.2f} µm")
    write_calibration(out, focal_plane=cal)
    print(f"calibration: {out} (apply with: smdinspect reconstruct STACK --calibration {out})")
    return 0


def run_z_scale(args: argparse.Namespace) -> int:
    from ..calibrate import (apply_calibration, apply_z_scale, calibrate_z_scale,
                             read_calibration, write_calibration)
    from ..errors import InputError

    out = _default_out(args)
    top_at = None
    if args.top_at is not None:
        try:
            x, y = (float(t) for t in args.top_at.split(","))
        except ValueError:
            raise InputError(f"--top-at must be X,Y (pixel column,row); got {args.top_at!r}") \
                from None
        top_at = (x, y)
    focal = read_calibration(out)["focal_plane"] if out.is_file() else None
    surface = _reconstruct_target(args)
    if focal is not None:  # measured in nominal z, like this sweep
        surface = apply_calibration(surface, focal)
        print(f"focal-plane correction of {out} applied before reading the step")
    cal = calibrate_z_scale(surface, step_height_mm=args.step_height_mm, top_at=top_at)
    print(cal.summary())
    check = calibrate_z_scale(apply_z_scale(surface, cal), step_height_mm=args.step_height_mm,
                              top_at=top_at)
    print(f"after the correction the step reads {check.measured_step_mm * 1000:.1f} µm")
    write_calibration(out, z_scale=cal)
    print(f"calibration: {out} (apply with: smdinspect reconstruct STACK --calibration {out})")
    return 0
