"""KiCad board files (``.kicad_pcb``, KiCad 6 to 9) → the reference board model.

The file is parsed by :mod:`sexpdata` (see :mod:`._sexpr`); this module interprets the
tree. What it reads:

* ``(version N)``: format dates 20211014 (KiCad 6), 20221018 (7), 20240108 (8),
  20241229 (9); older (KiCad 5 ``module``) files are refused, newer ones read with a note;
* the board outline: every ``gr_line / gr_rect / gr_arc / gr_circle / gr_poly /
  gr_curve`` (and footprint ``fp_*``) item on ``Edge.Cuts``; the board frame's origin is
  the outline's lower-left corner and its size the outline's bounding box;
* ``(general (thickness T))``;
* every footprint: reference (``fp_text reference`` in KiCad 6/7, ``property
  "Reference"`` from KiCad 8), side, position, rotation, attributes, and its copper pads
  with their real outline (``rect``, ``roundrect``, chamfered, ``oval``, ``circle``,
  ``trapezoid``, ``custom`` polygons).

KiCad's frame has y down and angles counter-clockwise as seen on screen; a pad's ``at``
angle in a board file is absolute (the footprint's rotation included); pad positions are
in the unrotated footprint frame. The board model's frame has y up, so
``x_board = x − x_min``, ``y_board = y_max − y`` and angles keep their value.

Footprints that are not top-side SMD chips or gull-wing parts are listed with a reason
(:class:`Skipped`), never dropped silently.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ._packages import PackageMatch, PackageTable, footprint_base, match_package
from ._sexpr import SexprDoc, parse_sexpr

__all__ = ["KICAD_VERSIONS", "read_kicad_pcb"]

log = logging.getLogger(__name__)

#: Board file format dates written by each KiCad release.
KICAD_VERSIONS = {6: 20211014, 7: 20221018, 8: 20240108, 9: 20241229}

_ARC_SEGMENTS = 8          # per quarter circle of rounded corners and ovals
_CIRCLE_SEGMENTS = 32


def kicad_release(version: int) -> str:
    """``20240108`` → ``"8"``; dates between releases name the next development version."""
    if version <= KICAD_VERSIONS[6]:
        return "6"
    for major in (7, 8, 9):
        if version <= KICAD_VERSIONS[major]:
            return str(major) if version == KICAD_VERSIONS[major] else f"{major} (development)"
    return f"newer than 9 (format {version})"


# --------------------------------------------------------------------------------------
# Tree helpers.
# --------------------------------------------------------------------------------------


def _head(node: Any) -> str | None:
    return str(node[0]) if isinstance(node, list) and node and isinstance(node[0], str) \
        else None


def _items(node: list, name: str) -> list[list]:
    return [c for c in node[1:] if _head(c) == name]


def _item(node: list, name: str) -> list | None:
    for c in node[1:]:
        if _head(c) == name:
            return c
    return None


def _num(doc: SexprDoc, node: list, index: int, what: str, default=None) -> float:
    if len(node) <= index:
        if default is not None:
            return float(default)
        raise doc.error(node, f"({_head(node)} ...) lacks its {what}")
    v = node[index]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise doc.error(node, f"({_head(node)} ...): {what} must be a number; got {v!r}")
    return float(v)


def _xy(doc: SexprDoc, node: list | None, what: str) -> tuple[float, float]:
    if node is None:
        raise InputError(f"{doc.source}: missing ({what} x y)")
    return _num(doc, node, 1, f"{what} x"), _num(doc, node, 2, f"{what} y")


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _yup(pts) -> np.ndarray:
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2).copy()
    p[:, 1] = -p[:, 1]
    return p


# --------------------------------------------------------------------------------------
# Board outline.
# --------------------------------------------------------------------------------------


def _arc_points(start, mid, end, n: int = 64) -> np.ndarray:
    (x1, y1), (x2, y2), (x3, y3) = start, mid, end
    d = 2 * (x1 * (y2 - y3) + x2 * (y3 - y1) + x3 * (y1 - y2))
    if abs(d) < 1e-12:
        return np.array([start, mid, end], dtype=np.float64)
    ux = ((x1 ** 2 + y1 ** 2) * (y2 - y3) + (x2 ** 2 + y2 ** 2) * (y3 - y1)
          + (x3 ** 2 + y3 ** 2) * (y1 - y2)) / d
    uy = ((x1 ** 2 + y1 ** 2) * (x3 - x2) + (x2 ** 2 + y2 ** 2) * (x1 - x3)
          + (x3 ** 2 + y3 ** 2) * (x2 - x1)) / d
    r = math.hypot(x1 - ux, y1 - uy)
    a1, a2, a3 = (math.atan2(y - uy, x - ux) for x, y in (start, mid, end))
    # Sweep from a1 to a3 through a2.
    sweep = (a3 - a1) % (2 * math.pi)
    if (a2 - a1) % (2 * math.pi) > sweep:
        sweep -= 2 * math.pi
    t = a1 + np.linspace(0.0, sweep, n)
    return np.column_stack([ux + r * np.cos(t), uy + r * np.sin(t)])


def _shape_points(doc: SexprDoc, node: list) -> np.ndarray:
    """Points (KiCad frame) bounding one graphic item (lines, arcs, circles, polygons)."""
    kind = _head(node).split("_", 1)[1]
    if kind in ("line", "rect"):
        a = _xy(doc, _item(node, "start"), "start")
        b = _xy(doc, _item(node, "end"), "end")
        return np.array([a, b])
    if kind == "arc":
        a = _xy(doc, _item(node, "start"), "start")
        b = _xy(doc, _item(node, "end"), "end")
        mid = _item(node, "mid")
        if mid is None:
            raise doc.error(node, "arc without (mid x y): KiCad 5 arcs are not read; "
                                  "open and save the board in KiCad 6 or newer")
        return _arc_points(a, _xy(doc, mid, "mid"), b)
    if kind == "circle":
        c = np.array(_xy(doc, _item(node, "center"), "center"))
        e = np.array(_xy(doc, _item(node, "end"), "end"))
        r = float(np.hypot(*(e - c)))
        t = np.linspace(0, 2 * math.pi, _CIRCLE_SEGMENTS, endpoint=False)
        return c + r * np.column_stack([np.cos(t), np.sin(t)])
    if kind in ("poly", "curve"):
        return _pts(doc, _item(node, "pts"), node)
    raise doc.error(node, f"unknown graphic item {_head(node)}")


def _pts(doc: SexprDoc, pts: list | None, owner: list) -> np.ndarray:
    if pts is None:
        raise doc.error(owner, f"({_head(owner)} ...) without (pts ...)")
    out: list = []
    for p in pts[1:]:
        h = _head(p)
        if h == "xy":
            out.append(_xy(doc, p, "xy"))
        elif h == "arc":
            arc = _arc_points(_xy(doc, _item(p, "start"), "start"),
                              _xy(doc, _item(p, "mid"), "mid"),
                              _xy(doc, _item(p, "end"), "end"), n=_ARC_SEGMENTS * 2)
            out.extend(map(tuple, arc))
    if len(out) < 2:
        raise doc.error(pts, "a polygon needs at least 3 points")
    # Drop consecutive duplicates (arc ends meet the next segment).
    keep = [out[0]] + [q for p, q in zip(out, out[1:]) if math.dist(p, q) > 1e-9]
    if len(keep) > 2 and math.dist(keep[0], keep[-1]) <= 1e-9:
        keep.pop()
    return np.array(keep, dtype=np.float64)


def _layer(node: list) -> str | None:
    lay = _item(node, "layer")
    return str(lay[1]) if lay is not None and len(lay) > 1 else None


def _outline_points(doc: SexprDoc) -> np.ndarray:
    pts = []
    for node in doc.root[1:]:
        h = _head(node)
        if h and h.startswith("gr_") and _layer(node) == "Edge.Cuts":
            pts.append(_shape_points(doc, node))
    for fp in _items(doc.root, "footprint"):
        origin, angle = _placement(doc, fp)
        for node in fp[1:]:
            h = _head(node)
            if h and h.startswith("fp_") and h != "fp_text" and _layer(node) == "Edge.Cuts":
                local = _shape_points(doc, node)
                pts.append(_yup(_yup(local) @ _rot(angle).T) + origin)
    if not pts:
        raise InputError(f"{doc.source}:1: no board outline: the board has no item on "
                         f"Edge.Cuts")
    return np.vstack(pts)


# --------------------------------------------------------------------------------------
# Pads.
# --------------------------------------------------------------------------------------


def _rounded_rect(w: float, h: float, r: float, chamfer: float = 0.0,
                  chamfered: frozenset = frozenset()) -> np.ndarray:
    """Counter-clockwise outline (y up) of a w × h rectangle with rounded/chamfered corners.

    ``chamfered`` names corners in KiCad's screen terms (``top_left`` ... with y down).
    """
    hw, hh = w / 2.0, h / 2.0
    r = min(max(r, 0.0), hw, hh)
    out = []
    # Corners counter-clockwise from bottom-right (y up); screen names flip top/bottom.
    corners = [((hw, -hh), "bottom_right", -90.0), ((hw, hh), "top_right", 0.0),
               ((-hw, hh), "top_left", 90.0), ((-hw, -hh), "bottom_left", 180.0)]
    screen = {"bottom_right": "top_right", "top_right": "bottom_right",
              "top_left": "bottom_left", "bottom_left": "top_left"}
    for (cx, cy), name, a0 in corners:
        sx, sy = (1 if cx > 0 else -1), (1 if cy > 0 else -1)
        if screen[name] in chamfered and chamfer > 0:
            c = min(chamfer, hw, hh)
            # entering along the previous edge, leaving along the next (CCW order)
            p_in = (cx, cy - sy * c) if sx * sy > 0 else (cx - sx * c, cy)
            p_out = (cx - sx * c, cy) if sx * sy > 0 else (cx, cy - sy * c)
            out += [p_in, p_out]
        elif r > 1e-12:
            ox, oy = cx - sx * r, cy - sy * r
            t = np.radians(a0 + np.linspace(0.0, 90.0, _ARC_SEGMENTS + 1))
            out += list(zip(ox + r * np.cos(t), oy + r * np.sin(t)))
        else:
            out.append((cx, cy))
    return np.array(out, dtype=np.float64)


def _pad_outline(doc: SexprDoc, pad: list, shape: str, size: tuple[float, float]
                 ) -> np.ndarray:
    """Pad outline in its own frame, y up, centred on the pad's ``at`` point."""
    w, h = size
    if shape == "rect":
        return _rounded_rect(w, h, 0.0)
    if shape == "roundrect":
        rr = _item(pad, "roundrect_rratio")
        ratio = _num(doc, rr, 1, "ratio") if rr is not None else 0.25
        ch = _item(pad, "chamfer_ratio")
        corners = _item(pad, "chamfer")
        chamfered = frozenset(str(c) for c in corners[1:]) if corners is not None \
            else frozenset()
        cr = _num(doc, ch, 1, "ratio") * min(w, h) if ch is not None else 0.0
        return _rounded_rect(w, h, ratio * min(w, h), cr, chamfered)
    if shape == "oval":
        return _rounded_rect(w, h, min(w, h) / 2.0)
    if shape == "circle":
        t = np.linspace(0, 2 * math.pi, _CIRCLE_SEGMENTS, endpoint=False)
        return np.column_stack([w / 2 * np.cos(t), w / 2 * np.sin(t)])
    if shape == "trapezoid":
        d = _item(pad, "rect_delta")
        dx = _num(doc, d, 1, "dx", 0.0) / 2 if d is not None else 0.0
        dy = _num(doc, d, 2, "dy", 0.0) / 2 if d is not None else 0.0
        hw, hh = w / 2, h / 2
        screen = [(-hw - dy, hh + dx), (hw + dy, hh - dx), (hw - dy, -hh + dx),
                  (-hw + dy, -hh - dx)]
        return _yup(screen)
    if shape == "custom":
        prims = _item(pad, "primitives")
        items = [p for p in (prims[1:] if prims else []) if isinstance(p, list)]
        polys = [p for p in items if _head(p) in ("gr_poly", "gr_rect", "gr_circle")]
        if len(items) != 1 or len(polys) != 1:
            raise _Unmodelled(f"custom pad {pad[1]!r} has {len(items)} primitives; only "
                              f"one polygon, rectangle or circle is modelled")
        prim = polys[0]
        if _head(prim) == "gr_rect":
            a = _xy(doc, _item(prim, "start"), "start")
            b = _xy(doc, _item(prim, "end"), "end")
            pts = [(a[0], a[1]), (b[0], a[1]), (b[0], b[1]), (a[0], b[1])]
        elif _head(prim) == "gr_circle":
            pts = _shape_points(doc, prim)
        else:
            pts = _pts(doc, _item(prim, "pts"), prim)
        return _yup(pts)
    raise doc.error(pad, f"pad {pad[1]!r}: unknown pad shape {shape!r}")


class _Unmodelled(Exception):
    """A footprint we skip (with this reason), not a broken file."""


# --------------------------------------------------------------------------------------
# Footprints.
# --------------------------------------------------------------------------------------


def _placement(doc: SexprDoc, fp: list) -> tuple[np.ndarray, float]:
    at = _item(fp, "at")
    if at is None:
        raise doc.error(fp, "footprint without (at x y [angle])")
    x, y = _num(doc, at, 1, "x"), _num(doc, at, 2, "y")
    angle = _num(doc, at, 3, "angle", 0.0) if len(at) > 3 and not isinstance(at[3], str) \
        else 0.0
    return np.array([x, y]), angle


def _text(fp: list, field: str) -> str | None:
    for t in _items(fp, "fp_text"):
        if len(t) > 2 and str(t[1]) == field:
            return str(t[2])
    for p in _items(fp, "property"):
        if len(p) > 2 and str(p[1]).lower() == field:
            return str(p[2])
    return None


def _attrs(fp: list) -> set[str]:
    a = _item(fp, "attr")
    return {str(x) for x in a[1:]} if a is not None else set()


def _copper_pads(doc: SexprDoc, fp: list, fp_angle: float):
    """Copper pads on F.Cu: (number, kind, outline in the footprint frame y up, node)."""
    pads = []
    for pad in _items(fp, "pad"):
        if len(pad) < 4:
            raise doc.error(pad, "pad needs a number, a type and a shape")
        number, kind, shape = str(pad[1]), str(pad[2]), str(pad[3])
        layers = _item(pad, "layers")
        names = {str(x) for x in layers[1:]} if layers is not None else set()
        copper = bool(names & {"F.Cu", "*.Cu", "F&B.Cu"})
        if kind in ("thru_hole", "np_thru_hole"):
            pads.append((number, kind, None, pad))
            continue
        if not copper or kind not in ("smd", "connect"):
            continue  # paste/mask-only apertures are not joints
        at = _item(pad, "at")
        px, py = _xy(doc, at, "pad at")
        pad_angle = float(at[3]) if len(at) > 3 and isinstance(at[3], (int, float)) \
            and not isinstance(at[3], bool) else 0.0
        size = _item(pad, "size")
        w, h = _num(doc, size, 1, "size x") if size else 0.0, \
            _num(doc, size, 2, "size y", _num(doc, size, 1, "size x")) if size else 0.0
        if shape != "custom" and (w <= 0 or h <= 0):
            raise doc.error(pad, f"pad {number!r}: size must be > 0; got {w} x {h}")
        outline = _pad_outline(doc, pad, shape, (w, h))
        local_angle = pad_angle - fp_angle
        outline = outline @ _rot(local_angle).T + np.array([px, -py])
        pads.append((number, kind, outline, pad))
    return pads


def _orient(kind: str, centres: dict[str, np.ndarray], body: dict[str, float],
            sides: int) -> float | None:
    """Rotation α (deg) of the footprint frame from the board-model component frame."""
    L, W = body["length_mm"], body["width_mm"]
    pts = np.array(list(centres.values()))
    first = centres.get("1")
    for alpha in (0.0, -90.0, 90.0, 180.0):
        ours = pts @ _rot(-alpha).T
        p1 = first @ _rot(-alpha).T if first is not None else None
        if kind == "chip":
            if np.ptp(ours[:, 0]) + 1e-9 < np.ptp(ours[:, 1]):
                continue
            if p1 is not None and p1[0] > 0:
                continue
            return alpha
        # Gull-wing: every pad on a row of the body's long sides (2 sides) or pin 1 on
        # the bottom side, left of centre.
        on_y = np.abs(ours[:, 1]) * L > np.abs(ours[:, 0]) * W
        if sides == 2 and not on_y.all():
            continue
        if p1 is not None:
            if not (p1[1] < 0 and abs(p1[1]) * L > abs(p1[0]) * W and p1[0] < 1e-9):
                continue
        return alpha
    return None


def _local_pad(number: str, poly: np.ndarray, kind: str, body: dict[str, float]
               ) -> dict[str, Any]:
    """A pad in the board file's component frame: a rectangle when it is one, else a polygon."""
    poly = np.where(np.abs(poly) < 5e-10, 0.0, poly)
    if len(poly) == 4:
        xs, ys = np.unique(np.round(poly[:, 0], 9)), np.unique(np.round(poly[:, 1], 9))
        if len(xs) == 2 and len(ys) == 2:
            cx, cy = float(xs.mean()), float(ys.mean())
            ex, ey = float(xs[1] - xs[0]), float(ys[1] - ys[0])
            if kind == "chip":
                axis = 0
            else:
                axis = 1 if abs(cy) * body["length_mm"] > abs(cx) * body["width_mm"] else 0
            length, width = (ex, ey) if axis == 0 else (ey, ex)
            return {"number": number, "x_mm": _c(cx), "y_mm": _c(cy),
                    "length_mm": _c(length), "width_mm": _c(width)}
    return {"number": number, "polygon_mm": [[_c(x), _c(y)] for x, y in poly]}


def _c(v: float) -> float:
    v = round(float(v), 7)
    return 0.0 if v == 0 else v


def read_kicad_pcb(path: str | Path, *, packages: PackageTable | None = None):
    """Read a KiCad 6–9 board file into a board-file dict.

    Parameters
    ----------
    path : str or Path
        The ``.kicad_pcb`` file.
    packages : PackageTable, optional
        Extra footprint-name → package rules, searched before the built-in ones.

    Returns
    -------
    (dict, list of dict, dict)
        The board-file dict (schema ``smdinspect-board`` v1, not yet validated), the
        skipped footprints (``ref``, ``footprint``, ``line``, ``reason``) and facts about
        the import (``kicad_version``, ``format_version``, ``lines`` of each reference).

    Raises
    ------
    InputError
        ``FILE:LINE: problem`` for syntax errors and malformed items.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read KiCad board: {exc}") from None
    doc = parse_sexpr(text, source=str(p))
    root = doc.root
    if _head(root) != "kicad_pcb":
        raise doc.error(root, f"not a KiCad board file: top-level item is "
                              f"({_head(root) or root[:1]!r} ...), expected (kicad_pcb ...)")
    ver = _item(root, "version")
    version = int(_num(doc, ver, 1, "version")) if ver is not None else 0
    if version < KICAD_VERSIONS[6] or _items(root, "module"):
        raise doc.error(ver if ver is not None else root,
                        f"board format {version} is older than KiCad 6 (20211014); open "
                        f"and save the board in KiCad 6 or newer")
    release = kicad_release(version)
    notes = []
    if version > KICAD_VERSIONS[9]:
        notes.append(f"format {version} is newer than KiCad 9; read as KiCad 9")

    outline = _outline_points(doc)
    x0, y_top = float(outline[:, 0].min()), float(outline[:, 1].max())
    width = float(outline[:, 0].max() - x0)
    height = float(y_top - outline[:, 1].min())
    if width <= 0 or height <= 0:
        raise InputError(f"{doc.source}:1: the Edge.Cuts outline has no area "
                         f"({width:.3f} x {height:.3f} mm)")

    def to_board(pt_kicad) -> tuple[float, float]:
        return float(pt_kicad[0] - x0), float(y_top - pt_kicad[1])

    general = _item(root, "general")
    thick = _item(general, "thickness") if general is not None else None
    thickness = _num(doc, thick, 1, "thickness") if thick is not None else 1.6

    comps, fids, skipped = [], [], []
    lines: dict[str, int | None] = {}
    seen: set[str] = set()
    for fp in _items(root, "footprint"):
        name = str(fp[1]) if len(fp) > 1 else ""
        base = footprint_base(name)
        ref = _text(fp, "reference") or "?"
        line = doc.line(fp)
        lines[ref] = line

        def skip(reason: str) -> None:
            skipped.append({"ref": ref, "footprint": name, "line": line, "reason": reason})

        side = _layer(fp)
        origin, angle = _placement(doc, fp)
        attrs = _attrs(fp)
        if side != "F.Cu":
            skip(f"bottom side ({side})" if side == "B.Cu" else f"on layer {side}")
            continue
        if ref in seen:
            skip(f"duplicate reference {ref!r}")
            continue
        if "." in ref or ref == "?":
            skip(f"reference {ref!r} cannot name joints (empty or contains '.')")
            continue
        if "dnp" in attrs:
            skip("marked do-not-populate (dnp)")
            continue
        try:
            pads = _copper_pads(doc, fp, angle)
        except _Unmodelled as exc:
            skip(str(exc))
            continue
        if base.lower().startswith("fiducial"):
            smd = [q for q in pads if q[2] is not None]
            if len(smd) != 1:
                skip(f"fiducial with {len(smd)} copper pads (one round pad expected)")
                continue
            poly = smd[0][2]
            d = float(max(np.ptp(poly[:, 0]), np.ptp(poly[:, 1])))
            c = (poly.max(axis=0) + poly.min(axis=0)) / 2.0
            centre = _yup(_yup(c) @ _rot(angle).T)[0] + origin  # footprint → KiCad frame
            bx, by = to_board(centre)
            fids.append({"id": ref, "x_mm": _c(bx), "y_mm": _c(by), "diameter_mm": _c(d)})
            seen.add(ref)
            continue
        if "board_only" in attrs and "smd" not in attrs:
            skip("board-only footprint (not a placed part)")
            continue
        holes = [q for q in pads if q[2] is None]
        if holes or "through_hole" in attrs:
            skip("through-hole footprint" if "through_hole" in attrs or
                 any(q[1] == "thru_hole" for q in holes) else "footprint with holes")
            continue
        if not pads:
            skip("no SMD copper pads on F.Cu")
            continue
        numbers = [q[0] for q in pads]
        dup = sorted({n for n in numbers if numbers.count(n) > 1})
        if dup:
            skip(f"several copper pads share number {dup[0]!r} (one joint per pad number)")
            continue
        if "" in numbers:
            skip("a copper pad without a number")
            continue
        match = match_package(name, ref=ref, table=packages)
        if isinstance(match, str):
            skip(match)
            continue
        comp, why = _component(ref, match, pads, origin, angle, to_board)
        if comp is None:
            skip(why)
            continue
        corners = np.array([pt for pd in comp.pop("_board_pts") for pt in pd])
        if (corners[:, 0].min() < -1e-9 or corners[:, 1].min() < -1e-9
                or corners[:, 0].max() > width + 1e-9 or corners[:, 1].max() > height + 1e-9):
            skip("pads outside the Edge.Cuts outline")
            continue
        seen.add(ref)
        comps.append(comp)

    data = {
        "schema": "smdinspect-board", "version": 1, "name": p.stem, "units": "mm",
        "size_mm": [_c(width), _c(height)], "thickness_mm": thickness,
        "fiducials": fids, "components": comps,
    }
    info = {"format": "kicad_pcb", "kicad_version": release, "format_version": version,
            "lines": lines, "notes": notes,
            "origin_kicad_mm": [_c(x0), _c(y_top)]}
    return data, skipped, info


def _component(ref: str, match: PackageMatch, pads, origin: np.ndarray, angle: float,
               to_board) -> tuple[dict | None, str]:
    centres = {n: (poly.max(axis=0) + poly.min(axis=0)) / 2.0 for n, _, poly, _ in pads}
    if match.kind == "chip" and len(pads) != 2:
        return None, f"{match.package} chip footprint with {len(pads)} copper pads (2 expected)"
    if match.kind == "gullwing" and match.pins and len(pads) != match.pins:
        return None, (f"{match.package}: footprint has {len(pads)} copper pads, the package "
                      f"{match.pins} pins")
    alpha = _orient(match.kind, centres, match.body, match.sides)
    if alpha is None:
        return None, (f"cannot orient {match.package}: pads do not sit on the body's sides "
                      f"as the package expects (pin 1 first)")
    bx, by = to_board(origin)
    rotation = (angle + alpha + 180.0) % 360.0 - 180.0
    if math.isclose(rotation, -180.0):
        rotation = 180.0
    out_pads, board_pts = [], []
    r_board = _rot(angle)
    for number, _, poly, _ in pads:
        local = poly @ _rot(-alpha).T
        out_pads.append(_local_pad(number, local, match.kind, match.body))
        board_pts.append(poly @ r_board.T + np.array([bx, by]))
    comp = {"ref": ref, "package": match.package, "kind": match.kind, "style": match.style,
            "x_mm": _c(bx), "y_mm": _c(by), "rotation_deg": _c(rotation),
            "body": dict(match.body), "pads": out_pads, "_board_pts": board_pts}
    if match.lead is not None:
        comp["lead"] = dict(match.lead)
    return comp, ""
