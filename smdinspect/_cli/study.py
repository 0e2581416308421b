"""``smdinspect study texture``: how texture variation affects SFF, per focus operator.

Also home of :func:`resolve_auto_operator`, the CLI side of ``--operator auto``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

_EPILOG = """\
Renders scenes of known shape (cone, slanted plane, steps) with textures swept over
contrast, dominant frequency and kind (band-limited noise, weave, grain, sparse marks)
at several sensor-noise levels, reconstructs every stack with each focus operator and
the power and gauss3 fits, and writes into --out: texture_study.csv (one row per
reconstruction), texture_study.json (settings and summary numbers), texture_study.png
(RMSE and coverage against contrast per operator family), texture_study_ranking.csv/.png,
texture_study.md (the written summary) and operator_table.json (the table of
`reconstruct --operator auto`). Finished cells are kept in --out/cells/: rerunning the
same command resumes where it stopped.

To ship a new table:  cp DIR/operator_table.json smdinspect/study/operator_table.json
"""


def register(sub: argparse._SubParsersAction) -> None:
    from ..cli import _add_verbosity

    p = sub.add_parser("study", help="studies of the SFF method (texture: operators vs texture)",
                       description="Studies of the shape-from-focus method on synthetic stacks.")
    ssub = p.add_subparsers(dest="study_command", metavar="STUDY", required=True)
    t = ssub.add_parser("texture", help="scenes × textures × noise × focus operators",
                        description="How texture contrast, frequency, kind and sensor noise "
                                    "affect each focus operator's reconstruction.",
                        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    t.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="output folder (created; an earlier run's cells are reused)")
    t.add_argument("--quick", action="store_true",
                   help="the small study (72 stacks of 64 px; under a minute on 2 cores)")
    t.add_argument("--seed", type=int, default=0,
                   help="study seed (default 0; keep 0-999 for tuning, 10000-10999 for tests)")
    t.add_argument("--workers", type=int, default=2,
                   help="cells computed at once, one process each (default 2)")
    t.add_argument("--operators", default=None, metavar="OP,OP",
                   help="only these operators (comma-separated; default all 25)")
    _add_verbosity(t, "sub_")
    t.set_defaults(func=run_texture)


def run_texture(args: argparse.Namespace) -> int:
    from ..cli import progress_callback
    from ..study import TextureStudyConfig, run_texture_study

    # one line per reconstruction would drown the bar; the study logs its own progress
    logging.getLogger("smdinspect.sff").setLevel(max(logging.WARNING,
                                                     logging.getLogger().level))
    kw: dict = {"seed": args.seed, "workers": args.workers}
    if args.operators:
        kw["operators"] = tuple(o.strip() for o in args.operators.split(",") if o.strip())
    config = TextureStudyConfig.quick(**kw) if args.quick else TextureStudyConfig(**kw)
    bar = progress_callback(args, "texture study", unit="cell")
    try:
        study = run_texture_study(args.out, config, progress=bar)
    finally:
        bar.close()
    a = _top(study)
    print(f"texture study: {len(study.cells)} cells ({study.computed} computed in "
          f"{study.seconds:.0f} s, {study.reused} reused)")
    print(a)
    print(f"outputs in {args.out}/ (read texture_study.md; figure texture_study.png)")
    return 0


def _top(study) -> str:
    a = study.analysis
    rank = a["ranking"][a["fit"]]
    best = ", ".join(f"{r['operator']} {r['score']:.2f}" for r in rank[:3])
    sml = next((r for r in rank if r["operator"] == "sml"), None)
    line = f"best mean score (fit {a['fit']}): {best}"
    if sml is not None:
        line += f"; sml {sml['score']:.2f} (rank {sml['rank']})"
    return line


def resolve_auto_operator(args: argparse.Namespace, stack) -> dict | None:
    """``--operator auto``: replace ``args.operator`` by the operator the texture study's
    table picks for ``stack`` and return the choice (for ``summary.json``); None when the
    operator was given."""
    if getattr(args, "operator", None) != "auto":
        return None
    from ..study import choose_operator

    choice = choose_operator(stack, fit=getattr(args, "fit", "power"))
    args.operator = choice.operator
    return choice.to_dict()
