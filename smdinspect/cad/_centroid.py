"""Centroid (pick-and-place) files → the reference board model.

Read formats: KiCad ``.pos`` (ASCII, with ``## Unit = mm|inches``, or its CSV form),
Altium pick-and-place CSV (``Designator, Footprint, Center-X(mm), Center-Y(mm), Layer,
Rotation``; header lines before the table are skipped), EasyEDA / JLC CPL CSV
(``Designator, Footprint, Mid X, Mid Y, Layer, Rotation``, values such as ``12.7mm``).
Columns are found by their header names; coordinates are y up; rotations counter-
clockwise from the library's zero orientation (IPC-7351), which :mod:`._packages`
converts into the board model's frame.

A centroid file has neither pads nor an outline: pads come from the package (built-in
land patterns or the ``--packages`` table), the board is the pads' bounding box plus a
margin unless ``origin_mm`` / ``size_mm`` are given.
"""

from __future__ import annotations

import csv
import io
import math
import re
import shlex
from pathlib import Path

import numpy as np

from ..errors import InputError
from ._packages import PackageTable, land_pattern, match_package

__all__ = ["read_centroid"]

_ALIASES = {
    "ref": ("designator", "ref", "reference", "refdes", "refdesignator", "part", "name"),
    "value": ("val", "value", "comment"),
    "package": ("package", "footprint", "pattern", "packagename"),
    "x": ("posx", "midx", "centerx", "x", "locationx", "cx"),
    "y": ("posy", "midy", "centery", "y", "locationy", "cy"),
    "rot": ("rot", "rotation", "angle", "orientation"),
    "side": ("side", "layer", "tb", "mirror"),
}
_UNIT_MM = {"mm": 1.0, "mil": 0.0254, "mils": 0.0254, "in": 25.4, "inch": 25.4,
            "inches": 25.4}


def _key(header: str) -> tuple[str, float | None]:
    """Header cell → (normalised name, unit scale from ``(mm)``/``(mil)`` or None)."""
    h = header.strip().strip('"').lower()
    unit = None
    m = re.search(r"\((mm|mil|mils|in|inch)\)\s*$", h)
    if m:
        unit = _UNIT_MM[m.group(1)]
        h = h[:m.start()]
    return re.sub(r"[^a-z0-9]", "", h), unit


def _rows(text: str, source: str):
    """(header, [(line, cells)], default unit) of any of the supported layouts."""
    lines = text.splitlines()
    unit = 1.0
    for ln in lines:
        m = re.match(r"^\s*#+\s*unit\s*=\s*(mm|inches|inch|in|mils?)", ln, re.I)
        if m:
            unit = _UNIT_MM[m.group(1).lower()]
    # KiCad ASCII: "# Ref Val Package PosX PosY Rot Side" then whitespace columns.
    for i, ln in enumerate(lines):
        s = ln.strip()
        if s.startswith("#") and re.search(r"\bref\b", s, re.I) and re.search(r"posx", s, re.I):
            header = s.lstrip("#").split()
            body = []
            for k, row in enumerate(lines[i + 1:], start=i + 2):
                if not row.strip() or row.lstrip().startswith("#"):
                    continue
                try:
                    body.append((k, shlex.split(row)))
                except ValueError as exc:
                    raise InputError(f"{source}:{k}: cannot split the row: {exc}") from None
            return header, body, unit
    # CSV (comma, semicolon or tab): the first row naming a reference and an x column.
    sample = "\n".join(lines[:50])
    try:
        dialect = csv.Sniffer().sniff(sample, delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    reader = list(csv.reader(io.StringIO(text), dialect))
    for i, row in enumerate(reader):
        keys = {_key(c)[0] for c in row}
        if keys & set(_ALIASES["ref"]) and keys & set(_ALIASES["x"]):
            body = [(k + 1, r) for k, r in enumerate(reader[i + 1:], start=i + 1)
                    if any(c.strip() for c in r)]
            return row, body, unit
    raise InputError(f"{source}:1: not a centroid file: no header row naming a reference "
                     f"(Ref/Designator) and an x position (PosX/Mid X/Center-X) column")


def _number(cell: str, scale: float, source: str, line: int, column: str) -> float:
    s = cell.strip().strip('"')
    m = re.fullmatch(r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(mm|mils?|in|inch)?", s)
    if not m:
        raise InputError(f"{source}:{line}: column {column}: {cell!r} is not a number")
    v = float(m.group(1))
    if m.group(2):
        scale = _UNIT_MM[m.group(2)]
    return v * scale


def read_centroid(path: str | Path, *, packages: PackageTable | None = None,
                  origin_mm: tuple[float, float] | None = None,
                  size_mm: tuple[float, float] | None = None, margin_mm: float = 1.0,
                  thickness_mm: float = 1.6):
    """Read a centroid file into a board-file dict.

    Parameters
    ----------
    path : str or Path
        A KiCad ``.pos``, Altium or EasyEDA/JLC CSV file.
    packages : PackageTable, optional
        Package table; searched before the built-in name rules.
    origin_mm : (float, float), optional
        The board's lower-left corner in the file's coordinates.
    size_mm : (float, float), optional
        Board width and height; default: the pads' extent plus ``margin_mm`` each side
        (then the origin moves to keep the margin).
    margin_mm : float
        Margin around the pads when the board size is not given (default 1 mm).
    thickness_mm : float
        Board thickness (the file does not say; default 1.6).

    Returns
    -------
    (dict, list of dict, dict)
        As :func:`smdinspect.cad.read_kicad_pcb`.
    """
    if margin_mm < 0:
        raise InputError(f"margin_mm must be >= 0; got {margin_mm}")
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read centroid file: {exc}") from None
    src = str(p)
    header, body, unit = _rows(text, src)
    cols: dict[str, tuple[int, float | None]] = {}
    for idx, cell in enumerate(header):
        name, cu = _key(cell)
        for field, names in _ALIASES.items():
            if name in names and field not in cols:
                cols[field] = (idx, cu)
    missing = [f for f in ("ref", "package", "x", "y", "rot") if f not in cols]
    if missing:
        raise InputError(f"{src}:1: centroid header lacks column(s) {', '.join(missing)} "
                         f"(found: {', '.join(header)})")

    parts, skipped, lines = [], [], {}
    seen: set[str] = set()
    for line, cells in body:
        def cell(field: str) -> str:
            i = cols[field][0]
            if i >= len(cells):
                raise InputError(f"{src}:{line}: row has {len(cells)} columns; column "
                                 f"{header[i]!r} is missing")
            return cells[i].strip().strip('"')

        ref, package = cell("ref"), cell("package")
        lines[ref] = line

        def skip(reason: str) -> None:
            skipped.append({"ref": ref, "footprint": package, "line": line, "reason": reason})

        x = _number(cell("x"), cols["x"][1] or unit, src, line, header[cols["x"][0]])
        y = _number(cell("y"), cols["y"][1] or unit, src, line, header[cols["y"][0]])
        rot = _number(cell("rot"), 1.0, src, line, header[cols["rot"][0]])
        side = cell("side").lower() if "side" in cols else "top"
        if side not in ("top", "t", "toplayer", "f.cu", "front", "f"):
            skip(f"bottom side ({side})" if side.startswith("b") else f"side {side!r}")
            continue
        if not ref or "." in ref:
            skip(f"reference {ref!r} cannot name joints (empty or contains '.')")
            continue
        if ref in seen:
            raise InputError(f"{src}:{line}: duplicate reference {ref!r}")
        if package.lower().startswith("fiducial") or ref.upper().startswith("FID"):
            m = re.search(r"(\d+(?:\.\d+)?)mm", package)
            d = float(m.group(1)) if m else 1.0
            parts.append(("fid", ref, x, y, d))
            seen.add(ref)
            continue
        match = match_package(package, ref=ref, table=packages)
        if isinstance(match, str):
            skip(match)
            continue
        pads = land_pattern(match)
        rotation = (rot - match.zero_rotation_deg + 180.0) % 360.0 - 180.0
        if math.isclose(rotation, -180.0):
            rotation = 180.0
        parts.append(("comp", ref, x, y, rotation, match, pads))
        seen.add(ref)

    if not parts:
        raise InputError(f"{src}: no top-side part could be modelled "
                         f"({len(skipped)} skipped)")
    # The pads' exact extent: build the board once in a provisional frame with room
    # around every part, let the loader lay out the pads, then place the real frame.
    pos = np.array([[part[2], part[3]] for part in parts])
    reach = 2.0 + max((max(abs(v) for pd in part[6] for v in _pad_reach(pd))
                       for part in parts if part[0] == "comp"), default=1.0)
    lo0 = pos.min(axis=0) - reach
    size0 = pos.max(axis=0) + reach - lo0
    provisional = _board_dict(p.stem, parts, lo0, size0, thickness_mm)
    from ..inspect._board import board_from_dict

    try:
        b0 = board_from_dict(provisional, source=src)
    except InputError:
        b0 = None  # the caller's validation reports it against the final frame
    if b0 is not None:
        pts = [j.polygon_mm for j in b0.joints()]
        pts += [np.array([[f.x_mm - f.diameter_mm / 2, f.y_mm - f.diameter_mm / 2],
                          [f.x_mm + f.diameter_mm / 2, f.y_mm + f.diameter_mm / 2]])
                for f in b0.fiducials]
        allp = np.vstack(pts) + lo0
        ext_lo, ext_hi = allp.min(axis=0), allp.max(axis=0)
    else:
        ext_lo, ext_hi = pos.min(axis=0), pos.max(axis=0)
    origin = ext_lo - margin_mm if origin_mm is None else np.array(origin_mm, float)
    if size_mm is None:
        size = ext_hi + margin_mm - origin
    else:
        size = np.array(size_mm, float)
        if (size <= 0).any():
            raise InputError(f"size_mm must be > 0; got {tuple(size_mm)}")
    data = _board_dict(p.stem, parts, origin, size, thickness_mm)
    info = {"format": "centroid", "lines": lines, "notes": [],
            "origin_file_mm": [round(float(origin[0]), 6), round(float(origin[1]), 6)]}
    return data, skipped, info


def _pad_reach(pd: dict) -> list[float]:
    if "polygon_mm" in pd:
        return [v for q in pd["polygon_mm"] for v in q]
    r = max(pd["length_mm"], pd["width_mm"])
    return [abs(pd["x_mm"]) + r, abs(pd["y_mm"]) + r]


def _board_dict(name: str, parts: list, origin, size, thickness_mm: float) -> dict:
    fids, comps = [], []
    for part in parts:
        if part[0] == "fid":
            _, ref, x, y, d = part
            fids.append({"id": ref, "x_mm": round(x - origin[0], 6),
                         "y_mm": round(y - origin[1], 6), "diameter_mm": d})
            continue
        _, ref, x, y, rotation, match, pads = part
        comp = {"ref": ref, "package": match.package, "kind": match.kind,
                "style": match.style, "x_mm": round(x - origin[0], 6),
                "y_mm": round(y - origin[1], 6), "rotation_deg": round(rotation, 6),
                "body": dict(match.body), "pads": pads}
        if match.lead is not None:
            comp["lead"] = dict(match.lead)
        comps.append(comp)
    return {"schema": "smdinspect-board", "version": 1, "name": name, "units": "mm",
            "size_mm": [round(float(size[0]), 6), round(float(size[1]), 6)],
            "thickness_mm": thickness_mm, "fiducials": fids, "components": comps}
