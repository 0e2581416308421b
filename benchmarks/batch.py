"""Benchmark of `smdinspect batch` (issue 6): boards per minute.

Renders N synthetic demo boards (not timed; default 6 boards, 512 x 512 px at
0.022 mm/px, 40 frames, a few injected defects), then inspects them with
``smdinspect.batch.run_batch`` three ways, each into a fresh report folder:

* the local process pool with 1 worker,
* the local process pool with 2 workers,
* a 2-worker Dask ``LocalCluster`` (127.0.0.1, single-threaded workers),

then reruns the last report folder, where every finished board is unchanged and skipped.

Wall time includes starting the workers (spawned processes / the cluster), as a user
would see it. Prints one line per executor (median over ``--repeat`` runs) and checks
that every run gave the same verdicts.

    .venv/bin/python benchmarks/batch.py [--boards 6] [--size 512] [--frames 40]
        [--repeat 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import statistics
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
            _wait(procs)
            procs = []
    _wait(procs)


def _wait(procs) -> None:
    if any(p.wait() != 0 for p in procs):
        raise SystemExit("simulate board failed")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boards", type=int, default=6)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--pixel-size-mm", type=float, default=0.022)
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs per executor; the median wall time is reported")
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
        verdicts: dict[str, set[str]] = {label: set() for label, _ in runs}
        times: dict[str, list[float]] = {label: [] for label, _ in runs}
        last = {}
        n_out = 0
        for _ in range(args.repeat):  # round-robin: a busy spell hits every executor
            for label, kw in runs:
                n_out += 1
                res = run_batch(stacks, BOARD, Path(tmp) / f"reports-{n_out}", **kw)
                times[label].append(res.seconds)
                last[label] = res
                verdicts[label].add(json.dumps(
                    [(b.stack, b.status.value, b.defects, b.reason) for b in res.boards]))
        rows = []
        for label, _ in runs:
            res = last[label]
            seconds = statistics.median(times[label])
            c = res.counts()
            per_board = sum(b.seconds for b in res.boards) / len(res.boards)
            bpm = 60.0 * len(res.boards) / seconds
            rows.append({"executor": label, "boards": len(res.boards),
                         "seconds": [round(t, 2) for t in times[label]],
                         "boards_per_minute": round(bpm, 2), "counts": c})
            print(f"{label:<30} {len(res.boards)} boards in {seconds:6.1f} s  ->  "
                  f"{bpm:5.2f} boards/min  (median of {len(times[label])}; last run: mean "
                  f"{per_board:.1f} s per board in its worker; ok {c['ok']}, defects "
                  f"{c['defects']}, errors {c['error']})")
            for reason in sorted({b.reason for b in res.boards if b.status.value == "error"}):
                print(f"{'':<30} error: {reason[:150]}")
        # a rerun over finished reports: every board unchanged, so skipped
        skip_times = []
        for _ in range(args.repeat):
            res = run_batch(stacks, BOARD, Path(tmp) / f"reports-{n_out}", workers=2)
            skip_times.append(res.seconds)
        print(f"{'rerun over finished reports':<30} {len(res.boards)} boards in "
              f"{statistics.median(skip_times):6.1f} s (median of {len(skip_times)}; "
              f"{res.counts()['skipped']} unchanged and skipped, failed boards are retried)")
        distinct = set().union(*verdicts.values())
        print(f"same verdicts in every run: {len(distinct) == 1}")
        if len(distinct) > 1:
            for label, v in verdicts.items():
                for doc in sorted(v):
                    print(f"  {label}: " + "; ".join(f"{r[0]} {r[1]} {r[2]}"
                                                     for r in json.loads(doc)))
        print(json.dumps(rows))


if __name__ == "__main__":
    main()
