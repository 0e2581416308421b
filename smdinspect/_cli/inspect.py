"""``smdinspect inspect``: a focal stack (or a reconstruction) + a board file → verdicts.

Exit codes: 0 every joint passes (unreliable joints are reported but do not fail),
1 at least one defect, 2 bad input, 3 the board could not be located.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..inspect._config import InspectConfig
    from .reconstruct import (add_calibration_argument, add_cloud_filled_argument,
                              add_stack_arguments)

    p = sub.add_parser(
        "inspect", help="locate the board, measure and judge every solder joint",
        description="Reconstruct a focal stack (or read a reconstruction directory), locate "
                    "the reference board in it, measure every joint and write report.json, "
                    "joints.csv, junit.xml, report.html and the IPC-CFX UnitsInspected "
                    "message cfx_units_inspected.json. Exit 0: all joints pass; "
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
    add_cloud_filled_argument(p)
    add_calibration_argument(p, "before the joints are measured")
    # Inspection focuses with its own, smaller window by default (steep, narrow fillets).
    p.set_defaults(func=run, window_px=None)  # from the pixel size (inspection_window_px)


def inspect_config_from(args: argparse.Namespace):
    from .._json import read_json
    from ..errors import InputError
    from ..inspect import InspectConfig

    doc = {}
    if args.inspect_config is not None:
        if not args.inspect_config.is_file():
            raise InputError(f"--inspect-config {args.inspect_config}: no such file")
        doc = read_json(args.inspect_config)
        if not isinstance(doc, dict):
            raise InputError(f"--inspect-config {args.inspect_config}: must hold a JSON object")
    if args.min_reliable_fraction is not None:
        doc["min_reliable_fraction"] = args.min_reliable_fraction
    return InspectConfig.from_dict(doc)


def run(args: argparse.Namespace) -> int:
    from .. import _atomic
    from ..cad import load_any_board
    from ..cli import progress_callback
    from ..errors import BoardNotLocatedError, InputError
    from ..inspect._board import check_board_in_field
    from ..pipeline import (inspect_stack, inspection_focus_config, inspection_outputs,
                            is_reconstruction, load_reconstruction)
    from ..sff._export import RECONSTRUCTION_OUTPUTS, check_cloud_options
    from ..stack import open_stack
    from .reconstruct import check_calibration_argument, focus_config_from

    check_cloud_options(args.keep_unreliable, args.cloud_filled)
    board = load_any_board(args.board)  # a board JSON, or a CAD file imported on the fly
    check_calibration_argument(args)
    config = inspect_config_from(args)
    carry: tuple[str, ...] = ()
    if len(args.stack) == 1 and is_reconstruction(args.stack[0]):
        stack = load_reconstruction(args.stack[0], pixel_size_mm=args.pixel_size_mm)
        source, shape = str(args.stack[0]), stack.shape
        if args.out.is_dir() and args.out.samefile(args.stack[0]):
            carry = RECONSTRUCTION_OUTPUTS  # the reports join the reconstruction they read
    else:
        stack = open_stack(args.stack, step_mm=args.step_mm, pixel_size_mm=args.pixel_size_mm,
                           z_from_name=args.z_from_name)
        source, shape = None, stack.read_frame(0).shape[:2]
    if stack.pixel_size_mm is None:
        raise InputError("inspection needs the pixel size in mm: give --pixel-size-mm "
                         f"(the input {args.stack[0]} has none)")
    check_board_in_field(board, shape, stack.pixel_size_mm)
    not_located = None
    # Every output of this run goes to a temporary sibling of --out, swapped in at the end:
    # a run that fails leaves --out as it was, and no old report survives beside new ones.
    with _atomic.replace_dir(args.out, replaces=inspection_outputs(), carry=carry) as tmp:
        try:
            focus = focus_config_from(args, inspection_focus_config(stack.pixel_size_mm))
            result = inspect_stack(stack, board, tmp, focus_config=focus,
                                   inspect_config=config, keep_unreliable=args.keep_unreliable,
                                   cloud_filled=args.cloud_filled,
                                   progress=progress_callback(args, "focus"),
                                   html=not args.no_html, source=source,
                                   calibration=args.calibration)
        except BoardNotLocatedError as exc:
            not_located = exc  # its report.json (and the reconstruction) are this run's outputs
    if not_located is not None:
        raise not_located
    print(result.summary())
    print(f"reports in {args.out}/ (open report.html)")
    return result.exit_code
