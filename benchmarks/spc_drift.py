"""SPC through the whole pipeline: a simulated batch with a slow drift in one joint.

Renders ``--boards`` demo boards (each re-placed by its seed, sensor noise drawn anew)
in which one chip joint's fillet height stays at the nominal for the first
``--stable`` boards and then sinks by ``--drift`` of the band minimum per board, until
it falls below the band. Every board is reconstructed and inspected as the CLI would,
then SPC runs over the reports (the same code as ``smdinspect spc``) and prints, next
to the issue's goal (flag the drift at least 3 boards before the joint leaves its
band):

* the board at which the drifting joint's max-height series first trips a run rule;
* the first board whose *true* fillet is below the band minimum (and the first whose
  measured height is);
* how many other joints' series were flagged (false alarms of the eight rules).

Control limits come from the first ``--stable`` boards (a known-good period).

    .venv/bin/python benchmarks/spc_drift.py [--boards 20] [--joint R1.1] [--out DIR]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from smdinspect.inspect import analyse_reports, load_board
from smdinspect.optics import Optics
from smdinspect.pipeline import inspect_stack
from smdinspect.synth import board_scene, render_stack

ROOT = Path(__file__).resolve().parents[1]
BOARD = ROOT / "references" / "demo_board.json"
STEP = 0.05


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--boards", type=int, default=20)
    p.add_argument("--stable", type=int, default=6, help="boards before the drift starts")
    p.add_argument("--drift", type=float, default=0.12,
                   help="fillet loss per board, as a fraction of the band minimum")
    p.add_argument("--joint", default="R1.1")
    p.add_argument("--out", type=Path, default=None, help="keep the reports here")
    args = p.parse_args(argv)

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="smdinspect-spc-drift-") as tmp:
        root = args.out or Path(tmp)
        reports, true_frac = [], []
        joint = load_board(BOARD).joint(args.joint)
        lo = joint.min_height_mm
        nominal_frac = joint.nominal_height_mm / lo  # the fillet in band minima
        for k in range(args.boards):
            seed = 10_500 + k  # test seeds
            frac = nominal_frac - max(0, k - args.stable + 1) * args.drift
            scene, labels = board_scene(BOARD, defects={args.joint: "insufficient"},
                                        params={args.joint: {"fraction": frac}},
                                        pixel_size_mm=0.02, seed=seed)
            top = float(scene.height_mm.max())
            z = np.round(np.arange(-3 * STEP, top + 3 * STEP, STEP) - 0.0123, 6)[::-1]
            stack = render_stack(scene, z, optics=Optics.for_pixel_size(0.02), seed=seed,
                                 out=root / f"stack{k:02d}", previews=False)
            out = root / f"board{k:02d}"
            inspect_stack(stack, BOARD, out, html=False)
            reports.append(out)
            true_frac.append(frac)
            print(f"board {k + 1:2d}: true fillet {frac:.2f} x band minimum", flush=True)
        # control limits from the known-good boards (a drift inside the default baseline,
        # the first half, would move the centre line)
        analysis = analyse_reports(reports, order="given", baseline=args.stable)
        series = analysis.get("joint", args.joint, "max_height_mm")
        hits = sorted(h.index for h in series.chart.hits)
        early = [i for i in hits if i < args.stable]  # before the drift: false alarms
        first_flag = next((i for i in hits if i >= args.stable), None)
        first_true_out = next((k for k, f in enumerate(true_frac) if f < 1.0), None)
        measured = series.values
        first_measured_out = next((k for k, v in enumerate(measured) if np.isfinite(v) and v < lo),
                                  None)
        others = [s for s in analysis.flagged() if s.scope == "joint" and s.key != args.joint
                  and s.metric == "max_height_mm"]
        elapsed = time.perf_counter() - t0
    lead = None if first_flag is None or first_true_out is None else first_true_out - first_flag
    one = lambda k: "never" if k is None else f"board {k + 1}"  # noqa: E731
    print(f"\n{args.boards} boards, {args.joint} drifting from board {args.stable + 1}, "
          f"{elapsed:.0f} s")
    rule = next((h.rule for h in series.chart.hits if h.index == first_flag), None)
    print(f"  first run-rule hit on {args.joint} max height after the drift starts: "
          f"{one(first_flag)}" + (f" (rule {rule})" if rule else "")
          + (f"; hits before it (false): {', '.join(str(i + 1) for i in early)}" if early else ""))
    print(f"  true fillet below the band minimum from:   {one(first_true_out)}")
    print(f"  measured max height below the band from:   {one(first_measured_out)}")
    ok = lead is not None and lead >= 3
    print(f"  lead: {lead if lead is not None else '-'} boards      goal >= 3   {'PASS' if ok else 'FAIL'}")
    print(f"  other joints' max-height series flagged: {len(others)} of "
          f"{sum(1 for s in analysis.series if s.scope == 'joint' and s.metric == 'max_height_mm') - 1}"
          + (f" ({', '.join(s.key for s in others)})" if others else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
