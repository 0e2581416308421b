"""``smdinspect batch``: inspect every stack under a folder (process pool or Dask)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

#: Boards listed by name at the end of a run (errors first); the rest are in the summary.
_MAX_LISTED = 20

_EPILOG = """\
exit codes: 0 every board passed; 1 some board has defects; 2 some board could not be
inspected (bad or corrupt stack, board not located, crash) or bad arguments. An error
outranks defects. Per-board codes are in REPORTS_DIR/summary.csv.

Rerunning skips the boards whose reports are complete and whose inputs (stack.json,
frames, board file, settings) did not change; --force redoes them.
"""


def register(sub: argparse._SubParsersAction) -> None:
    from ..inspect._config import InspectConfig
    from ..sff import OPERATORS

    p = sub.add_parser(
        "batch", help="inspect every stack under a folder (process pool or Dask cluster)",
        description="Inspect every stack directory (a folder holding stack.json) under\n"
                    "STACKS_DIR against one reference board. Each board's reports go to\n"
                    "REPORTS_DIR/<stack path>/; summary.csv, summary.json and one merged\n"
                    "junit.xml go to REPORTS_DIR. Boards run in a local process pool, or on\n"
                    "a Dask cluster with --scheduler / --dask-local.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stacks_dir", type=Path, metavar="STACKS_DIR",
                   help="folder searched recursively for stack directories")
    p.add_argument("--board", required=True, type=Path, metavar="BOARD.json",
                   help="reference board file (e.g. references/demo_board.json)")
    p.add_argument("--out", required=True, type=Path, metavar="REPORTS_DIR",
                   help="batch report folder (created)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local process pool size (default: number of CPUs)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster, e.g. tcp://HOST:8786 (workers "
                            "need the same smdinspect and must see the same paths)")
    where.add_argument("--dask-local", type=int, metavar="N", default=None,
                       help="start a local Dask cluster of N worker processes for this run")
    p.add_argument("--force", action="store_true",
                   help="redo every board, even those whose reports are up to date")
    f = p.add_argument_group("inspection options (as for smdinspect inspect)")
    f.add_argument("--operator", default=None, choices=OPERATORS, metavar="OP",
                   help="focus measure (default sml)")
    f.add_argument("--window-px", type=int, default=None,
                   help="focus window side, odd (default: the inspection's, 5)")
    f.add_argument("--fit", default=None, choices=["power", "gauss3", "lsq", "argmax"],
                   help="peak model (default power)")
    f.add_argument("--fit-half-width", type=int, default=None,
                   help="frames kept each side of the peak (default 3)")
    f.add_argument("--min-confidence", type=float, default=None,
                   help="pixels below this confidence are unreliable (default 0.5)")
    f.add_argument("--align", action="store_true", default=None,
                   help="register frames first")
    f.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads per board (default: CPUs / workers; 1 on Dask)")
    f.add_argument("--keep-unreliable", action="store_true",
                   help="keep unreliable points in cloud.ply and the mesh")
    f.add_argument("--inspect-config", type=Path, default=None, metavar="JSON",
                   help="JSON file of InspectConfig settings (see the README, 'Inspection')")
    f.add_argument("--min-reliable-fraction", type=float, default=None,
                   help="joints with a smaller fraction of reliable pixels are 'unreliable' "
                        f"(default {InspectConfig.min_reliable_fraction})")
    f.add_argument("--no-html", action="store_true", help="skip each board's report.html")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from ..batch import run_batch
    from ..cli import progress_callback
    from ..errors import InputError
    from ..pipeline import inspection_focus_config
    from .inspect import inspect_config_from

    if args.workers is not None and (args.scheduler or args.dask_local is not None):
        raise InputError("--workers sizes the local process pool; with --scheduler or "
                         "--dask-local the Dask workers run the boards")
    given = {k: getattr(args, k) for k in ("operator", "window_px", "fit", "fit_half_width",
                                           "min_confidence", "align")
             if getattr(args, k) is not None}
    focus = dataclasses.replace(inspection_focus_config(), **given)
    progress = progress_callback(args, "boards", unit="board")
    try:
        res = run_batch(args.stacks_dir, args.board, args.out, workers=args.workers,
                        threads=args.threads, scheduler=args.scheduler,
                        dask_workers=args.dask_local, force=args.force, focus_config=focus,
                        inspect_config=inspect_config_from(args),
                        keep_unreliable=args.keep_unreliable, html=not args.no_html,
                        progress=progress)
    finally:
        progress.close()
    c = res.counts()
    print(f"{len(res.boards)} boards in {res.seconds:.1f} s on {res.executor}: {c['ok']} ok, "
          f"{c['defects']} with defects, {c['error']} errors"
          + (f" ({c['skipped']} unchanged, skipped)" if c["skipped"] else ""))
    # errors first, then boards with defects; the summary has them all
    bad = sorted((b for b in res.boards if b.status.value != "ok"),
                 key=lambda b: (b.status.value != "error", b.stack))
    for b in bad[:_MAX_LISTED]:
        print(f"  {b.stack}: {b.status.value} (exit {b.exit_code}) {b.reason}")
    if len(bad) > _MAX_LISTED:
        print(f"  ... and {len(bad) - _MAX_LISTED} more (see summary.csv)")
    print(f"summary: {res.summary_csv}  junit: {res.junit}")
    return res.exit_code
