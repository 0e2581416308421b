"""Benchmark of large frames (issue: pictures and speed, goal ≤ 1.2 GB for 4096 × 3072 × 10).

Renders a textured slope (0 .. 0.9 mm across the frame) seen through a Gaussian defocus
into ``--frames`` JPEG frames of ``--width`` × ``--height`` px, then times what a user
waits for: the whole ``smdinspect -q reconstruct STACK --step-mm 0.1 --out DIR`` command
(imports, reading, writing every default output), one fresh process a run, as medians of
``--repeat`` runs of wall time, CPU time and peak RSS, with the machine's load; once with
the default bands of rows and once with ``--band-mpixels 0`` (whole frames), and the share
of pixels whose reliability differs between the two.

    .venv/bin/python benchmarks/large_frames.py [--width 4096] [--height 3072]
        [--frames 10] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

#: The issue's goal for 4096 × 3072 × 10 frames (bytes).
GOAL_PEAK_BYTES = 1.2e9


def make_stack(root: Path, *, width: int, height: int, frames: int, seed: int = 0) -> list[Path]:
    """JPEG frames of a textured slope, z = 0, 0.1, ... mm; returns their paths."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((height, width), dtype=np.float32), (0, 0), 1.5)
    tex = np.clip(0.5 + 0.18 * (tex - tex.mean()) / tex.std(), 0, 1)
    slope = np.linspace(0.0, 0.9, width, dtype=np.float32)[None, :]  # mm, along x
    levels = np.arange(9, dtype=np.float32)  # blur σ (px) of each pre-blurred copy
    blurred = [tex if s == 0 else cv2.GaussianBlur(tex, (0, 0), float(s)) for s in levels]
    paths = []
    for n in range(frames):
        f = np.clip(np.abs(slope - 0.1 * n) * 40.0, 0, 8) * np.ones((height, 1), np.float32)
        lo = np.floor(f).astype(np.intp)
        t = f - lo
        img = np.zeros((height, width), np.float32)
        for j in range(len(levels)):  # linear between the two nearest blur levels
            img += np.where(lo == j, (1 - t) * blurred[j], 0)
            img += np.where(np.minimum(lo + 1, len(levels) - 1) == j, t * blurred[j], 0)
        img = img * 255 + rng.normal(0, 1.0, img.shape)
        path = root / f"f{n:02d}.jpg"
        cv2.imwrite(str(path), np.clip(img, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 92])
        paths.append(path)
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=4096)
    ap.add_argument("--height", type=int, default=3072)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3, help="whole-command runs (median; default 3)")
    args = ap.parse_args()
    from real_stacks import describe_process, time_process  # this folder

    cli = Path(sys.executable).with_name("smdinspect")
    print(f"large frames: {args.frames} x {args.width}x{args.height} JPEG, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory(prefix="smd-large-") as tmp:
        paths = [str(p) for p in make_stack(Path(tmp), width=args.width, height=args.height,
                                            frames=args.frames)]
        reliable = {}
        for label, extra in (("bands (default)", []), ("whole frames", ["--band-mpixels", "0"])):
            cmd = [str(cli), "-q", "reconstruct", *paths, "--step-mm", "0.1", *extra,
                   "--out", "{tmp}/out"]
            t = time_process(cmd, args.repeat)
            goal = "PASS" if t["peak_mib"] * 2**20 <= GOAL_PEAK_BYTES else "FAIL"
            print(f"{label:>16}: {describe_process(t)}; goal peak <= 1.2 GB: {goal}")
            out = Path(tmp) / label.split()[0]
            cmd[-1] = str(out)
            subprocess.run(cmd, check=True, capture_output=True)
            reliable[label] = cv2.imread(str(out / "confidence.tiff"), cv2.IMREAD_UNCHANGED) >= 0.5
        a, b = reliable.values()
        print(f"reliability differs on {100 * np.mean(a != b):.3f} % of the pixels "
              f"(coverage {100 * a.mean():.1f} % / {100 * b.mean():.1f} %)")


if __name__ == "__main__":
    main()
