"""Time every focus measure operator on one 1024x1024 frame.

Run from the repository root::

    .venv/bin/python benchmarks/focus.py [--size 1024] [--window 9] [--runs 20]

Prints the median and best milliseconds per frame of ``focus_measure`` for each operator
(float32 input), then the ``sml`` hot path for uint8 input (including the conversion).
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np

from smdinspect.sff._focus import OPERATORS, FocusOperator, focus_measure


def _time_ms(fn, runs: int) -> tuple[float, float]:
    for _ in range(3):  # warm-up: caches, page faults, OpenCV thread pool
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), min(times)


def _frame(size: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 1.0, (size, size)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 1.0)
    return np.clip(128.0 + 40.0 * tex / tex.std(), 0, 255).astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024, help="frame side in px")
    ap.add_argument("--window", type=int, default=9, help="window_px")
    ap.add_argument("--runs", type=int, default=20, help="timed runs per operator")
    ap.add_argument("--threads", type=int, default=None, help="cv2.setNumThreads")
    args = ap.parse_args(argv)
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
    f32 = _frame(args.size)
    u8 = f32.astype(np.uint8)
    print(f"{args.size}x{args.size} frame, window {args.window} px, {args.runs} runs, "
          f"OpenCV {cv2.__version__} with {cv2.getNumThreads()} threads")
    print(f"{'operator':8s} {'family':13s} {'median ms':>9s} {'best ms':>8s}")
    order = ["sml"] + [op for op in OPERATORS if op != "sml"]
    for op in order:
        med, best = _time_ms(lambda: focus_measure(f32, operator=op, window_px=args.window),
                             args.runs)
        print(f"{op:8s} {FocusOperator(op).family:13s} {med:9.2f} {best:8.2f}")
    print()
    med, best = _time_ms(lambda: focus_measure(u8, window_px=args.window), args.runs)
    print(f"sml, uint8 input (includes the conversion)   {med:6.2f} ms median, {best:.2f} best")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
