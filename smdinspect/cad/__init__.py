"""CAD import: KiCad boards and centroid files → the reference board model.

Every reader returns the same thing, a board-file dict (schema ``smdinspect-board``
version 1, the format :func:`smdinspect.inspect.load_board` reads) plus the footprints it
skipped and why; :func:`import_board` validates the dict with the board loader and wraps
it in an :class:`ImportResult`.

>>> from smdinspect.cad import import_board            # doctest: +SKIP
>>> result = import_board("myboard.kicad_pcb")          # doctest: +SKIP
>>> result.board.joint("R3.1").center_mm                # doctest: +SKIP
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import InputError
from ._centroid import read_centroid
from ._kicad import KICAD_VERSIONS, read_kicad_pcb
from ._packages import PackageMatch, PackageTable, land_pattern, load_package_table, match_package

__all__ = [
    "KICAD_VERSIONS",
    "ImportResult",
    "PackageMatch",
    "PackageTable",
    "Skipped",
    "import_board",
    "is_cad_file",
    "land_pattern",
    "load_any_board",
    "load_package_table",
    "match_package",
    "read_centroid",
    "read_kicad_pcb",
]

_CENTROID_SUFFIXES = (".pos", ".csv", ".txt")


@dataclass(frozen=True)
class Skipped:
    """A footprint or centroid row that was not imported, and why."""

    ref: str
    footprint: str
    line: int | None
    reason: str

    def __str__(self) -> str:
        at = f" (line {self.line})" if self.line else ""
        return f"{self.ref} {self.footprint}{at}: {self.reason}"


@dataclass(frozen=True, eq=False)
class ImportResult:
    """A validated imported board.

    Attributes
    ----------
    board : smdinspect.inspect.Board
        The board, as the loader builds it from the written file.
    skipped : tuple of Skipped
    info : dict
        ``format`` (``kicad_pcb`` or ``centroid``), ``kicad_version``, ``notes``...
    """

    board: Any
    skipped: tuple[Skipped, ...]
    info: dict

    def to_dict(self) -> dict[str, Any]:
        """The board file: ``Board.to_dict()`` plus an ``import`` record (ignored by the
        loader) naming the source and every skipped footprint with its reason."""
        d = self.board.to_dict()
        d["import"] = {
            "source": self.info.get("source"),
            "format": self.info.get("format"),
            **({"kicad_version": self.info["kicad_version"],
                "format_version": self.info["format_version"]}
               if "kicad_version" in self.info else {}),
            "notes": list(self.info.get("notes", [])),
            "skipped": [{"ref": s.ref, "footprint": s.footprint, "line": s.line,
                         "reason": s.reason} for s in self.skipped],
        }
        return d

    def write(self, path: str | os.PathLike) -> Path:
        """Write the board file atomically (temporary file + rename)."""
        from .._atomic import write_text

        return write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")


def is_cad_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a KiCad board or a centroid file (not a board JSON)."""
    s = Path(path).suffix.lower()
    return s == ".kicad_pcb" or s in _CENTROID_SUFFIXES


def import_board(path: str | os.PathLike, *, packages: PackageTable | str | os.PathLike | None
                 = None, **centroid_options) -> ImportResult:
    """Import a KiCad board (``.kicad_pcb``) or a centroid file and validate it.

    Parameters
    ----------
    path : str or PathLike
        ``.kicad_pcb`` (KiCad 6–9) or a centroid file (``.pos``, ``.csv``, ``.txt``).
    packages : PackageTable or path, optional
        A package table (TOML, see :func:`load_package_table`).
    **centroid_options
        ``origin_mm``, ``size_mm``, ``margin_mm``, ``thickness_mm`` for centroid files.

    Returns
    -------
    ImportResult

    Raises
    ------
    InputError
        One line ``FILE:LINE: problem``: syntax errors, malformed items, or a board the
        loader rejects (e.g. overlapping pads: the line of the footprint named).
    """
    from ..inspect._board import board_from_dict

    p = Path(path)
    if not p.is_file():
        raise InputError(f"board file {str(p)!r} does not exist or is not a file")
    table = packages if isinstance(packages, PackageTable) or packages is None \
        else load_package_table(packages)
    if p.suffix.lower() == ".kicad_pcb":
        if centroid_options:
            raise InputError(f"options {', '.join(centroid_options)} apply to centroid "
                             f"files only")
        data, skipped, info = read_kicad_pcb(p, packages=table)
    elif p.suffix.lower() in _CENTROID_SUFFIXES:
        data, skipped, info = read_centroid(p, packages=table, **centroid_options)
    else:
        raise InputError(f"{p}: unknown CAD file type {p.suffix!r}; expected .kicad_pcb, "
                         f".pos or .csv")
    info["source"] = str(p)
    if not data["components"]:
        reasons = "; ".join(sorted({s["reason"] for s in skipped}))[:300]
        raise InputError(f"{p}: no top-side SMD part could be imported ({len(skipped)} "
                         f"skipped: {reasons})")
    try:
        board = board_from_dict(data, source=str(p))
    except InputError as exc:
        raise _with_line(exc, str(p), info.get("lines", {})) from None
    return ImportResult(board, tuple(Skipped(**s) for s in skipped), info)


def _with_line(exc: InputError, source: str, lines: dict[str, int | None]) -> InputError:
    msg = str(exc)
    rest = msg[len(source) + 2:] if msg.startswith(source + ": ") else msg
    m = re.search(r"(?:joints?|component|fiducial) ([^\s.:]+)", rest)
    line = lines.get(m.group(1)) if m else None
    return InputError(f"{source}:{line}: {rest}" if line else msg)


def load_any_board(path: str | os.PathLike, *, packages=None):
    """A :class:`~smdinspect.inspect.Board` from a board JSON, a KiCad board or a
    centroid file (the latter two imported on the fly)."""
    from ..inspect import load_board

    if is_cad_file(path):
        return import_board(path, packages=packages).board
    return load_board(path)
