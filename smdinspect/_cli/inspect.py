"""``smdinspect inspect``: a focal stack (or a reconstruction) + a board file → verdicts.

Exit codes: 0 every joint passes (unreliable joints are reported but do not fail),
1 at least one defect, 2 bad input, 3 the board could not be located.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..inspect._config import InspectConfig
    from ..pipeline import inspection_focus_config
    from .reconstruct import add_stack_arguments

    p = sub.add_parser(
        "inspect", help="locate the board, measure and judge every solder joint",
        description="Reconstruct a focal stack (or read a reconstruction directory), locate "
                    "the reference board in it, measure every joint and write report.json, "
                    "joints.csv, junit.xml and report.html. Exit 0: all joints pass; "
                    "1: defects; 2: bad input; 3: board not located.")
    add_stack_arguments(p)
    p.add_argument("--board", required=True, type=Path,
                   help="reference board file (JSON), or a .kicad_pcb / centroid file")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--inspect-config", type=Path, default=None, metavar="JSON",
                   help="JSON file of InspectConfig settings (see the README, 'Inspection')")
    p.add_argument("--min-reliable-fraction", type=float, default=None,
                   help="joints with a smaller fraction of reliable pixels are 'unreliable' "
                        f"(default {InspectConfig.min_reliable_fraction})")
    p.add_argument("--no-html", action="store_true", help="skip report.html")
    # Inspection focuses with its own, smaller window by default (steep, narrow fillets).
    p.set_defaults(func=run, window_px=inspection_focus_config().window_px)


def inspect_config_from(args: argparse.Namespace):
    from ..errors import InputError
    from ..inspect import InspectConfig

    doc = {}
    if args.inspect_config is not None:
        try:
            doc = json.loads(args.inspect_config.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"--inspect-config {args.inspect_config}: {exc}") from None
        if not isinstance(doc, dict):
            raise InputError(f"--inspect-config {args.inspect_config}: must hold a JSON object")
    if args.min_reliable_fraction is not None:
        doc["min_reliable_fraction"] = args.min_reliable_fraction
    return InspectConfig.from_dict(doc)


def run(args: argparse.Namespace) -> int:
    from ..cad import load_any_board
    from ..cli import progress_callback
    from ..pipeline import inspect_stack, is_reconstruction, load_reconstruction
    from ..stack import open_stack
    from .reconstruct import focus_config_from

    board = load_any_board(args.board)  # a board JSON, or a CAD file imported on the fly
    config = inspect_config_from(args)
    if len(args.stack) == 1 and is_reconstruction(args.stack[0]):
        stack = load_reconstruction(args.stack[0], pixel_size_mm=args.pixel_size_mm)
        source = str(args.stack[0])
    else:
        stack = open_stack(args.stack, step_mm=args.step_mm, pixel_size_mm=args.pixel_size_mm)
        source = None
    result = inspect_stack(stack, board, args.out, focus_config=focus_config_from(args),
                           inspect_config=config, keep_unreliable=args.keep_unreliable,
                           progress=progress_callback(args, "focus"), html=not args.no_html,
                           source=source)
    print(result.summary())
    print(f"reports in {args.out}/ (open report.html)")
    return result.exit_code
