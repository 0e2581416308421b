"""Benchmark of `smdinspect batch` (issue 6): boards per minute.

Renders N synthetic demo boards (not timed; default 6 boards, 512 x 512 px at
0.022 mm/px, 40 frames, a few injected defects), then inspects them with
``smdinspect.batch.run_batch`` three ways, each into a fresh report folder:

* the local process pool with 1 worker,
* the local process pool with 2 workers,
* a 2-worker Dask ``LocalCluster`` (127.0.0.1, single-threaded workers).

Wall time includes starting the workers (spawned processes / the cluster), as a user
would see it. Prints one line per executor and checks that all three gave the same
verdicts.

    .venv/bin/python benchmarks/batch.py [--boards 6] [--size 512] [--frames 40]
        [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BOARD = REPO / "references" / "demo_board.json"
DEFECTS = ["", "R1.1:missing", "C2.1:insufficient", "U1.4:bridge", "R3.1:excess",
           "C1.1:tombstone"]


def generate(root: Path, *, n: int, size: int, frames: int, pixel_mm: float) -> None:
    """Render ``n`` boards with ``smdinspect simulate board``, two at a time."""
    procs = []
    for i in range(n):
        out = root / f"board{i:02d}"
        if (out / "stack.json").is_file():
            continue
        cmd = [sys.executable, "-m", "smdinspect", "-q", "simulate", "board",
               "--board", str(BOARD), "--seed", str(i), "--size", str(size),
               "--pixel-size-mm", str(pixel_mm), "--frames", str(frames),
               f"--offset-mm={0.25 * ((i % 3) - 1)},{0.2 * ((i % 2) - 0.5)}",
               f"--rotate-deg={(i % 5) - 2}", "--out", str(out)]
        if DEFECTS[i % len(DEFECTS)]:
            cmd += ["--defects", DEFECTS[i % len(DEFECTS)]]
        procs.append(subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL))
        if len(procs) == 2:
            for p in procs:
                if p.wait() != 0:
                    raise SystemExit("simulate board failed")
            procs = []
    for p in procs:
        if p.wait() != 0:
            raise SystemExit("simulate board failed")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boards", type=int, default=6)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--pixel-size-mm", type=float, default=0.022)
    ap.add_argument("--keep", type=Path, default=None,
                    help="render the boards here and keep them (reused when present)")
    args = ap.parse_args()

    from smdinspect.batch import run_batch

    with tempfile.TemporaryDirectory(prefix="smdinspect-bench-batch-") as tmp:
        stacks = args.keep or Path(tmp) / "stacks"
        t = time.perf_counter()
        generate(stacks, n=args.boards, size=args.size, frames=args.frames,
                 pixel_mm=args.pixel_size_mm)
        print(f"rendered {args.boards} boards ({args.size}x{args.size} px, {args.frames} frames) "
              f"in {time.perf_counter() - t:.1f} s (not timed below)")
        runs = [("process pool, 1 worker", dict(workers=1)),
                ("process pool, 2 workers", dict(workers=2)),
                ("Dask LocalCluster, 2 workers", dict(dask_workers=2))]
        verdicts = {}
        rows = []
        for label, kw in runs:
            out = Path(tmp) / f"reports-{len(rows)}"
            res = run_batch(stacks, BOARD, out, **kw)
            c = res.counts()
            per_board = sum(b.seconds for b in res.boards) / len(res.boards)
            rows.append({"executor": label, "boards": len(res.boards),
                         "seconds": round(res.seconds, 2),
                         "boards_per_minute": round(res.boards_per_minute, 2),
                         "mean_board_s": round(per_board, 2), "counts": c})
            print(f"{label:<30} {len(res.boards)} boards in {res.seconds:6.1f} s  ->  "
                  f"{res.boards_per_minute:5.2f} boards/min  (mean {per_board:.1f} s per board "
                  f"in its worker; ok {c['ok']}, defects {c['defects']}, errors {c['error']})")
            for reason in sorted({b.reason for b in res.boards if b.status.value == "error"}):
                print(f"{'':<30} error: {reason[:150]}")
            verdicts[label] = [(b.stack, b.status.value, b.defects, b.reason) for b in res.boards]
        same = len({json.dumps(v) for v in verdicts.values()}) == 1
        print(f"same verdicts on all three executors: {same}")
        if not same:
            for i, rows_i in enumerate(zip(*verdicts.values())):
                if len({json.dumps(r) for r in rows_i}) > 1:
                    print(f"  differs: {rows_i[0][0]}: "
                          + " | ".join(f"{r[1]} {r[2]}" for r in rows_i))
        print(json.dumps(rows))


if __name__ == "__main__":
    main()
