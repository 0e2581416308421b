"""``smdinspect simulate``: render a synthetic focal stack with its ground truth."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

SCENES = ("cone", "staircase", "plane", "halftex", "step", "board")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="render a synthetic focal stack (cone, staircase, plane, halftex, step, board)",
        description=(
            "Render a focal stack of a known scene through the thin-lens optics and a noisy "
            "sensor. Writes frames + stack.json to OUT and the ground truth to OUT/truth/ "
            "(height_mm.tiff/.npy, scene.json, PNG previews; labels.json for boards)."
        ),
    )
    p.add_argument("scene", choices=SCENES, help="what to render")
    p.add_argument("--out", required=True, type=Path, help="stack directory to write")
    p.add_argument("--force", action="store_true", help="overwrite a stack already in OUT")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--noise-seed", type=int, default=None, metavar="N",
                   help="seed of the sensor noise alone (default: --seed); the same --seed with "
                        "another --noise-seed is the same scene swept again")
    p.add_argument("--size", type=int, default=None, metavar="PX",
                   help="image side in pixels (default 256; boards: fit the board)")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="number of frames (default: cover the scene's heights)")
    p.add_argument("--step-mm", type=float, default=0.05, metavar="S",
                   help="focus step Δd between frames (default 0.05)")
    p.add_argument("--z-range-mm", default=None, metavar="LO,HI",
                   help="lowest and highest focus height (default: 3 steps beyond the "
                        "scene's lowest and highest point); write a negative LO as "
                        "--z-range-mm=-0.2,1.8")
    p.add_argument("--pixel-size-mm", type=float, default=0.015, metavar="P",
                   help="object pixel size (default 0.015)")
    p.add_argument("--bit-depth", type=int, choices=(8, 16), default=8)
    p.add_argument("--noise", default="normal", choices=("off", "low", "normal", "high"),
                   help="sensor noise level (default normal: shot + read noise, ±1%% flicker)")
    p.add_argument("--jitter-px", type=float, default=None,
                   help="RMS lateral jitter per frame in pixels (default 0)")
    p.add_argument("--lens", default="telecentric", choices=("telecentric", "ordinary"),
                   help="ordinary lenses change magnification with height (default telecentric)")
    p.add_argument("--color", action="store_true",
                   help="RGB frames for the test scenes (boards are always RGB)")
    p.add_argument("--stage-scale", type=float, default=1.0, metavar="S",
                   help="a stage whose real step is S times the one it records (default 1): "
                        "try `smdinspect calibrate z-scale` on it")
    p.add_argument("--block-mm", type=float, default=None, metavar="H",
                   help="'step': the block's height (default 0.4)")
    g = p.add_argument_group("board")
    g.add_argument("--board", type=Path, default=None,
                   help="reference board file (default references/demo_board.json)")
    g.add_argument("--defects", default="",
                   help="defects to inject, e.g. R3.1:insufficient,U1.4:bridge")
    g.add_argument("--offset-mm", default=None, metavar="X,Y",
                   help="board offset from the image centre (default: random within ±2 mm); "
                        "write negative values as --offset-mm=-1,0.5")
    g.add_argument("--rotate-deg", type=float, default=None,
                   help="board rotation (default: random within ±5°)")
    g.add_argument("--fillet-curvature", default=None, metavar="LO,HI",
                   help="chip fillets as circular arcs (constant curvature, what surface "
                        "tension makes), each joint's curvature drawn in [LO, HI] (0: a "
                        "straight wedge, 1: the most curved arc; e.g. 0.5,1); default: "
                        "parabolic fillets")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import progress_callback
    from ..optics import Optics
    from ..synth import SensorConfig, render_stack

    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise InputError(f"--out {out} is not empty; pass --force to overwrite it")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0; got {args.seed}")
    if args.noise_seed is not None and args.noise_seed < 0:
        raise InputError(f"--noise-seed must be >= 0; got {args.noise_seed}")
    _positive(args.step_mm, "--step-mm")
    _positive(args.pixel_size_mm, "--pixel-size-mm")
    if args.size is not None and args.size < 16:
        raise InputError(f"--size must be >= 16 pixels; got {args.size}")
    _positive(args.stage_scale, "--stage-scale")
    if args.block_mm is not None:
        if args.scene != "step":
            raise InputError("--block-mm is only for 'simulate step'")
        _positive(args.block_mm, "--block-mm")
    if args.scene != "board":
        for name in ("board", "offset_mm", "rotate_deg", "fillet_curvature"):
            if getattr(args, name) is not None:
                raise InputError(f"--{name.replace('_', '-')} is only for 'simulate board'")
        if args.defects:
            raise InputError("--defects is only for 'simulate board'")

    scene, labels = _build_scene(args)
    optics = Optics.for_pixel_size(args.pixel_size_mm, telecentric=args.lens == "telecentric")
    overrides: dict[str, Any] = {"bit_depth": args.bit_depth}
    if args.jitter_px is not None:
        overrides["jitter_px"] = _non_negative(args.jitter_px, "--jitter-px")
    sensor = SensorConfig.preset(args.noise, **overrides)
    z = sweep_heights(scene.height_range_mm(), step_mm=args.step_mm, frames=args.frames,
                      z_range=_pair(args.z_range_mm, "--z-range-mm"))
    extra = None
    if labels is not None:
        extra = {"labels": "labels.json"}
    log.info("rendering %s: %dx%d px, %d frames, z %.3f..%.3f mm", scene.name,
             scene.shape[1], scene.shape[0], len(z), z.min(), z.max())
    noise_seed = args.seed if args.noise_seed is None else args.noise_seed
    stack = render_stack(scene, z, optics=optics, sensor=sensor, seed=noise_seed, out=out,
                         progress=progress_callback(args, f"simulate {args.scene}"),
                         overwrite=args.force, truth_extra=extra, stage_scale=args.stage_scale)
    if labels is not None:
        from .. import _atomic

        _atomic.write_json(out / "truth" / "labels.json", labels)
    print(f"wrote {len(stack)} frames of '{scene.name}' ({scene.shape[1]}x{scene.shape[0]} px, "
          f"z {z.min():.3f}..{z.max():.3f} mm, step {stack.step_mm:.3f} mm) to {out}/; "
          f"ground truth in {out / 'truth'}/")
    return 0


def sweep_heights(height_range_mm, *, step_mm: float, frames: int | None = None,
                  z_range: tuple[float, float] | None = None,
                  margin_steps: int = 3) -> np.ndarray:
    """Focus heights of a simulated sweep, highest first (the camera moves down by Δd).

    Default: from ``margin_steps`` steps below the lowest point of the scene to
    ``margin_steps`` steps above its highest point. ``frames`` centres that many frames on
    the scene when they span it; when they do not, they start ``margin_steps`` below its
    lowest point (the board must stay in range; the tops of tall parts are cut off).
    ``z_range`` with ``frames`` sets the step.
    """
    from ..acquire import MAX_FRAMES

    lo, hi = height_range_mm
    step = float(step_mm)
    if frames is not None and frames < 3:
        raise InputError(f"--frames must be >= 3; got {frames}")
    span = (z_range[1] - z_range[0]) if z_range is not None else hi - lo + 2 * margin_steps * step
    planned = frames if frames is not None else span / step + 1
    if not planned <= MAX_FRAMES:
        raise InputError(f"the sweep would take {planned:,.0f} frames, more than {MAX_FRAMES} "
                         "(check --step-mm or --frames)")
    if z_range is not None:
        zlo, zhi = z_range
        if zhi <= zlo:
            raise InputError(f"--z-range-mm needs LO < HI; got {zlo},{zhi}")
        if frames is not None:
            return np.linspace(zhi, zlo, frames)
        n = int(math.floor((zhi - zlo) / step + 1e-9)) + 1
        if n < 3:
            raise InputError(f"--z-range-mm {zlo},{zhi} holds fewer than 3 steps of {step} mm")
        return zhi - step * np.arange(n)
    if frames is None:
        zlo, zhi = lo - margin_steps * step, hi + margin_steps * step
        n = int(math.ceil((zhi - zlo) / step - 1e-9)) + 1
    else:
        n = int(frames)
    if (n - 1) * step >= hi - lo + 2 * margin_steps * step:
        top = 0.5 * (lo + hi) + 0.5 * (n - 1) * step
    else:
        top = lo - margin_steps * step + (n - 1) * step
    z = top - step * np.arange(n)
    return np.round(z, 9)


def _build_scene(args: argparse.Namespace):
    from .. import synth

    common = dict(pixel_size_mm=args.pixel_size_mm, seed=args.seed)
    size = 256 if args.size is None else args.size
    if args.scene == "cone":
        return synth.cone_scene(size_px=size, color=args.color, **common), None
    if args.scene == "staircase":
        return synth.staircase_scene(size_px=size, color=args.color, **common), None
    if args.scene == "plane":
        return synth.slanted_plane_scene(size_px=size, color=args.color, **common), None
    if args.scene == "halftex":
        return synth.half_textured_scene(size_px=size, color=args.color, **common), None
    if args.scene == "step":
        block = 0.4 if args.block_mm is None else args.block_mm
        return synth.step_target_scene(size_px=size, color=args.color, block_mm=block,
                                       **common), None
    return _board_scene(args)


def _board_scene(args: argparse.Namespace):
    from ..demo import demo_board_path
    from ..inspect import load_board
    from ..synth import board_scene, parse_defects

    board = load_board(args.board if args.board is not None else demo_board_path())
    defects = parse_defects(args.defects, board=board) if args.defects else {}
    offset = _pair(args.offset_mm, "--offset-mm")
    shape = None if args.size is None else (args.size, args.size)
    scene, labels = board_scene(board, defects=defects, pixel_size_mm=args.pixel_size_mm,
                                shape=shape, offset_mm=offset, rotate_deg=args.rotate_deg,
                                seed=args.seed,
                                fillet_curvature=_pair(args.fillet_curvature,
                                                       "--fillet-curvature"))
    outside = [j["id"] for j in labels["joints"] if not j.get("in_view", True)]
    if outside:
        h, w = scene.shape
        log.warning("%d of %d joints lie outside the rendered %dx%d px (%.1f x %.1f mm): %s; "
                    "leave out --size to render the whole board", len(outside),
                    len(labels["joints"]), w, h, w * args.pixel_size_mm, h * args.pixel_size_mm,
                    ", ".join(outside[:6]) + (", ..." if len(outside) > 6 else ""))
    return scene, labels


def _pair(text: str | None, name: str) -> tuple[float, float] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        a, b = (float(v) for v in parts)
    except ValueError:
        raise InputError(f"{name} must be two numbers like 0.5,-1.2; got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputError(f"{name} must be finite; got {text!r}")
    return a, b


def _positive(v: float, name: str) -> float:
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be > 0; got {v}")
    return v


def _non_negative(v: float, name: str) -> float:
    if not (math.isfinite(v) and v >= 0):
        raise InputError(f"{name} must be >= 0; got {v}")
    return v
