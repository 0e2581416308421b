"""``smdinspect spc``: statistical process control across inspected boards."""

from __future__ import annotations

import argparse
from pathlib import Path

_EPILOG = """\
Each REPORT_DIR is a board's report folder (holding report.json, as written by
`smdinspect inspect` or `batch`) or a folder searched for them (e.g. a batch's
REPORTS_DIR). Series: every joint, and every package/joint type, for max height, volume
and area. Outputs in --out: spc.csv (mean, sigma, Cp/Cpk against the joint's band,
control limits, the run rules that fired), spc_flags.csv, spc_values.csv,
charts/*.png and spc.html.

exit codes: 0 no run rule fired; 1 some joint or type drifts (a rule fired);
2 bad input (no reports, fewer than 2 inspected boards, unreadable report).
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "spc", help="SPC across boards: distributions, Cp/Cpk, control charts, run rules",
        description="Statistical process control across inspected boards: per joint and\n"
                    "per package/joint type, individuals or X-bar-R control charts with\n"
                    "the Western Electric / Nelson run rules flagging drift before a joint\n"
                    "fails.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("report_dirs", nargs="+", type=Path, metavar="REPORT_DIR",
                   help="board report folders, or folders holding them")
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="folder for spc.csv, the charts and spc.html (created)")
    p.add_argument("--order", choices=("name", "given", "created"), default="name",
                   help="production order of the boards: natural sort of their folder "
                        "names (default), as given, or the reports' creation time")
    p.add_argument("--baseline", type=int, default=None, metavar="N",
                   help="control limits from the first N boards (default: the first "
                        "half, at least 8; all when fewer than 8)")
    p.add_argument("--no-charts", action="store_true", help="skip the PNG charts")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..inspect import analyse_reports, write_spc

    analysis = analyse_reports(args.report_dirs, order=args.order, baseline=args.baseline)
    written = write_spc(analysis, args.out, charts=not args.no_charts)
    flagged = analysis.flagged()
    keys = sorted({(s.scope, s.key) for s in flagged})
    print(f"{len(analysis.boards)} boards, {len(analysis.series)} series "
          f"(limits from the first {analysis.baseline} boards): "
          f"{len(keys)} joint(s)/type(s) with a run rule firing")
    for s in flagged[:20]:
        first = s.chart.first_hit
        rules = sorted({h.rule for h in s.chart.hits})
        print(f"  {s.scope} {s.key} {s.metric}: rules {rules}, first at "
              f"{analysis.boards[first].label}")
    if len(flagged) > 20:
        print(f"  ... and {len(flagged) - 20} more (see spc.csv)")
    if analysis.skipped:
        print(f"left out (not located): {', '.join(analysis.skipped)}")
    print(f"spc: {written['spc.csv']}  page: {written['spc.html']}")
    return 1 if flagged else 0
