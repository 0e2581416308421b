"""Benchmark of `smdinspect.sff.reconstruct` (issue: SFF core).

Prints, for a 40-frame and an 80-frame 1024x1024 8-bit PNG stack of a textured cone:
end-to-end Mpixel/s (decode included), peak resident memory of a fresh process, and
the ratio of the total time to the time needed just to decode the frames (with the same
number of threads).

    .venv/bin/python benchmarks/reconstruct.py [--size 1024] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
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
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]))
        return
    print(f"smdinspect reconstruct benchmark: {args.size}x{args.size} 8-bit PNG, "
          f"{args.workers} worker threads, best of 3 runs each")
    print(f"{'frames':>6} {'decode s':>9} {'total s':>8} {'Mpixel/s':>9} {'total/decode':>12} {'peak MiB':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        for n in (40, 80):
            root = Path(tmp) / f"cone{n}"
            make_stack(root, n_frames=n, size=args.size)
            out = subprocess.run([sys.executable, __file__, "--child", str(root), str(args.workers)],
                                 check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1])
            print(f"{r['frames']:>6} {r['decode_s']:>9.3f} {r['total_s']:>8.3f} "
                  f"{r['mpixel_per_s']:>9.1f} {r['ratio']:>12.2f} {r['peak_mib']:>9.0f}")


if __name__ == "__main__":
    main()
