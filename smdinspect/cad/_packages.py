"""Package matching: footprint and package names → body, lead and land geometry.

Footprint names in KiCad's libraries and IPC-7351 land-pattern names carry the package:
``R_0603_1608Metric``, ``RESC1608X55N``, ``SOIC-8_3.9x4.9mm_P1.27mm``,
``SOIC127P600X175-8N``, ``TSSOP-20_4.4x6.5mm_P0.65mm``, ``LQFP-64_10x10mm_P0.5mm``,
``SOT-23-5``. :func:`match_package` turns such a name into the body and lead geometry
the board model needs (nominal JEDEC/EIA values, see the tables below), or says why the
part cannot be modelled (bottom-terminated packages, exposed pads, no match).

A user's package table (TOML, :func:`load_package_table`) maps other names, and takes
precedence over the built-in rules.

Frames: the geometry returned is in the board model's component frame (body length
along local x; gull-wing pin rows along x, pin 1 at (−x, −y)). Footprint libraries draw
parts in IPC-7351's zero orientation instead (chips: pin 1 left; two- and four-sided
gull-wing parts: pin 1 top left, first row running down the left side), which is the
board frame rotated by ``zero_rotation_deg`` (0 for chips, 90 for gull-wing parts):
``board rotation = file rotation − zero_rotation_deg``.
"""

from __future__ import annotations

import fnmatch
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputError
from ..inspect._board import PACKAGES

__all__ = ["PackageMatch", "PackageTable", "land_pattern", "load_package_table",
           "match_package"]

# Imperial chip code → (length, width, termination length) mm (EIA nominal).
_CHIP_BODY = {
    "0201": (0.60, 0.30, 0.15), "0402": (1.00, 0.50, 0.25), "0603": (1.60, 0.80, 0.30),
    "0805": (2.00, 1.25, 0.40), "1206": (3.20, 1.60, 0.50), "1210": (3.20, 2.50, 0.50),
    "1812": (4.50, 3.20, 0.50), "2010": (5.00, 2.50, 0.60), "2512": (6.35, 3.20, 0.60),
}
_METRIC_TO_IMPERIAL = {"0603": "0201", "1005": "0402", "1608": "0603", "2012": "0805",
                       "3216": "1206", "3225": "1210", "4532": "1812", "5025": "2010",
                       "6332": "2512", "6432": "2512"}
# Typical body heights (thick-film resistor, MLCC), mm.
_CHIP_HEIGHT = {
    "0201": (0.23, 0.30), "0402": (0.35, 0.50), "0603": (0.45, 0.80),
    "0805": (0.50, 0.85), "1206": (0.55, 1.15), "1210": (0.55, 1.60),
    "1812": (0.60, 1.60), "2010": (0.55, 0.85), "2512": (0.55, 0.85),
}
_CHIP_PREFIX_STYLE = {"R": "resistor", "FUSE": "resistor", "RES": "resistor",
                      "C": "capacitor", "CAP": "capacitor", "L": "capacitor",
                      "IND": "capacitor", "LED": "capacitor", "D": "capacitor",
                      "DIO": "capacitor"}

# Gull-wing families: body height, standoff, lead thickness T, foot length L, exit
# height (where the lead leaves the mould); span tables by body width (JEDEC MS-012,
# MO-153, MO-187, MO-150, MS-026, TO-236/MO-178/MO-203 nominal values).
_GULLWING = {
    "SOIC": {"height": 1.50, "standoff": 0.15, "T": 0.20, "foot": 0.84, "exit": 0.80,
             "span": {3.9: 6.0, 5.3: 7.9, 7.5: 10.3}, "span_add": 2.1},
    "TSSOP": {"height": 1.05, "standoff": 0.10, "T": 0.15, "foot": 0.60, "exit": 0.55,
              "span": {4.4: 6.4, 6.1: 8.1, 3.0: 4.9}, "span_add": 2.0},
    "MSOP": {"height": 0.95, "standoff": 0.10, "T": 0.15, "foot": 0.55, "exit": 0.50,
             "span": {3.0: 4.9}, "span_add": 1.9},
    "SSOP": {"height": 1.75, "standoff": 0.10, "T": 0.15, "foot": 0.75, "exit": 0.90,
             "span": {5.3: 7.8, 3.9: 6.0, 4.4: 6.4}, "span_add": 2.5},
    "LQFP": {"height": 1.50, "standoff": 0.10, "T": 0.15, "foot": 0.60, "exit": 0.75,
             "span": {}, "span_add": 2.0},
    "TQFP": {"height": 1.00, "standoff": 0.10, "T": 0.15, "foot": 0.60, "exit": 0.50,
             "span": {}, "span_add": 2.0},
    "QFP": {"height": 2.00, "standoff": 0.25, "T": 0.15, "foot": 0.80, "exit": 1.00,
            "span": {}, "span_add": 2.6},
}
_FAMILY_ALIAS = {"SO": "SOIC", "SOP": "SOIC", "VSSOP": "MSOP", "QSOP": "SSOP",
                 "TSOP": "TSSOP"}
# SOT families: body length (along the pin rows) x width, span, height, lead width.
_SOT = {
    "SOT-23": (2.90, 1.30, 2.40, 1.00, 0.40, 0.95),
    "SOT-23-5": (2.90, 1.60, 2.80, 1.10, 0.40, 0.95),
    "SOT-23-6": (2.90, 1.60, 2.80, 1.10, 0.40, 0.95),
    "SOT-323": (2.00, 1.25, 2.10, 0.90, 0.30, 0.65),
    "SOT-363": (2.00, 1.25, 2.10, 0.90, 0.25, 0.65),
    "SC-70-5": (2.00, 1.25, 2.10, 0.90, 0.25, 0.65),
}

_NOT_MODELLED = [
    (re.compile(r"^(V|W|U|X)?(QFN|DFN|SON|LGA|BGA|CSP|WLCSP|MLF|MLP|LLP|TDFN|UDFN|WSON|"
                r"VSON|USON|XSON|TQFN|VQFN|UQFN|WQFN|HVQFN|XQFN)", re.I),
     "bottom-terminated package (no side fillet to measure)"),
    (re.compile(r"-\d*EP|_EP[\d.]|ThermalVias|PowerPAD|HTSSOP|HSOP|HSSOP", re.I),
     "package with an exposed (thermal) pad: not modelled"),
    (re.compile(r"^(SOT-223|SOT-89|TO-252|TO-263|DPAK|D2PAK|SOT-428|TO-2)", re.I),
     "power package with a tab lead: not modelled"),
    (re.compile(r"^(D_)?(SOD-|SMA|SMB|SMC|MELF|MiniMELF|DO-2)", re.I),
     "diode package (SOD/DO-214/MELF): no joint model"),
    (re.compile(r"^(CP_Elec|C_Elec|CP_EIA|C_EIA|Crystal|Oscillator|L_[A-Z]|Fuseholder|"
                r"Buzzer|Relay|SW_|Button|Conn|PinHeader|PinSocket|USB|TestPoint|"
                r"MountingHole|Jumper|SolderJumper|NetTie|Battery)", re.I),
     "not a chip or gull-wing part: no joint model"),
]


@dataclass(frozen=True)
class PackageMatch:
    """What a footprint or package name resolved to.

    Attributes
    ----------
    package : str
        Package name written into the board file (a :data:`PACKAGES` key when the part
        is one of them, e.g. ``"0603"``, ``"SOIC-8"``).
    kind : str
        ``"chip"`` or ``"gullwing"``.
    style : str
        ``"resistor"``, ``"capacitor"`` or ``"ic"``.
    body : dict
        ``length_mm, width_mm, height_mm, standoff_mm`` (+ ``termination_length_mm``
        for chips), board-model frame.
    lead : dict or None
        Gull-wing lead geometry (see :class:`smdinspect.inspect.Component`).
    pins, pitch_mm, sides : int, float, int
        Pin count, pitch and number of pin rows (chips: 2, 0, 2).
    zero_rotation_deg : float
        Rotation of the library's zero orientation from the board-model frame.
    pads : list of dict or None
        A package table's explicit pads (board-model frame), else ``None``.
    pad : dict or None
        A package table's land (``length_mm, width_mm, center_mm``), else ``None``.
    """

    package: str
    kind: str
    style: str
    body: dict[str, float]
    lead: dict[str, float] | None
    pins: int
    pitch_mm: float
    sides: int
    zero_rotation_deg: float = 0.0
    pads: list | None = None
    pad: dict | None = None


@dataclass(frozen=True)
class PackageTable:
    """A user's package table: name patterns → :class:`PackageMatch` or a skip reason."""

    entries: tuple[tuple[str, Any], ...] = ()
    source: str = ""

    def lookup(self, name: str) -> PackageMatch | str | None:
        for pattern, value in self.entries:
            if pattern == name or fnmatch.fnmatchcase(name, pattern):
                return value
        return None


@dataclass(frozen=True)
class _Unmatched:
    reason: str
    extra: dict = field(default_factory=dict)


def _r(x: float) -> float:
    return round(float(x), 4)


def footprint_base(name: str) -> str:
    """``"Package_SO:SOIC-8_3.9x4.9mm_P1.27mm"`` → ``"SOIC-8_3.9x4.9mm_P1.27mm"``."""
    return name.split(":", 1)[-1].strip()


def match_package(name: str, *, ref: str = "", table: PackageTable | None = None
                  ) -> PackageMatch | str:
    """Resolve a footprint or package name.

    Parameters
    ----------
    name : str
        Footprint name (a KiCad ``Library:Name`` lib id is accepted) or package name.
    ref : str, optional
        Reference designator, used for the body style of bare size codes (``C...``).
    table : PackageTable, optional
        A user's table, searched first (exact names, then glob patterns).

    Returns
    -------
    PackageMatch or str
        The match, or a one-line reason why the name cannot be modelled.
    """
    base = footprint_base(name)
    if table is not None:
        hit = table.lookup(base)
        if hit is None and base != name:
            hit = table.lookup(name)
        if isinstance(hit, (PackageMatch, str)):
            return hit
    for rx, reason in _NOT_MODELLED:
        if rx.search(base):
            return reason
    for fn in (_match_chip, _match_sot, _match_gullwing_kicad, _match_gullwing_ipc):
        m = fn(base, ref)
        if m is not None:
            return m
    return (f"footprint name {base!r} matches no known package (IPC-7351 / KiCad library "
            f"names of chips, SOIC, SSOP/TSSOP/MSOP, QFP, SOT-23; add it to a --packages "
            f"table)")


def _chip(code: str, style: str, height: float | None = None) -> PackageMatch:
    length, width, term = _CHIP_BODY[code]
    if height is None:
        hr, hc = _CHIP_HEIGHT[code]
        height = hr if style == "resistor" else hc
    body = {"length_mm": length, "width_mm": width, "height_mm": _r(height),
            "standoff_mm": 0.03, "termination_length_mm": term}
    return PackageMatch(package=code, kind="chip", style=style, body=body, lead=None,
                        pins=2, pitch_mm=0.0, sides=2)


_RX_KICAD_CHIP = re.compile(r"^(R|C|L|LED|D|Fuse)_(\d{4})_(\d{4})Metric(?:_|$)", re.I)
_RX_IPC_CHIP = re.compile(r"^(RES|CAP|IND|LED|DIO)C(\d{2})(\d{2})X(\d{2,3})", re.I)
_RX_BARE_CHIP = re.compile(r"^(R|C|L|LED|D)?[_-]?(0201|0402|0603|0805|1206|1210|1812|2010|"
                           r"2512)(?:$|[_-])", re.I)


def _style(prefix: str, ref: str) -> str:
    if prefix:
        return _CHIP_PREFIX_STYLE.get(prefix.upper(), "resistor")
    return "capacitor" if ref[:1].upper() in ("C", "L", "D") else "resistor"


def _match_chip(base: str, ref: str) -> PackageMatch | None:
    m = _RX_KICAD_CHIP.match(base)
    if m:
        code = m.group(2)
        if code in _CHIP_BODY and _METRIC_TO_IMPERIAL.get(m.group(3)) == code:
            return _chip(code, _style(m.group(1), ref))
        return None
    m = _RX_IPC_CHIP.match(base)
    if m:
        metric = m.group(2) + m.group(3)
        code = _METRIC_TO_IMPERIAL.get(metric)
        if code is None:
            return None
        return _chip(code, _style(m.group(1), ref), height=int(m.group(4)) / 100.0)
    m = _RX_BARE_CHIP.match(base)
    if m:
        return _chip(m.group(2), _style(m.group(1) or "", ref))
    return None


def _gullwing(package: str, family: str, pins: int, pitch: float, body_w: float,
              body_l: float, sides: int, span: float | None = None,
              height: float | None = None) -> PackageMatch:
    fam = _GULLWING[family]
    if span is None:
        span = fam["span"].get(round(body_w, 2), body_w + fam["span_add"])
    foot = min(fam["foot"], 0.3 * (span - body_w) + 0.3)
    lead = {"width_mm": round(min(0.42, 0.45 * pitch), 2), "thickness_mm": fam["T"],
            "foot_length_mm": _r(foot), "span_mm": _r(span), "exit_height_mm": fam["exit"],
            "solder_thickness_mm": 0.03}
    h = fam["height"] if height is None else height
    body = {"length_mm": _r(body_l), "width_mm": _r(body_w), "height_mm": _r(h),
            "standoff_mm": fam["standoff"]}
    if lead["exit_height_mm"] >= h:
        lead["exit_height_mm"] = _r(0.55 * h)
    return PackageMatch(package=package, kind="gullwing", style="ic", body=body, lead=lead,
                        pins=pins, pitch_mm=pitch, sides=sides, zero_rotation_deg=90.0)


def _named(short: str, m: PackageMatch, full: str) -> PackageMatch:
    """The short name when it is free or denotes the same part in PACKAGES."""
    known = PACKAGES.get(short)
    if known is None:
        return _replace(m, package=short)
    same = (known["kind"] == m.kind and known.get("pins") == m.pins
            and math.isclose(known.get("pitch_mm", 0), m.pitch_mm)
            and math.isclose(known["body"]["length_mm"], m.body["length_mm"])
            and math.isclose(known["body"]["width_mm"], m.body["width_mm"]))
    if same:  # the built-in package: its own tabled body and lead
        return _replace(m, package=short, body=dict(known["body"]),
                        lead=dict(known["lead"]))
    return _replace(m, package=full)


def _replace(m: PackageMatch, **kw) -> PackageMatch:
    from dataclasses import replace

    return replace(m, **kw)


_RX_KICAD_GW = re.compile(
    r"^(SOIC|SO|SOP|SSOP|QSOP|TSSOP|TSOP|MSOP|VSSOP|LQFP|TQFP|QFP)-(\d+)W?_"
    r"([\d.]+)x([\d.]+)mm_P([\d.]+)mm(?:_|$)", re.I)
_RX_IPC_GW = re.compile(r"^(SOIC|SOP|SSOP|TSSOP|TSOP|QFP)(\d+)P(\d+)X(\d+)(?:X(\d+))?-(\d+)",
                        re.I)


def _match_gullwing_kicad(base: str, ref: str) -> PackageMatch | None:
    m = _RX_KICAD_GW.match(base)
    if not m:
        return None
    fam = m.group(1).upper()
    family = _FAMILY_ALIAS.get(fam, fam)
    pins, a, b, pitch = int(m.group(2)), float(m.group(3)), float(m.group(4)), \
        float(m.group(5))
    sides = 4 if family.endswith("QFP") else 2
    # KiCad names give width (across the rows) x length (along them).
    body_w, body_l = a, b
    short = f"{fam}-{pins}"
    full = f"{fam}-{pins}_{m.group(3)}x{m.group(4)}mm_P{m.group(5)}mm"
    return _named(short, _gullwing(short, family, pins, pitch, body_w, body_l, sides), full)


def _match_gullwing_ipc(base: str, ref: str) -> PackageMatch | None:
    m = _RX_IPC_GW.match(base)
    if not m:
        return None
    fam = m.group(1).upper()
    family = {"SOP": "SOIC", "TSOP": "TSSOP"}.get(fam, fam)
    pitch = int(m.group(2)) / 100.0
    span = int(m.group(3)) / 100.0
    pins = int(m.group(6))
    sides = 4 if family == "QFP" else 2
    height = int(m.group(5) or m.group(4)) / 100.0
    if sides == 4 and m.group(5) is None:
        return None
    per_row = pins // sides
    body_l = _r(per_row * pitch - 0.18 if sides == 2 else span - 2.0)
    body_w = _r(span - 2 * 1.05 if sides == 2 else span - 2.0)
    fam_key = family if sides == 2 else ("LQFP" if height <= 1.7 else "QFP")
    match = _gullwing(f"{fam}-{pins}", fam_key, pins, pitch, body_w, body_l, sides,
                      span=span, height=height)
    return _replace(match, package=base)


_RX_SOT = re.compile(r"^(?:T)?(SOT-23|SOT-323|SOT-363|SC-70)(?:-(\d))?(?:_|$)", re.I)


def _match_sot(base: str, ref: str) -> PackageMatch | None:
    m = _RX_SOT.match(base)
    if not m:
        return None
    fam = m.group(1).upper()
    pins = int(m.group(2)) if m.group(2) else (6 if fam == "SOT-363" else 3)
    key = fam if fam != "SC-70" else "SC-70-5"
    if fam == "SOT-23" and pins in (5, 6):
        key = f"SOT-23-{pins}"
    if key not in _SOT or pins not in (3, 5, 6):
        return None
    length, width, span, height, lead_w, pitch = _SOT[key]
    lead = {"width_mm": lead_w, "thickness_mm": 0.12, "foot_length_mm": 0.40,
            "span_mm": span, "exit_height_mm": _r(0.5 * height), "solder_thickness_mm": 0.03}
    body = {"length_mm": length, "width_mm": width, "height_mm": height,
            "standoff_mm": 0.05}
    name = key if pins != 3 or fam != "SOT-23" else "SOT-23"
    return PackageMatch(package=name, kind="gullwing", style="ic", body=body, lead=lead,
                        pins=pins, pitch_mm=pitch, sides=2, zero_rotation_deg=90.0)


# --------------------------------------------------------------------------------------
# Land patterns for centroid files (no pads in the file).
# --------------------------------------------------------------------------------------


def land_pattern(m: PackageMatch) -> list[dict[str, Any]]:
    """Nominal pads of a package in the board-model frame (for centroid imports).

    Chips: two pads at ±c along x. Gull-wing: pads numbered counter-clockwise from pin 1
    at (−x, −y), as :func:`smdinspect.inspect.package_defaults`; SOT-23 (3 pins): pins 1
    and 2 on the −y row, pin 3 alone on the +y row. Lands are IPC-7351-like nominal
    (pad length 1.5 mm or less, width ``pitch − 0.25`` up to 0.6 mm) unless the package
    table gives ``pad`` or ``pads``.
    """
    if m.pads is not None:
        return [dict(p) for p in m.pads]
    if m.package in PACKAGES and m.pad is None and (
            PACKAGES[m.package]["kind"] == m.kind):
        from ..inspect._board import package_defaults

        return package_defaults(m.package, style=m.style if m.kind == "chip" else None)["pads"]
    b = m.body
    if m.kind == "chip":
        length, width = b["length_mm"], b["width_mm"]
        pad = m.pad or {"length_mm": _r(0.35 * length + 0.2), "width_mm": _r(width + 0.15),
                        "center_mm": _r(length / 2.0)}
        c = pad["center_mm"]
        return [{"number": str(k + 1), "x_mm": s * c, "y_mm": 0.0,
                 "length_mm": pad["length_mm"], "width_mm": pad["width_mm"]}
                for k, s in enumerate((-1.0, 1.0))]
    lead = m.lead or {}
    span = float(lead.get("span_mm", b["width_mm"] + 2.0))
    pad = m.pad or {"length_mm": _r(min(1.5, 0.5 * (span - b["width_mm"]) + 0.6)),
                    "width_mm": _r(min(0.6, m.pitch_mm - 0.25)),
                    "center_mm": _r(span / 2.0 - 0.3)}
    c = pad["center_mm"]
    pads = []

    def add(x, y):
        pads.append({"number": str(len(pads) + 1), "x_mm": _r(x), "y_mm": _r(y),
                     "length_mm": pad["length_mm"], "width_mm": pad["width_mm"]})

    if m.sides == 2 and m.pins == 3:          # SOT-23: 1, 2 below; 3 above, centred
        add(-m.pitch_mm, -c)
        add(m.pitch_mm, -c)
        add(0.0, c)
        return pads
    if m.sides == 2 and m.pins == 5:          # SOT-23-5: 1..3 below, 4, 5 above
        for k in (-1, 0, 1):
            add(k * m.pitch_mm, -c)
        add(m.pitch_mm, c)
        add(-m.pitch_mm, c)
        return pads
    per = m.pins // m.sides
    offs = [(k - (per - 1) / 2.0) * m.pitch_mm for k in range(per)]
    cy = c
    cx = c if m.sides == 4 else c
    if m.sides == 4:
        for o in offs:
            add(o, -cy)
        for o in offs:
            add(cx, o)
        for o in offs:
            add(-o, cy)
        for o in offs:
            add(-cx, -o)
    else:
        for o in offs:
            add(o, -cy)
        for o in offs:
            add(-o, cy)
    return pads


# --------------------------------------------------------------------------------------
# The user's package table.
# --------------------------------------------------------------------------------------

_ENTRY_KEYS = {"package", "kind", "style", "body", "lead", "pins", "pitch_mm", "sides",
               "pad", "pads", "zero_rotation_deg", "skip"}


def load_package_table(path: str | Path) -> PackageTable:
    """Read a package table (TOML).

    Each ``[package."NAME"]`` table maps a footprint / package name (exact, or a glob
    such as ``"R_0603*"``) to one of:

    * ``package = "SOIC-8_3.9x4.9mm_P1.27mm"``: another name the built-in rules know
      (optionally with ``style``, ``zero_rotation_deg``);
    * a full description: ``kind`` (``chip`` | ``gullwing``), ``body`` {length_mm,
      width_mm, height_mm, standoff_mm[, termination_length_mm]}, for gull-wing parts
      ``lead`` {width_mm, thickness_mm, foot_length_mm, span_mm, exit_height_mm} and
      ``pins``, ``pitch_mm``, ``sides``; optional ``pad`` {length_mm, width_mm,
      center_mm} or explicit ``pads`` (board-model frame) for centroid files, ``style``
      and ``zero_rotation_deg`` (default 0 for chips, 90 for gull-wing);
    * ``skip = "reason"``: never modelled; the reason is listed.

    Raises
    ------
    InputError
        ``FILE: ...`` naming the entry and the bad key or value (TOML errors with their
        line).
    """
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"package table {p}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{p}: not valid TOML: {exc}") from None
    extra = set(doc) - {"package"}
    if extra:
        raise InputError(f"{p}: unknown top-level table(s) {', '.join(sorted(extra))}; "
                         f"expected [package.\"NAME\"] tables")
    entries = []
    for name, spec in (doc.get("package") or {}).items():
        where = f"{p}: [package.{name!r}]"
        if not isinstance(spec, dict):
            raise InputError(f"{where} must be a table")
        unknown = set(spec) - _ENTRY_KEYS
        if unknown:
            raise InputError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; "
                             f"allowed: {', '.join(sorted(_ENTRY_KEYS))}")
        entries.append((name, _entry(spec, name, where)))
    return PackageTable(tuple(entries), str(p))


def _entry(spec: dict, name: str, where: str) -> PackageMatch | str:
    if "skip" in spec:
        if not isinstance(spec["skip"], str) or not spec["skip"].strip():
            raise InputError(f"{where}: 'skip' must be a non-empty reason")
        return f"skipped by the package table: {spec['skip']}"
    if "package" in spec and "kind" not in spec:
        m = match_package(str(spec["package"]))
        if isinstance(m, str):
            raise InputError(f"{where}: package {spec['package']!r}: {m}")
        kw: dict[str, Any] = {}
        if "style" in spec:
            kw["style"] = spec["style"]
            if m.kind == "chip" and "height_mm" in m.body:
                code = m.package
                if code in _CHIP_HEIGHT and spec["style"] in ("resistor", "capacitor"):
                    body = dict(m.body)
                    body["height_mm"] = _CHIP_HEIGHT[code][spec["style"] == "capacitor"]
                    kw["body"] = body
        for key in ("zero_rotation_deg", "pad", "pads"):
            if key in spec:
                kw[key] = spec[key]
        return _replace(m, **kw)
    kind = spec.get("kind")
    if kind not in ("chip", "gullwing"):
        raise InputError(f"{where}: 'kind' must be chip or gullwing (or give 'package' or "
                         f"'skip'); got {kind!r}")
    body = spec.get("body")
    if not isinstance(body, dict):
        raise InputError(f"{where}: missing table 'body'")
    lead = spec.get("lead")
    if kind == "gullwing":
        if not isinstance(lead, dict):
            raise InputError(f"{where}: a gull-wing entry needs a 'lead' table")
        for key in ("pins", "pitch_mm"):
            if key not in spec and "pads" not in spec:
                raise InputError(f"{where}: missing {key!r} (or explicit 'pads')")
    pads = spec.get("pads")
    if pads is not None and (not isinstance(pads, list) or not pads):
        raise InputError(f"{where}: 'pads' must be a non-empty list of pad tables")
    style = spec.get("style", "ic" if kind == "gullwing" else "resistor")
    return PackageMatch(package=str(spec.get("package", name)), kind=kind, style=style,
                        body=dict(body), lead=dict(lead) if lead else None,
                        pins=int(spec.get("pins", len(pads) if pads else 2)),
                        pitch_mm=float(spec.get("pitch_mm", 0.0)),
                        sides=int(spec.get("sides", 2)),
                        zero_rotation_deg=float(spec.get("zero_rotation_deg",
                                                         90.0 if kind == "gullwing" else 0.0)),
                        pads=pads, pad=spec.get("pad"))
