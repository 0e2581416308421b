"""Benchmark of `smdinspect.sff.reconstruct` (issue: SFF core).

Prints, for 1024x1024 8-bit PNG stacks of a textured cone (40 and 80 frames by default):
end-to-end Mpixel/s of ``reconstruct()`` (decode included, best of 3 in one process),
the ratio of that time to the time needed just to decode the frames (with the same
number of threads), and the marginal throughput between the two frame counts; then what
users wait for: the whole ``smdinspect reconstruct`` command (imports, reading,
writing every default output), one fresh process a run, as medians of ``--repeat``
runs of wall time, CPU time and peak RSS, with the machine's load.

    .venv/bin/python benchmarks/reconstruct.py [--size 1024] [--workers 2]
        [--frames 40,80] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np


def make_stack(root: Path, *, n_frames: int, size: int, seed: int = 0) -> None:
    """A textured cone seen through a Gaussian defocus that grows with |h - z|."""
    from smdinspect.stack import StackWriter

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((size, size), dtype=np.float32), (0, 0), 1.2)
    tex = np.clip(0.5 + 0.18 * (tex - tex.mean()) / tex.std(), 0, 1)
    yy, xx = np.mgrid[:size, :size] - size / 2
    height = np.clip(1.6 * (1 - np.hypot(xx, yy) / (0.45 * size)), 0, None).astype(np.float32)
    step = 1.75 / n_frames
    levels = np.linspace(0, 8, 17)
    blurred = np.stack([tex if s == 0 else cv2.GaussianBlur(tex, (0, 0), float(s)) for s in levels])
    writer = StackWriter(root, pixel_size_mm=0.01)
    for n in range(n_frames):
        z = -0.05 + n * step
        f = np.clip(np.abs(height - z) * 14.0, 0, 8) / (levels[1] - levels[0])
        lo = np.floor(f).astype(np.intp)
        hi = np.minimum(lo + 1, len(levels) - 1)
        t = (f - lo).astype(np.float32)
        img = (1 - t) * np.take_along_axis(blurred, lo[None], 0)[0] + t * np.take_along_axis(blurred, hi[None], 0)[0]
        img = img * 255 + rng.normal(0, 1.0, img.shape)
        writer.add_frame(np.clip(img, 0, 255).astype(np.uint8), z)


def child(stack_dir: str, workers: int) -> None:
    """Run in a fresh process: decode-only time, reconstruct time, peak RSS."""
    from smdinspect.sff import FocusConfig, reconstruct
    from smdinspect.stack import FocalStack, read_image

    stack = FocalStack.open(stack_dir)
    paths = [f.path for f in stack.frames]
    read_image(paths[0])  # warm up imports and the page cache
    decode = []
    with ThreadPoolExecutor(workers) as pool:
        for _ in range(3):
            t = time.perf_counter()
            for _ in pool.map(read_image, paths):
                pass
            decode.append(time.perf_counter() - t)
    decode_s = min(decode)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        surface = reconstruct(stack, FocusConfig(workers=workers))
        times.append(time.perf_counter() - t)
    total_s = min(times)
    h, w = surface.shape
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"frames": len(stack), "size": [w, h], "decode_s": decode_s,
                      "total_s": total_s, "mpixel_per_s": len(stack) * h * w / 1e6 / total_s,
                      "ratio": total_s / decode_s, "peak_mib": peak_mib,
                      "coverage": surface.coverage}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--frames", default="40,80", help="frame counts (default %(default)s)")
    ap.add_argument("--repeat", type=int, default=5, help="whole-command runs (median; default 5)")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]))
        return
    from real_stacks import describe_process, time_process  # this folder

    counts = [int(x) for x in args.frames.split(",") if x.strip()]
    print(f"smdinspect reconstruct benchmark: {args.size}x{args.size} 8-bit PNG, "
          f"{args.workers} worker threads; load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs")
    print("reconstruct() in one process, best of 3 runs each:")
    print(f"{'frames':>6} {'decode s':>9} {'total s':>8} {'Mpixel/s':>9} {'total/decode':>12} {'peak MiB':>9}")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            root = Path(tmp) / f"cone{n}"
            make_stack(root, n_frames=n, size=args.size)
            out = subprocess.run([sys.executable, __file__, "--child", str(root), str(args.workers)],
                                 check=True, capture_output=True, text=True).stdout
            r = rows[n] = json.loads(out.strip().splitlines()[-1])
            print(f"{r['frames']:>6} {r['decode_s']:>9.3f} {r['total_s']:>8.3f} "
                  f"{r['mpixel_per_s']:>9.1f} {r['ratio']:>12.2f} {r['peak_mib']:>9.0f}")
        if len(counts) > 1:
            a, b = counts[0], counts[-1]
            dt = rows[b]["total_s"] - rows[a]["total_s"]
            marginal = (b - a) * args.size**2 / 1e6 / dt if dt > 0 else float("inf")
            dec = (rows[b]["decode_s"] - rows[a]["decode_s"]) / (b - a)
            print(f"marginal {a}->{b} frames: {marginal:.1f} Mpixel/s, "
                  f"{1e3 * dt / (b - a):.1f} ms/frame (decode {1e3 * dec:.1f} ms/frame)")
        cli = Path(sys.executable).with_name("smdinspect")
        print(f"whole command `smdinspect -q reconstruct STACK --workers {args.workers} --out DIR`:")
        for n in counts:
            t = time_process([str(cli), "-q", "reconstruct", str(Path(tmp) / f"cone{n}"),
                              "--workers", str(args.workers), "--out", "{tmp}/out"], args.repeat)
            print(f"{n:>6} frames: {describe_process(t)}")


if __name__ == "__main__":
    main()
