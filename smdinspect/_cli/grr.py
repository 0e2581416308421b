"""``smdinspect grr``: gauge repeatability and reproducibility from repeated sweeps."""

from __future__ import annotations

import argparse
import csv
import math
import re
from pathlib import Path

_EPILOG = """\
Each STACK is one sweep of the same board, re-placed between sweeps: an inspection
report folder (report.json, as inspect or batch write it; taken as it is, unless
--reinspect for a reconstruction), a stack directory (stack.json; reconstructed and
inspected) or a reconstruction directory (inspected). New inspections go to
OUT/inspections/LABEL/.

Operators (or fixturings, days): --operators A,A,B,B gives one per STACK in order; or
--manifest sweeps.csv with the columns 'stack' and 'operator' (paths relative to the
CSV). Each operator needs the same number of sweeps. Without them all sweeps are one
operator's and only the repeatability is estimated.

Per joint and per package/joint type, for max height, volume and area: mean,
repeatability σ (EV), reproducibility σ (AV, the AIAG ANOVA method), GR&R σ, part
σ (between the joints of a type), %GR&R of the tolerance (6σ_GRR / band width x 100;
only the max height has a band), %GR&R of the study variation, the number of distinct
categories (types) and the AIAG rating: <= 10 % acceptable, 10-30 % marginal, above
unacceptable. Readings of joints judged unreliable in a sweep are left out unless
--include-unreliable. Outputs in --out: grr.csv, grr_values.csv, grr.json, grr.png.

exit codes: 0 every joint's and type's max-height %GR&R of tolerance is at most
--fail-above (default 30 %); 1 some joint or type is above it; 2 bad input (fewer than
2 sweeps, sweeps of different boards, unbalanced operators); 3 the board was not
located in a sweep.
"""


def register(sub: argparse._SubParsersAction) -> None:
    from .reconstruct import add_calibration_argument, add_stack_arguments

    p = sub.add_parser(
        "grr", help="gauge R&R: repeatability and %%GR&R per joint from repeated sweeps",
        description="Gauge repeatability and reproducibility of the joint measurements: "
                    "inspect N sweeps of one board and report, per joint and per "
                    "package/joint type, the repeatability and reproducibility of max "
                    "height, volume and area and the %GR&R against the joint's band.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_stack_arguments(p)
    for action in p._actions:  # the shared stack argument: several sweeps, or a manifest
        if action.dest == "stack":
            action.nargs = "*"
            action.help = ("sweeps of the board: stack, reconstruction or report folders "
                           "(or give --manifest)")
    p.add_argument("--board", required=True, type=Path,
                   help="reference board file (JSON), or a .kicad_pcb / centroid file")
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="folder for grr.csv, grr.json, grr.png and the inspections")
    p.add_argument("--operators", default=None, metavar="LIST",
                   help="operator (fixturing) of each STACK in order, e.g. A,A,B,B")
    p.add_argument("--manifest", type=Path, default=None, metavar="CSV",
                   help="CSV with columns 'stack' and 'operator' instead of STACKs")
    p.add_argument("--fail-above", type=float, default=30.0, metavar="PCT",
                   help="exit 1 when a joint's or type's max-height %%GR&R of tolerance is "
                        "above this (default 30, AIAG's limit; 10 for 'acceptable' only)")
    p.add_argument("--k-sigma", type=float, default=6.0, metavar="K",
                   help="gauge spread in σ for %%GR&R (default 6, AIAG 4th edition; 5.15 "
                        "for the older convention)")
    p.add_argument("--interaction-alpha", type=float, default=0.05, metavar="A",
                   help="pool the part x operator interaction into the error when its "
                        "p-value is above A (default 0.05)")
    p.add_argument("--include-unreliable", action="store_true",
                   help="keep the readings of joints judged unreliable in a sweep")
    p.add_argument("--inspect-config", type=Path, default=None, metavar="JSON",
                   help="JSON file of InspectConfig settings (as for inspect)")
    p.add_argument("--min-reliable-fraction", type=float, default=None,
                   help="as for inspect")
    p.add_argument("--reinspect", action="store_true",
                   help="inspect reconstruction folders again even when they hold a "
                        "report.json (default: take the report as it is)")
    p.add_argument("--html", action="store_true", help="write each sweep's report.html")
    add_calibration_argument(p, "to the sweeps inspected here")
    p.add_argument("--no-chart", action="store_true", help="skip grr.png")
    p.set_defaults(func=run, window_px=None)  # from the pixel size (inspection_window_px)


def _sweeps(args: argparse.Namespace) -> tuple[list[Path], list[str] | None]:
    from ..errors import InputError

    stacks = list(args.stack)
    operators = None
    if args.manifest is not None:
        if stacks:
            raise InputError("give either STACKs or --manifest, not both")
        if args.operators is not None:
            raise InputError("--operators and --manifest exclude each other (the manifest "
                             "names the operators)")
        try:
            with open(args.manifest, newline="", encoding="utf-8-sig") as fh:
                rows = list(csv.DictReader(fh))
        except OSError as exc:
            raise InputError(f"--manifest {args.manifest}: {exc.strerror or exc}") from None
        if not rows or not {"stack", "operator"} <= set(rows[0]):
            raise InputError(f"--manifest {args.manifest} needs the columns 'stack' and "
                             "'operator' and one row per sweep")
        for n, r in enumerate(rows, start=2):
            if not (r.get("stack") or "").strip() or not (r.get("operator") or "").strip():
                raise InputError(f"--manifest {args.manifest} line {n}: empty stack or operator")
        base = args.manifest.parent
        stacks = [base / r["stack"].strip() for r in rows]
        operators = [r["operator"].strip() for r in rows]
    elif args.operators is not None:
        operators = [o.strip() for o in args.operators.split(",")]
        if len(operators) != len(stacks) or not all(operators):
            raise InputError(f"--operators must name one operator per STACK ({len(stacks)}); "
                             f"got {args.operators!r}")
    if len(stacks) < 2:
        raise InputError(f"a gauge R&R study needs at least 2 sweeps of the board; got "
                         f"{len(stacks)}")
    return stacks, operators


def run(args: argparse.Namespace) -> int:
    from ..cad import load_any_board
    from ..cli import progress_callback
    from ..errors import InputError
    from ..grr import analyse_grr, inspect_for_grr, read_records, write_grr
    from ..pipeline import inspection_focus_config, stack_pixel_size
    from .inspect import inspect_config_from
    from .reconstruct import check_calibration_argument, focus_config_from

    if args.step_mm is not None or args.z_from_name is not None:
        raise InputError("--step-mm and --z-from-name are not used by grr: give stack folders "
                         "with stack.json")
    if not (math.isfinite(args.fail_above) and args.fail_above > 0):
        raise InputError(f"--fail-above must be > 0 (percent); got {args.fail_above}")
    stacks, operators = _sweeps(args)
    board = load_any_board(args.board)
    check_calibration_argument(args)
    pixel = args.pixel_size_mm
    if pixel is None and stacks:  # the sweeps' rig: the first one's stack.json
        pixel = stack_pixel_size(stacks[0])
    focus = focus_config_from(args, inspection_focus_config(pixel))
    config = inspect_config_from(args)
    found = inspect_for_grr(stacks, board, args.out, focus_config=focus, inspect_config=config,
                            pixel_size_mm=args.pixel_size_mm, html=args.html,
                            reinspect=args.reinspect, calibration=args.calibration,
                            progress=progress_callback(args, "sweeps", unit="sweep"),
                            frame_progress=lambda label: progress_callback(args, label))
    records = read_records(found, operators=operators)
    study = analyse_grr(records, board_name=board.name,
                        joint_ids=[j.id for j in board.joints()],
                        include_unreliable=args.include_unreliable, k_sigma=args.k_sigma,
                        interaction_alpha=args.interaction_alpha)
    written = write_grr(study, args.out, max_pct=args.fail_above, chart=not args.no_chart)
    failing = study.failing(args.fail_above)
    _print_summary(study, args)
    if failing:
        print(f"{len(failing)} joint(s)/type(s) with max-height %GR&R above "
              f"{args.fail_above:g} %: " + ", ".join(
                  f"{r.key} {r.gauge.pct_tolerance:.1f} %" for r in failing[:8])
              + (" ..." if len(failing) > 8 else ""))
    chart = f"  chart: {written['grr.png']}" if "grr.png" in written else ""
    print(f"grr: {written['grr.csv']}{chart}")
    return 1 if failing else 0


def _um(v: float) -> str:
    return f"{1000 * v:.1f}" if math.isfinite(v) else "-"


def _pct(v: float) -> str:
    return f"{v:.1f}" if math.isfinite(v) else "-"


def _print_summary(study, args: argparse.Namespace) -> None:
    ops = study.operators
    print(f"{len(study.records)} sweeps of {study.board_name}, {len(ops)} operator(s)"
          f"{' (' + ', '.join(ops) + ')' if len(ops) > 1 else ''}; max joint height, "
          f"%GR&R = {study.k_sigma:g}σ_GRR / band width:")
    head = (f"  {'package/joint type':28s} {'joints':>6s} {'σ_rep µm':>9s} {'σ_repro µm':>10s} "
            f"{'%GR&R':>6s} {'%SV':>6s} {'ndc':>4s}  rating")
    print(head)
    for r in study.rows:
        if r.scope != "type" or r.metric != "max_height_mm":
            continue
        g = r.gauge
        ndc = f"{g.ndc:.0f}" if math.isfinite(g.ndc) else "-"
        print(f"  {r.key:28s} {r.n_joints:6d} {_um(g.sigma_repeatability):>9s} "
              f"{_um(g.sigma_reproducibility):>10s} {_pct(g.pct_tolerance):>6s} "
              f"{_pct(g.pct_study):>6s} {ndc:>4s}  {r.rating}")
    joints = sorted((r for r in study.rows if r.scope == "joint" and r.metric == "max_height_mm"
                     and math.isfinite(r.gauge.pct_tolerance)),
                    key=lambda r: -r.gauge.pct_tolerance)
    if joints:
        print("  worst joints: " + ", ".join(
            f"{r.key} {r.gauge.pct_tolerance:.1f} % ({r.rating})" for r in joints[:5]))
    short = [r.key for r in study.rows if r.scope == "joint" and r.metric == "max_height_mm"
             and not math.isfinite(r.gauge.pct_tolerance)]
    if short:
        print("  no %GR&R (fewer than 2 reliable readings):")
        for key in short[:10]:
            print(f"    {key}: {_why_unread(study, key)}")
        if len(short) > 10:
            print(f"    ... and {len(short) - 10} more")


def _why_unread(study, joint_id: str) -> str:
    """How often a joint was `unreliable` over the sweeps, and why (the first such sweep's
    reason, up to its first clause)."""
    reasons = [str(j.get("reason", "")) for r in study.records for j in r.joints
               if j.get("id") == joint_id and j.get("verdict") == "unreliable"]
    n = len(study.records)
    if not reasons:
        unread = int(sum(not math.isfinite(v) for v in study.values["max_height_mm"][joint_id]))
        return f"no max height read in {unread} of {n} sweeps"
    first = re.split(r": |; ", reasons[0], maxsplit=1)[0]
    return f"unreliable in {len(reasons)} of {n} sweeps: {first}"
