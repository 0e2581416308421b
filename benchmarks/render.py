"""Time rendering a 40-frame 1024x1024 synthetic board stack.

Run from the repository root::

    .venv/bin/python benchmarks/render.py [--size 1024] [--frames 40] [--scene board|cone]

Prints the seconds to build the scene, to render the frames in memory (optics + sensor,
the first frame includes the one-off shading and layer set-up), and to write the same
stack to disk with ``render_stack`` (PNG frames, stack.json, truth/ with previews), and
frames per second. The board is ``references/demo_board.json`` with two defects; with
``--scene cone`` a colour cone of the same size.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from smdinspect.optics import Optics
from smdinspect.synth import (
    SensorConfig,
    board_scene,
    cone_scene,
    render_frame,
    render_stack,
)

ROOT = Path(__file__).resolve().parents[1]


def _scene(kind: str, size: int):
    if kind == "board":
        scene, _ = board_scene(ROOT / "references" / "demo_board.json",
                               defects={"R1.1": "insufficient", "U1.4": "bridge"},
                               shape=(size, size), seed=7)
        return scene
    return cone_scene(size_px=size, color=True, seed=7)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024, help="image side in px")
    ap.add_argument("--frames", type=int, default=40, help="frames in the stack")
    ap.add_argument("--scene", choices=("board", "cone"), default="board")
    ap.add_argument("--step-mm", type=float, default=0.05)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    scene = _scene(args.scene, args.size)
    t_scene = time.perf_counter() - t0
    lo, hi = scene.height_range_mm()
    mid = 0.5 * (lo + hi)
    z = mid + (np.arange(args.frames)[::-1] - (args.frames - 1) / 2) * args.step_mm
    optics = Optics.for_pixel_size(scene.pixel_size_mm)
    sensor = SensorConfig()
    print(f"scene '{scene.name}' {scene.shape[1]}x{scene.shape[0]} px "
          f"{'RGB' if scene.is_color else 'grey'}, heights {lo:.3f}..{hi:.3f} mm; "
          f"{args.frames} frames z {z.min():.3f}..{z.max():.3f} mm; OpenCV "
          f"{cv2.__version__} with {cv2.getNumThreads()} threads")
    print(f"build scene:           {t_scene:7.2f} s")

    t0 = time.perf_counter()
    first = None
    for zi in z:
        render_frame(scene, float(zi), optics=optics, sensor=sensor, rng=0)
        if first is None:
            first = time.perf_counter() - t0
    t_mem = time.perf_counter() - t0
    print(f"render in memory:      {t_mem:7.2f} s  ({args.frames / t_mem:5.2f} frames/s; "
          f"first frame {first:.2f} s incl. set-up)")

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        render_stack(scene, z, optics=optics, sensor=sensor, seed=0, out=Path(tmp) / "s")
        t_disk = time.perf_counter() - t0
    print(f"render_stack to disk:  {t_disk:7.2f} s  ({args.frames / t_disk:5.2f} frames/s; "
          f"PNG frames + truth/ + previews)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
