"""``smdinspect board import``: a KiCad board or a centroid file → a board file (JSON)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two numbers 'A,B'; got {text!r}") from None
    return a, b


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("board", help="board files: import from CAD (KiCad, centroid files)",
                       description="Work with reference board files.")
    bsub = p.add_subparsers(dest="board_command", metavar="ACTION", required=True)
    imp = bsub.add_parser(
        "import", help="KiCad 6-9 .kicad_pcb or a centroid file (.pos/.csv) → board JSON",
        description="Import every top-side SMD chip and gull-wing part with its real pads, "
                    "the Edge.Cuts outline and Fiducial* footprints; list every footprint "
                    "that is skipped, with the reason.")
    imp.add_argument("source", type=Path, metavar="FILE",
                     help=".kicad_pcb board, or a KiCad .pos / Altium / EasyEDA CSV file")
    imp.add_argument("--out", required=True, type=Path, help="board file to write (JSON)")
    imp.add_argument("--packages", type=Path, default=None, metavar="TOML",
                     help="package table: footprint/package names → body, lead, pads "
                          "(see the README, 'Board import')")
    imp.add_argument("--origin-mm", type=_pair, default=None, metavar="X,Y",
                     help="centroid files: the board's lower-left corner in file "
                          "coordinates (default: pads' extent minus the margin)")
    imp.add_argument("--size-mm", type=_pair, default=None, metavar="W,H",
                     help="centroid files: board width and height (default: pads' extent "
                          "plus the margin)")
    imp.add_argument("--margin-mm", type=float, default=1.0,
                     help="centroid files: margin around the pads (default %(default)s)")
    imp.add_argument("--thickness-mm", type=float, default=1.6,
                     help="centroid files: board thickness (default %(default)s)")
    imp.set_defaults(func=run_import)


def run_import(args: argparse.Namespace) -> int:
    from ..cad import import_board

    opts = {}
    if args.source.suffix.lower() != ".kicad_pcb":
        opts = {"origin_mm": args.origin_mm, "size_mm": args.size_mm,
                "margin_mm": args.margin_mm, "thickness_mm": args.thickness_mm}
    result = import_board(args.source, packages=args.packages, **opts)
    result.write(args.out)
    b = result.board
    what = f"KiCad {result.info['kicad_version']}" if "kicad_version" in result.info \
        else "centroid file"
    print(f"imported {len(b.components)} components ({len(b.joints())} joints), "
          f"{len(b.fiducials)} fiducials from {args.source} ({what}); board "
          f"{b.size_mm[0]:g} x {b.size_mm[1]:g} mm")
    for note in result.info.get("notes", []):
        print(f"note: {note}")
    if result.skipped:
        print(f"skipped {len(result.skipped)}:")
        for s in result.skipped:
            print(f"  {s}")
    print(f"board file: {args.out}")
    return 0
