"""Reference boards: the board file format, its loader and the package defaults.

A board file (``references/*.json``, schema in ``references/README.md``) lists the
board's size, fiducials and components with their pads. The same file drives the
simulator (:func:`smdinspect.synth.board_scene`) and the inspection.

Board frame: origin at the board's lower-left corner, x right, y up, mm; z = 0 on the
board's top surface (solder mask and pad tops), z up. A component's local frame has its
origin at the body centre, x along the body length; ``BOARD = R(rotation_deg) · LOCAL +
(x_mm, y_mm)`` with counter-clockwise rotation.

Joint acceptance bands default to IPC-A-610 Class 2 fillet-height rules (see
:func:`joint_band` and ``references/README.md``).
"""

from __future__ import annotations

import copy
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .._json import read_json
from ..errors import InputError

__all__ = [
    "BOARD_SCHEMA",
    "BOARD_VERSION",
    "PACKAGES",
    "Board",
    "Component",
    "Fiducial",
    "Joint",
    "MAX_BOARD_SIDE_MM",
    "board_from_dict",
    "check_board_in_field",
    "joint_band",
    "load_board",
    "package_defaults",
    "polygons_overlap",
]

log = logging.getLogger(__name__)

BOARD_SCHEMA = "smdinspect-board"
BOARD_VERSION = 1
#: Largest board side accepted (mm); production panels are at most about 610 mm.
MAX_BOARD_SIDE_MM = 1000.0

_KINDS = ("chip", "gullwing")
_STYLES = ("resistor", "capacitor", "ic")
_TERMINATION = {"chip": "chip_end", "gullwing": "gullwing_heel"}

# --------------------------------------------------------------------------------------
# Package defaults.
#
# Chips: body length L, width W, termination (end-cap) length, body height per style
# (thick-film resistors are thinner than MLCCs), from the nominal values of common
# datasheet ranges (Yageo RC / Murata GRM series). Pads: IPC-7351-like nominal lands;
# "pad" gives the pad length along the component axis, its width across, and the
# distance of the pad centre from the body centre.
#
# Gull-wing: JEDEC MS-012 (SOIC), MO-153 (TSSOP), MS-026 (LQFP) nominal dimensions.
# "body" length is along the pin rows of the first pin side (local x), width across.
# "lead": width b, thickness T, foot length L, tip-to-tip span E, height above the
# board at which the lead leaves the mould ("exit_height_mm"), solder thickness G under
# the foot. Pads: IPC-7351-like (SOIC127P600X175 etc.).
# --------------------------------------------------------------------------------------

PACKAGES: dict[str, dict[str, Any]] = {
    "0402": {
        "kind": "chip",
        "body": {"length_mm": 1.00, "width_mm": 0.50, "standoff_mm": 0.03,
                 "termination_length_mm": 0.25},
        "height_mm": {"resistor": 0.35, "capacitor": 0.50},
        "pad": {"length_mm": 0.52, "width_mm": 0.62, "center_mm": 0.46},
    },
    "0603": {
        "kind": "chip",
        "body": {"length_mm": 1.60, "width_mm": 0.80, "standoff_mm": 0.03,
                 "termination_length_mm": 0.30},
        "height_mm": {"resistor": 0.45, "capacitor": 0.80},
        "pad": {"length_mm": 0.80, "width_mm": 0.95, "center_mm": 0.78},
    },
    "0805": {
        "kind": "chip",
        "body": {"length_mm": 2.00, "width_mm": 1.25, "standoff_mm": 0.03,
                 "termination_length_mm": 0.40},
        "height_mm": {"resistor": 0.50, "capacitor": 0.85},
        "pad": {"length_mm": 1.00, "width_mm": 1.40, "center_mm": 0.95},
    },
    "1206": {
        "kind": "chip",
        "body": {"length_mm": 3.20, "width_mm": 1.60, "standoff_mm": 0.03,
                 "termination_length_mm": 0.50},
        "height_mm": {"resistor": 0.55, "capacitor": 1.15},
        "pad": {"length_mm": 1.15, "width_mm": 1.80, "center_mm": 1.45},
    },
    "SOIC-8": {
        "kind": "gullwing",
        "body": {"length_mm": 4.90, "width_mm": 3.90, "height_mm": 1.50, "standoff_mm": 0.15},
        "lead": {"width_mm": 0.42, "thickness_mm": 0.20, "foot_length_mm": 0.84,
                 "span_mm": 6.00, "exit_height_mm": 0.80, "solder_thickness_mm": 0.03},
        "pins": 8, "pitch_mm": 1.27, "sides": 2,
        "pad": {"length_mm": 1.55, "width_mm": 0.60, "center_mm": 2.70},
    },
    "SOIC-16": {
        "kind": "gullwing",
        "body": {"length_mm": 9.90, "width_mm": 3.90, "height_mm": 1.50, "standoff_mm": 0.15},
        "lead": {"width_mm": 0.42, "thickness_mm": 0.20, "foot_length_mm": 0.84,
                 "span_mm": 6.00, "exit_height_mm": 0.80, "solder_thickness_mm": 0.03},
        "pins": 16, "pitch_mm": 1.27, "sides": 2,
        "pad": {"length_mm": 1.55, "width_mm": 0.60, "center_mm": 2.70},
    },
    "TSSOP-8": {
        "kind": "gullwing",
        "body": {"length_mm": 3.00, "width_mm": 4.40, "height_mm": 1.05, "standoff_mm": 0.10},
        "lead": {"width_mm": 0.25, "thickness_mm": 0.15, "foot_length_mm": 0.60,
                 "span_mm": 6.40, "exit_height_mm": 0.55, "solder_thickness_mm": 0.03},
        "pins": 8, "pitch_mm": 0.65, "sides": 2,
        "pad": {"length_mm": 1.45, "width_mm": 0.40, "center_mm": 2.85},
    },
    "LQFP-32": {
        "kind": "gullwing",
        "body": {"length_mm": 7.00, "width_mm": 7.00, "height_mm": 1.50, "standoff_mm": 0.10},
        "lead": {"width_mm": 0.37, "thickness_mm": 0.15, "foot_length_mm": 0.60,
                 "span_mm": 9.00, "exit_height_mm": 0.75, "solder_thickness_mm": 0.03},
        "pins": 32, "pitch_mm": 0.80, "sides": 4,
        "pad": {"length_mm": 1.50, "width_mm": 0.55, "center_mm": 4.15},
    },
}


def package_defaults(package: str, *, style: str | None = None) -> dict[str, Any]:
    """Default geometry of a known package as a component dict fragment.

    Parameters
    ----------
    package : str
        One of :data:`PACKAGES` (``"0402"``, ``"0603"``, ``"0805"``, ``"1206"``,
        ``"SOIC-8"``, ``"SOIC-16"``, ``"TSSOP-8"``, ``"LQFP-32"``).
    style : str, optional
        ``"resistor"`` or ``"capacitor"`` for chips (sets the body height);
        ignored for gull-wing parts.

    Returns
    -------
    dict
        ``{"kind", "style", "body": {...}, "lead": {...} or None, "pads": [...]}`` with
        pads in the component's local frame, numbered as on the part (gull-wing: pin 1
        at local (-x, -y), counter-clockwise seen from the top).
    """
    if package not in PACKAGES:
        raise InputError(f"unknown package {package!r}; known: {', '.join(PACKAGES)}")
    spec = PACKAGES[package]
    kind = spec["kind"]
    body = dict(spec["body"])
    if kind == "chip":
        style = style or "resistor"
        if style not in spec["height_mm"]:
            raise InputError(f"style must be one of resistor, capacitor for package "
                             f"{package}; got {style!r}")
        body["height_mm"] = spec["height_mm"][style]
        pad = spec["pad"]
        pads = [
            {"number": "1", "x_mm": -pad["center_mm"], "y_mm": 0.0,
             "length_mm": pad["length_mm"], "width_mm": pad["width_mm"]},
            {"number": "2", "x_mm": pad["center_mm"], "y_mm": 0.0,
             "length_mm": pad["length_mm"], "width_mm": pad["width_mm"]},
        ]
        return {"kind": kind, "style": style, "body": body, "lead": None, "pads": pads}
    pad = spec["pad"]
    n, pitch, sides = spec["pins"], spec["pitch_mm"], spec["sides"]
    per_side = n // sides
    offsets = (np.arange(per_side) - (per_side - 1) / 2.0) * pitch
    c = pad["center_mm"]
    pads = []
    number = 1
    # Counter-clockwise from pin 1 at the lower-left: bottom side left→right, then (for
    # four sides) right side bottom→top, top side right→left, left side top→bottom.
    side_xy = [
        lambda o: (o, -c),
        lambda o: (c, o),
        lambda o: (-o, c),
        lambda o: (-c, -o),
    ]
    order = [0, 2] if sides == 2 else [0, 1, 2, 3]
    for side in order:
        for o in offsets:
            x, y = side_xy[side](float(o))
            pads.append({"number": str(number), "x_mm": round(x, 6), "y_mm": round(y, 6),
                         "length_mm": pad["length_mm"], "width_mm": pad["width_mm"]})
            number += 1
    return {"kind": kind, "style": "ic", "body": body, "lead": dict(spec["lead"]),
            "pads": pads}


def joint_band(kind: str, *, body_height_mm: float, standoff_mm: float,
               lead: dict | None = None) -> tuple[float, float, float]:
    """Default (nominal, min, max) fillet height in mm above the pad (IPC-A-610 Class 2).

    Chip end joints (1, 3 or 5-sided terminations), termination height ``H`` = body
    height, solder thickness ``G`` = ``standoff_mm``:
    min ``F = G + min(0.25·H, 0.5 mm)``; max ``E = G + H`` (the fillet may reach the top
    of the end cap but not extend onto the body top); nominal ``G + 0.6·H``.

    Gull-wing heel joints, lead thickness ``T``, ``G = lead["solder_thickness_mm"]``:
    min ``F = G + 0.5·T``; max: the heel fillet may climb into the bend but must not
    touch the body, taken as 60 % of the way from the lead top at the heel (``G + T``)
    to the height at which the lead leaves the mould; nominal ``G + T + 0.05 mm``.
    """
    if kind == "chip":
        g, h = float(standoff_mm), float(body_height_mm)
        return _r(g + 0.6 * h), _r(g + min(0.25 * h, 0.5)), _r(g + h)
    if kind == "gullwing":
        if lead is None:
            raise InputError("a gull-wing joint band needs the lead geometry")
        g = float(lead.get("solder_thickness_mm", 0.03))
        t = float(lead["thickness_mm"])
        exit_h = float(lead["exit_height_mm"])
        top = g + t
        hi = top + 0.6 * max(exit_h - top, 0.0)
        nominal = min(top + 0.05, 0.5 * (top + hi))
        return _r(nominal), _r(g + 0.5 * t), _r(hi)
    raise InputError(f"kind must be one of {', '.join(_KINDS)}; got {kind!r}")


def _r(x: float) -> float:
    return round(float(x), 4)


# --------------------------------------------------------------------------------------
# Data model.
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Fiducial:
    """A round fiducial mark (bare copper in a solder-mask opening), board frame."""

    id: str
    x_mm: float
    y_mm: float
    diameter_mm: float


@dataclass(frozen=True, eq=False)
class Joint:
    """The solder joint of one pad.

    Attributes
    ----------
    id : str
        ``"R3.1"``: component reference + ``"."`` + pad number.
    component, pad_number : str
    center_mm : (float, float)
        Pad centre (centroid of the outline) in the BOARD frame.
    polygon_mm : (N, 2) float64
        Pad outline in the BOARD frame, counter-clockwise (rectangles: 4 corners).
    nominal_height_mm, min_height_mm, max_height_mm : float
        Nominal fillet height above the pad surface (z = 0) and the acceptance band of
        the joint's maximum solder height.
    termination : str
        ``"chip_end"`` or ``"gullwing_heel"``.
    outward : (float, float)
        Unit vector in the BOARD frame pointing from the component towards the pad's
        outer (toe) edge: the direction in which the fillet falls off.
    spec : dict
        The pad as written in the board file (component-local), used by
        :meth:`Board.to_dict`.
    """

    id: str
    component: str
    pad_number: str
    center_mm: tuple[float, float]
    polygon_mm: np.ndarray
    nominal_height_mm: float
    min_height_mm: float
    max_height_mm: float
    termination: str
    outward: tuple[float, float] = (1.0, 0.0)
    spec: dict = field(default_factory=dict, repr=False)


@dataclass(frozen=True, eq=False)
class Component:
    """One placed component.

    ``x_mm, y_mm, rotation_deg`` place the body centre in the BOARD frame; body length
    is along local x. ``lead`` is the gull-wing lead geometry (``width_mm``,
    ``thickness_mm``, ``foot_length_mm``, ``span_mm``, ``exit_height_mm``,
    ``solder_thickness_mm``) or ``None`` for chips; ``termination_length_mm`` is the
    end-cap length of a chip (0 for gull-wing parts); ``style`` is ``"resistor"``,
    ``"capacitor"`` or ``"ic"`` (the look of the body in the simulator).
    """

    ref: str
    package: str
    kind: str
    x_mm: float
    y_mm: float
    rotation_deg: float
    body_length_mm: float
    body_width_mm: float
    body_height_mm: float
    standoff_mm: float
    lead: dict | None
    joints: tuple[Joint, ...]
    termination_length_mm: float = 0.0
    style: str = "resistor"

    def to_board(self, xy_local) -> np.ndarray:
        """Component-local points ``(N, 2)`` mm → BOARD frame ``(N, 2)`` mm."""
        pts = np.asarray(xy_local, dtype=np.float64).reshape(-1, 2)
        return pts @ _rot(self.rotation_deg).T + np.array([self.x_mm, self.y_mm])

    def to_local(self, xy_board) -> np.ndarray:
        """BOARD frame points ``(N, 2)`` mm → component-local ``(N, 2)`` mm."""
        pts = np.asarray(xy_board, dtype=np.float64).reshape(-1, 2)
        return (pts - np.array([self.x_mm, self.y_mm])) @ _rot(self.rotation_deg)

    def body_polygon_mm(self) -> np.ndarray:
        """``(4, 2)`` float64 outline of the body (mould or ceramic) in the BOARD frame."""
        hl, hw = self.body_length_mm / 2.0, self.body_width_mm / 2.0
        return self.to_board([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])

    def termination_polygon_mm(self, joint_id: str) -> np.ndarray:
        """``(4, 2)`` outline (BOARD frame) of the metal that sits on the joint's pad.

        Chips: the end cap (body width × termination length at the body end facing the
        pad). Gull-wing: the lead from where it leaves the mould to its toe.
        The visible solder area of a joint is its pad minus this and the body outline.
        """
        joint = self._joint(joint_id)
        loc = self.to_local([joint.center_mm])[0]
        axis, sign = _pad_axis(loc, self.body_length_mm, self.body_width_mm, self.kind)
        if self.kind == "chip":
            hl, hw, t = self.body_length_mm / 2.0, self.body_width_mm / 2.0, \
                self.termination_length_mm
            u0, u1, v0, v1 = hl - t, hl, -hw, hw
            across = 0.0
        else:
            lead = self.lead or {}
            half_body = (self.body_width_mm if axis == 1 else self.body_length_mm) / 2.0
            u0, u1 = half_body, float(lead["span_mm"]) / 2.0
            hw = float(lead["width_mm"]) / 2.0
            across = float(loc[1 - axis])
            v0, v1 = -hw, hw
        quad = []
        for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)):
            p = [0.0, 0.0]
            p[axis] = sign * u
            p[1 - axis] = across + v
            quad.append(p)
        return self.to_board(_ccw(np.array(quad)))

    def _joint(self, joint_id: str) -> Joint:
        for j in self.joints:
            if j.id == joint_id:
                return j
        raise InputError(f"component {self.ref} has no joint {joint_id!r}; joints: "
                         f"{', '.join(j.id for j in self.joints)}")


@dataclass(frozen=True, eq=False)
class Board:
    """A reference board loaded from a board file (see :func:`load_board`)."""

    name: str
    size_mm: tuple[float, float]
    thickness_mm: float
    fiducials: tuple[Fiducial, ...]
    components: tuple[Component, ...]
    source: str = ""

    def outline_mm(self) -> np.ndarray:
        """The board's rectangle in the BOARD frame, (4, 2) counter-clockwise from (0, 0)."""
        w, h = self.size_mm
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])

    def joints(self) -> list[Joint]:
        """All joints, in file order (components, then pads)."""
        return [j for c in self.components for j in c.joints]

    def joint(self, joint_id: str) -> Joint:
        """The joint with id ``joint_id`` (``"R3.1"``)."""
        for j in self.joints():
            if j.id == joint_id:
                return j
        ids = [j.id for j in self.joints()]
        raise InputError(f"board {self.name} has no joint {joint_id!r}; e.g. "
                         f"{', '.join(ids[:6])}")

    def component(self, ref: str) -> Component:
        """The component with reference designator ``ref``."""
        for c in self.components:
            if c.ref == ref:
                return c
        raise InputError(f"board {self.name} has no component {ref!r}; components: "
                         f"{', '.join(c.ref for c in self.components)}")

    def to_dict(self) -> dict[str, Any]:
        """The board as a board-file dict; ``board_from_dict(b.to_dict())`` rebuilds it."""
        comps = []
        for c in self.components:
            body = {"length_mm": c.body_length_mm, "width_mm": c.body_width_mm,
                    "height_mm": c.body_height_mm, "standoff_mm": c.standoff_mm}
            if c.kind == "chip":
                body["termination_length_mm"] = c.termination_length_mm
            d: dict[str, Any] = {
                "ref": c.ref, "package": c.package, "kind": c.kind, "style": c.style,
                "x_mm": c.x_mm, "y_mm": c.y_mm, "rotation_deg": c.rotation_deg,
                "body": body,
            }
            if c.lead is not None:
                d["lead"] = dict(c.lead)
            pads = []
            for j in c.joints:
                p = {k: copy.deepcopy(v) for k, v in j.spec.items() if k != "joint"}
                p["joint"] = {"nominal_height_mm": j.nominal_height_mm,
                              "min_height_mm": j.min_height_mm,
                              "max_height_mm": j.max_height_mm}
                pads.append(p)
            d["pads"] = pads
            comps.append(d)
        return {
            "schema": BOARD_SCHEMA, "version": BOARD_VERSION, "name": self.name,
            "units": "mm", "size_mm": [self.size_mm[0], self.size_mm[1]],
            "thickness_mm": self.thickness_mm,
            "fiducials": [{"id": f.id, "x_mm": f.x_mm, "y_mm": f.y_mm,
                           "diameter_mm": f.diameter_mm} for f in self.fiducials],
            "components": comps,
        }


# --------------------------------------------------------------------------------------
# Loading and validation.
# --------------------------------------------------------------------------------------


def load_board(path: str | os.PathLike) -> Board:
    """Load and validate a board file.

    Parameters
    ----------
    path : str or PathLike
        A JSON board file (schema ``smdinspect-board`` version 1, see
        ``references/README.md``), or the name of a board shipped with smdinspect
        (``"demo_board"``; the repository's ``references/`` too).

    Returns
    -------
    Board

    Raises
    ------
    InputError
        One line naming the file, the component or joint and the problem, for any
        unreadable file, bad JSON, missing field, wrong type, non-positive size, unknown
        units, duplicate reference, pad outside the board or overlapping pads.
    """
    p = Path(path)
    if not p.is_file():
        p = _shipped_board(str(path)) or p
    if not p.is_file():
        shipped = ", ".join(sorted(q.stem for d in _SHIPPED_DIRS if d.is_dir()
                                   for q in d.glob("*.json")))
        raise InputError(f"board file {str(path)!r} does not exist or is not a file "
                         f"(boards shipped by name: {shipped or 'none'})")
    return board_from_dict(read_json(p), source=str(p))


#: Folders of the boards :func:`load_board` takes by name: the repository's, the package's.
_SHIPPED_DIRS = (Path(__file__).resolve().parents[2] / "references",
                 Path(__file__).resolve().parents[1] / "data")


def _shipped_board(name: str) -> Path | None:
    if Path(name).name != name or name.startswith("."):
        return None  # a path, not a name
    stem = name.removesuffix(".json")
    return next((p for d in _SHIPPED_DIRS if (p := d / f"{stem}.json").is_file()), None)


def check_board_in_field(board: Board, shape_px: tuple[int, int], pixel_size_mm: float, *,
                         max_ratio: float = 4.0) -> None:
    """Refuse a board far larger than the measured field, before any work is done.

    A board more than ``max_ratio`` times the field's width or height cannot be located
    in it; the usual cause is a wrong ``size_mm`` or ``pixel_size_mm``. This also bounds
    what registration allocates (reference points grow with the board's area).

    Parameters
    ----------
    board : Board
    shape_px : (rows, cols)
        The measurement's size in pixels.
    pixel_size_mm : float
    """
    field_w, field_h = shape_px[1] * pixel_size_mm, shape_px[0] * pixel_size_mm
    w, h = board.size_mm
    if w > max_ratio * field_w or h > max_ratio * field_h:
        raise InputError(
            f"board {board.name!r} is {w:g} x {h:g} mm, more than {max_ratio:g} times the "
            f"measured field ({field_w:.3g} x {field_h:.3g} mm: {shape_px[1]} x {shape_px[0]} "
            f"px at {pixel_size_mm:g} mm): check the board's size_mm and the pixel size")


def board_from_dict(data: dict[str, Any], *, source: str = "<dict>") -> Board:
    """Build and validate a :class:`Board` from a parsed board-file dict.

    Errors are :class:`InputError` messages prefixed with ``source``.
    """
    v = _Validator(source)
    if not isinstance(data, dict):
        v.fail(f"top level must be a JSON object; got {type(data).__name__}")
    schema = data.get("schema")
    if schema != BOARD_SCHEMA:
        v.fail(f"'schema' must be {BOARD_SCHEMA!r}; got {schema!r}")
    version = data.get("version")
    if version != BOARD_VERSION:
        v.fail(f"'version' must be {BOARD_VERSION}; got {version!r}")
    name = v.string(data, "name", "board")
    units = v.require(data, "units", "board")
    if units != "mm":
        v.fail(f"unknown units {units!r}; only 'mm' is accepted")
    size = v.require(data, "size_mm", "board")
    if not isinstance(size, list) or len(size) != 2:
        v.fail(f"board: 'size_mm' must be [width, height]; got {size!r}")
    w = v.number(size[0], "board: size_mm[0] (width)", positive=True, most=MAX_BOARD_SIDE_MM)
    h = v.number(size[1], "board: size_mm[1] (height)", positive=True, most=MAX_BOARD_SIDE_MM)
    thickness = v.number(v.require(data, "thickness_mm", "board"), "board: thickness_mm",
                         positive=True)

    fids = []
    seen_fid: set[str] = set()
    raw_fids = data.get("fiducials", [])
    if not isinstance(raw_fids, list):
        v.fail(f"'fiducials' must be a list; got {type(raw_fids).__name__}")
    for i, f in enumerate(raw_fids):
        where = f"fiducial #{i + 1}"
        if not isinstance(f, dict):
            v.fail(f"{where} must be an object")
        fid = v.string(f, "id", where)
        where = f"fiducial {fid}"
        if fid in seen_fid:
            v.fail(f"duplicate fiducial id {fid!r}")
        seen_fid.add(fid)
        fx = v.number(v.require(f, "x_mm", where), f"{where}: x_mm")
        fy = v.number(v.require(f, "y_mm", where), f"{where}: y_mm")
        fd = v.number(v.require(f, "diameter_mm", where), f"{where}: diameter_mm",
                      positive=True)
        if fx - fd / 2 < 0 or fy - fd / 2 < 0 or fx + fd / 2 > w or fy + fd / 2 > h:
            v.fail(f"{where} at ({fx}, {fy}) mm lies outside the board (0..{w} x 0..{h} mm)")
        fids.append(Fiducial(fid, float(fx), float(fy), float(fd)))

    raw_comps = v.require(data, "components", "board")
    if not isinstance(raw_comps, list) or not raw_comps:
        v.fail("'components' must be a non-empty list")
    comps = []
    seen_ref: set[str] = set()
    for i, c in enumerate(raw_comps):
        comp = _component(v, c, i)
        if comp.ref in seen_ref:
            v.fail(f"duplicate component ref {comp.ref!r}")
        seen_ref.add(comp.ref)
        for j in comp.joints:
            poly = j.polygon_mm
            tol = 1e-9
            if (poly[:, 0].min() < -tol or poly[:, 1].min() < -tol
                    or poly[:, 0].max() > w + tol or poly[:, 1].max() > h + tol):
                v.fail(f"joint {j.id}: pad lies outside the board (0..{w} x 0..{h} mm); "
                       f"pad spans x {poly[:, 0].min():.3f}..{poly[:, 0].max():.3f}, "
                       f"y {poly[:, 1].min():.3f}..{poly[:, 1].max():.3f} mm")
        comps.append(comp)

    joints = [j for c in comps for j in c.joints]
    _check_overlaps(v, joints)
    for f in fids:
        for j in joints:
            if _circle_hits_polygon(f.x_mm, f.y_mm, f.diameter_mm / 2, j.polygon_mm):
                v.fail(f"fiducial {f.id} overlaps pad of joint {j.id}")
    return Board(name=name, size_mm=(float(w), float(h)), thickness_mm=float(thickness),
                 fiducials=tuple(fids), components=tuple(comps), source=source)


class _Validator:
    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, message: str):
        raise InputError(f"{self.source}: {message}")

    def require(self, d: dict, key: str, where: str):
        if key not in d:
            self.fail(f"{where}: missing field {key!r}")
        return d[key]

    def string(self, d: dict, key: str, where: str) -> str:
        val = self.require(d, key, where)
        if not isinstance(val, str) or not val.strip():
            self.fail(f"{where}: {key!r} must be a non-empty string; got {val!r}")
        return val

    def number(self, val: Any, what: str, *, positive: bool = False,
               nonnegative: bool = False, most: float | None = None) -> float:
        if isinstance(val, bool) or not isinstance(val, (int, float)) or \
                not math.isfinite(val):
            self.fail(f"{what} must be a finite number; got {val!r}")
        if positive and val <= 0:
            self.fail(f"{what} must be > 0; got {val!r}")
        if nonnegative and val < 0:
            self.fail(f"{what} must be >= 0; got {val!r}")
        if most is not None and val > most:
            self.fail(f"{what} must be <= {most:g} mm; got {val!r}")
        return float(val)


def _component(v: _Validator, c: Any, index: int) -> Component:
    if not isinstance(c, dict):
        v.fail(f"component #{index + 1} must be an object")
    ref = v.string(c, "ref", f"component #{index + 1}")
    if "." in ref:
        v.fail(f"component {ref}: 'ref' must not contain '.'")
    where = f"component {ref}"
    package = v.string(c, "package", where)
    known = PACKAGES.get(package)
    kind = c.get("kind", known["kind"] if known else None)
    if kind is None:
        v.fail(f"{where}: missing field 'kind' (package {package!r} is not a known package)")
    if kind not in _KINDS:
        v.fail(f"{where}: 'kind' must be one of {', '.join(_KINDS)}; got {kind!r}")
    if known and known["kind"] != kind:
        v.fail(f"{where}: package {package} is a {known['kind']} part; got kind {kind!r}")
    style = c.get("style")
    if style is None:
        style = "ic" if kind == "gullwing" else (
            "capacitor" if ref.upper().startswith("C") else "resistor")
    if style not in _STYLES:
        v.fail(f"{where}: 'style' must be one of {', '.join(_STYLES)}; got {style!r}")
    defaults = package_defaults(package, style=style if kind == "chip" else None) \
        if known else None

    x = v.number(v.require(c, "x_mm", where), f"{where}: x_mm")
    y = v.number(v.require(c, "y_mm", where), f"{where}: y_mm")
    rot = v.number(v.require(c, "rotation_deg", where), f"{where}: rotation_deg")

    body = c.get("body", defaults["body"] if defaults else None)
    if body is None:
        v.fail(f"{where}: missing field 'body' (package {package!r} has no defaults)")
    if not isinstance(body, dict):
        v.fail(f"{where}: 'body' must be an object")
    bd = dict(defaults["body"]) if defaults else {}
    bd.update(body)
    bl = v.number(v.require(bd, "length_mm", f"{where} body"), f"{where}: body length_mm",
                  positive=True)
    bw = v.number(v.require(bd, "width_mm", f"{where} body"), f"{where}: body width_mm",
                  positive=True)
    bh = v.number(v.require(bd, "height_mm", f"{where} body"), f"{where}: body height_mm",
                  positive=True)
    so = v.number(v.require(bd, "standoff_mm", f"{where} body"), f"{where}: body standoff_mm",
                  nonnegative=True)
    if so >= bh:
        v.fail(f"{where}: body standoff_mm ({so}) must be below height_mm ({bh})")
    term_len = 0.0
    lead = None
    if kind == "chip":
        term_len = v.number(v.require(bd, "termination_length_mm", f"{where} body"),
                            f"{where}: body termination_length_mm", positive=True)
        if term_len * 2 >= bl:
            v.fail(f"{where}: body termination_length_mm ({term_len}) must be less than "
                   f"half the body length ({bl})")
    else:
        raw_lead = c.get("lead", defaults["lead"] if defaults else None)
        if raw_lead is None:
            v.fail(f"{where}: missing field 'lead' (gull-wing part without package defaults)")
        if not isinstance(raw_lead, dict):
            v.fail(f"{where}: 'lead' must be an object")
        lead = dict(defaults["lead"]) if defaults else {"solder_thickness_mm": 0.03}
        lead.update(raw_lead)
        for key in ("width_mm", "thickness_mm", "foot_length_mm", "span_mm",
                    "exit_height_mm"):
            lead[key] = v.number(v.require(lead, key, f"{where} lead"),
                                 f"{where}: lead {key}", positive=True)
        lead["solder_thickness_mm"] = v.number(lead.get("solder_thickness_mm", 0.03),
                                               f"{where}: lead solder_thickness_mm",
                                               nonnegative=True)
        if lead["foot_length_mm"] * 2 >= lead["span_mm"]:
            v.fail(f"{where}: lead foot_length_mm ({lead['foot_length_mm']}) must be less "
                   f"than half of span_mm ({lead['span_mm']})")
        if lead["span_mm"] <= min(bl, bw):
            v.fail(f"{where}: lead span_mm ({lead['span_mm']}) does not reach outside the "
                   f"body ({bl} x {bw} mm)")

    raw_pads = c.get("pads", defaults["pads"] if defaults else None)
    if raw_pads is None:
        v.fail(f"{where}: missing field 'pads' (package {package!r} has no default land "
               f"pattern)")
    if not isinstance(raw_pads, list) or not raw_pads:
        v.fail(f"{where}: 'pads' must be a non-empty list")
    proto = Component(ref, package, kind, x, y, rot, bl, bw, bh, so, lead, (), term_len,
                      style)
    nominal, lo, hi = joint_band(kind, body_height_mm=bh, standoff_mm=so, lead=lead)
    joints = []
    seen_num: set[str] = set()
    for k, pad in enumerate(raw_pads):
        joints.append(_joint(v, proto, pad, k, seen_num, (nominal, lo, hi)))
    return Component(ref, package, kind, x, y, rot, bl, bw, bh, so, lead, tuple(joints),
                     term_len, style)


def _joint(v: _Validator, comp: Component, pad: Any, k: int, seen: set[str],
           band: tuple[float, float, float]) -> Joint:
    where = f"component {comp.ref} pad #{k + 1}"
    if not isinstance(pad, dict):
        v.fail(f"{where} must be an object")
    number = v.require(pad, "number", where)
    if isinstance(number, bool) or not isinstance(number, (str, int)) or str(number) == "":
        v.fail(f"{where}: 'number' must be a string or integer; got {number!r}")
    number = str(number)
    if number in seen:
        v.fail(f"component {comp.ref}: duplicate pad number {number!r}")
    seen.add(number)
    jid = f"{comp.ref}.{number}"
    where = f"joint {jid}"
    spec: dict[str, Any] = {"number": number}
    if "polygon_mm" in pad:
        raw = pad["polygon_mm"]
        if not isinstance(raw, list) or len(raw) < 3 or not all(
                isinstance(q, list) and len(q) == 2 for q in raw):
            v.fail(f"{where}: 'polygon_mm' must be a list of at least 3 [x, y] points")
        local = np.array([[v.number(q[0], f"{where}: polygon_mm x"),
                           v.number(q[1], f"{where}: polygon_mm y")] for q in raw])
        if not _is_simple(local):
            v.fail(f"{where}: pad polygon intersects itself")
        if abs(_signed_area(local)) < 1e-9:
            v.fail(f"{where}: pad polygon has zero area")
        spec["polygon_mm"] = [[float(a), float(b)] for a, b in local]
        local = _ccw(local)
        centre_local = _centroid(local)
    else:
        px = v.number(v.require(pad, "x_mm", where), f"{where}: x_mm")
        py = v.number(v.require(pad, "y_mm", where), f"{where}: y_mm")
        length = v.number(v.require(pad, "length_mm", where), f"{where}: length_mm",
                          positive=True)
        width = v.number(v.require(pad, "width_mm", where), f"{where}: width_mm",
                         positive=True)
        spec.update({"x_mm": px, "y_mm": py, "length_mm": length, "width_mm": width})
        axis, _ = _pad_axis((px, py), comp.body_length_mm, comp.body_width_mm, comp.kind)
        half = [0.0, 0.0]
        half[axis] = length / 2.0
        half[1 - axis] = width / 2.0
        local = np.array([[px - half[0], py - half[1]], [px + half[0], py - half[1]],
                          [px + half[0], py + half[1]], [px - half[0], py + half[1]]])
        centre_local = np.array([px, py])
    nominal, lo, hi = band
    if "joint" in pad:
        jd = pad["joint"]
        if not isinstance(jd, dict):
            v.fail(f"{where}: 'joint' must be an object")
        nominal = v.number(jd.get("nominal_height_mm", nominal), f"{where}: nominal_height_mm",
                           positive=True)
        lo = v.number(jd.get("min_height_mm", lo), f"{where}: min_height_mm", positive=True)
        hi = v.number(jd.get("max_height_mm", hi), f"{where}: max_height_mm", positive=True)
    if not lo < hi:
        v.fail(f"{where}: min_height_mm ({lo}) must be < max_height_mm ({hi})")
    if not lo <= nominal <= hi:
        v.fail(f"{where}: nominal_height_mm ({nominal}) must lie within "
               f"[{lo}, {hi}]")
    axis, sign = _pad_axis(centre_local, comp.body_length_mm, comp.body_width_mm, comp.kind)
    out_local = np.zeros(2)
    out_local[axis] = sign
    out_board = _rot(comp.rotation_deg) @ out_local
    poly = comp.to_board(local)
    centre = comp.to_board([centre_local])[0]
    return Joint(id=jid, component=comp.ref, pad_number=number,
                 center_mm=(float(centre[0]), float(centre[1])), polygon_mm=poly,
                 nominal_height_mm=float(nominal), min_height_mm=float(lo),
                 max_height_mm=float(hi), termination=_TERMINATION[comp.kind],
                 outward=(float(out_board[0]), float(out_board[1])), spec=spec)


def _pad_axis(xy_local, body_length: float, body_width: float, kind: str) -> tuple[int, int]:
    """(axis, sign) of the direction from the component towards a pad, local frame.

    Chips: always the body axis x. Gull-wing: the side of the body the pad sits on,
    i.e. the local axis along which the pad centre is farther out relative to the
    body's half size (ties go to x).
    """
    x, y = float(xy_local[0]), float(xy_local[1])
    if kind == "chip":
        return 0, (1 if x >= 0 else -1)
    if abs(y) * body_length > abs(x) * body_width:
        return 1, (1 if y >= 0 else -1)
    return 0, (1 if x >= 0 else -1)


# --------------------------------------------------------------------------------------
# Geometry helpers (no shapely: convex pieces and OpenCV's convex intersection).
# --------------------------------------------------------------------------------------


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _ccw(poly: np.ndarray) -> np.ndarray:
    poly = np.asarray(poly, dtype=np.float64)
    return poly if _signed_area(poly) >= 0 else poly[::-1].copy()


def _centroid(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = cross.sum() / 2.0
    cx = ((x + np.roll(x, -1)) * cross).sum() / (6 * a)
    cy = ((y + np.roll(y, -1)) * cross).sum() / (6 * a)
    return np.array([cx, cy])


def _seg_cross(p1, p2, q1, q2) -> bool:
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return d1 * d2 < 0 and d3 * d4 < 0


def _is_simple(poly: np.ndarray) -> bool:
    n = len(poly)
    for i in range(n):
        for j in range(i + 1, n):
            if abs(i - j) <= 1 or (i == 0 and j == n - 1):
                continue
            if _seg_cross(poly[i], poly[(i + 1) % n], poly[j], poly[(j + 1) % n]):
                return False
    return True


def _is_convex(poly: np.ndarray) -> bool:
    d = np.roll(poly, -1, axis=0) - poly
    cross = d[:, 0] * np.roll(d[:, 1], -1) - d[:, 1] * np.roll(d[:, 0], -1)
    return bool(np.all(cross >= -1e-12) or np.all(cross <= 1e-12))


def _triangulate(poly: np.ndarray) -> list[np.ndarray]:
    """Ear-clipping triangulation of a simple counter-clockwise polygon."""
    pts = [np.asarray(p, dtype=np.float64) for p in _ccw(poly)]
    idx = list(range(len(pts)))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < 10000:
        guard += 1
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = pts[i0], pts[i1], pts[i2]
            if cross(a, b, c) <= 1e-15:
                continue
            inside = False
            for m in idx:
                if m in (i0, i1, i2):
                    continue
                p = pts[m]
                # Closed triangle: a reflex vertex on an ear's edge blocks the ear too.
                if cross(a, b, p) >= -1e-12 and cross(b, c, p) >= -1e-12 and \
                        cross(c, a, p) >= -1e-12:
                    inside = True
                    break
            if not inside:
                tris.append(np.array([a, b, c]))
                idx.pop(k)
                break
        else:  # degenerate (collinear run): drop a middle vertex
            idx.pop(1)
    if len(idx) == 3:
        tris.append(np.array([pts[i] for i in idx]))
    return tris


def _convex_pieces(poly: np.ndarray) -> list[np.ndarray]:
    poly = _ccw(poly)
    return [poly] if _is_convex(poly) else _triangulate(poly)


def polygons_overlap(a: np.ndarray, b: np.ndarray, *, min_area_mm2: float = 1e-9) -> bool:
    """Whether two simple polygons ``(N, 2)`` overlap with positive area.

    Touching edges do not count. Non-convex polygons are split into triangles and the
    pieces tested with :func:`cv2.intersectConvexConvex`.
    """
    import cv2

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if (a[:, 0].max() <= b[:, 0].min() or b[:, 0].max() <= a[:, 0].min()
            or a[:, 1].max() <= b[:, 1].min() or b[:, 1].max() <= a[:, 1].min()):
        return False
    # Centre both on a common origin so float32 inside OpenCV keeps µm precision.
    origin = a.mean(axis=0)
    for pa in _convex_pieces(a - origin):
        for pb in _convex_pieces(b - origin):
            area, _ = cv2.intersectConvexConvex(pa.astype(np.float32), pb.astype(np.float32))
            if area > min_area_mm2:
                return True
    return False


def _check_overlaps(v: _Validator, joints: Iterable[Joint]) -> None:
    joints = list(joints)
    boxes = np.array([[j.polygon_mm[:, 0].min(), j.polygon_mm[:, 1].min(),
                       j.polygon_mm[:, 0].max(), j.polygon_mm[:, 1].max()] for j in joints])
    for i in range(len(joints)):
        cand = np.nonzero((boxes[i + 1:, 0] < boxes[i, 2]) & (boxes[i + 1:, 2] > boxes[i, 0])
                          & (boxes[i + 1:, 1] < boxes[i, 3])
                          & (boxes[i + 1:, 3] > boxes[i, 1]))[0] + i + 1
        for k in cand:
            # 1 µm² tolerance: pads that merely touch are allowed.
            if polygons_overlap(joints[i].polygon_mm, joints[k].polygon_mm,
                                min_area_mm2=1e-6):
                v.fail(f"pads of joints {joints[i].id} and {joints[k].id} overlap")


def _circle_hits_polygon(cx: float, cy: float, r: float, poly: np.ndarray) -> bool:
    # Inside test, then distance to every edge.
    x, y = poly[:, 0], poly[:, 1]
    inside = False
    n = len(poly)
    for i in range(n):
        j = (i + 1) % n
        if (y[i] > cy) != (y[j] > cy):
            xin = x[i] + (cy - y[i]) * (x[j] - x[i]) / (y[j] - y[i])
            if cx < xin:
                inside = not inside
    if inside:
        return True
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ab = b - a
        t = np.clip(np.dot([cx, cy] - a, ab) / max(np.dot(ab, ab), 1e-18), 0.0, 1.0)
        if np.hypot(*(a + t * ab - [cx, cy])) < r:
            return True
    return False
