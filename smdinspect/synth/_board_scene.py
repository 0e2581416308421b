"""Synthetic SMD boards built from a reference board file, with injectable defects.

:func:`board_scene` turns a :class:`~smdinspect.inspect.Board` into a
:class:`~smdinspect.synth.Scene` (height map in mm, RGB albedo, shininess) placed shifted
and rotated in the field of view, plus truth labels for every joint.

What is drawn (heights above the board top surface, z = 0):

* solder mask (green, glossy, very weak texture, ±1.5 µm), raised 18 µm over copper
  traces and tented vias; a *panel* of mask continues beyond the board outline;
* white silkscreen (12 µm) component outlines, reference designators, pin-1 marks;
* mask openings around pads and fiducials (bare laminate 20 µm below the mask top);
* pads and fiducials in the board's finish: ENIG (gold, shiny, flat at z = 0), HASL
  (solder-grey, a 5–10 µm uneven pillow) or OSP (bare copper);
* chips: tin-plated end caps, black resistor overcoat with a printed value code (0603
  and larger) or tan MLCC ceramic;
* gull-wing parts: black mould with drafted rim, pin-1 dimple and laser marking; tin
  leads with shoulder, knee and foot;
* solder: concave meniscus fillets rising from the pad's outer edge to the chip end
  (or to the lead heel, sides and toe) — parabolas, or for chips circular arcs of a
  given curvature (``fillet_curvature``) —, with a thin solder coat over the wetted pad,
  a granular surface (albedo grain and 2.5 µm micro-relief) and high shininess.

Defects (:data:`DEFECTS`) change the geometry; see :func:`board_scene`. Their severity
(lift, tilt, fillet fraction, bridge size, shift...) is drawn from the seed or given per
joint (``params``, see :data:`SEVERITY`); :func:`random_board_case` draws whole randomised
cases (defects over realistic ranges, finish, fiducials, lighting, lens, field edge) for
the inspection benchmark and tests.
"""

from __future__ import annotations

import logging
import math
import os
import re
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..inspect._board import Board, Component, Joint, _pad_axis, load_board
from ..inspect._geometry import arc_fillet
from ._scene import Scene

__all__ = ["DEFECTS", "FINISHES", "SEVERITY", "TEST_SEEDS", "TUNING_SEEDS", "board_scene",
           "board_shape", "case_imaging", "parse_defects", "random_board_case", "scene_kwargs"]

log = logging.getLogger(__name__)

DEFECTS = ("ok", "missing", "insufficient", "excess", "bridge", "lifted_lead", "tombstone",
           "component_missing", "component_shifted")
_COMPONENT_LEVEL = ("tombstone", "component_missing", "component_shifted")
_GULLWING_ONLY = ("lifted_lead",)
_CHIP_ONLY = ("tombstone",)

MAX_OFFSET_MM = 2.0
MAX_ROTATE_DEG = 5.0
_MARGIN_MM = 0.5
_MAX_PIXELS = 64_000_000

# Colours (linear RGB reflectance) and shininess of the materials.
_MASK = np.array([0.10, 0.33, 0.16], np.float32)
_MASK_TRACE = np.array([0.15, 0.43, 0.20], np.float32)
_LAMINATE = np.array([0.40, 0.34, 0.17], np.float32)
_SILK = np.array([0.90, 0.90, 0.86], np.float32)
_ENIG = np.array([0.86, 0.68, 0.36], np.float32)
_HASL = np.array([0.78, 0.78, 0.76], np.float32)
_OSP = np.array([0.80, 0.46, 0.30], np.float32)
#: Pad finishes: colour and shininess of a bare pad (and the fiducials).
FINISHES = {"enig": (_ENIG, 0.6), "hasl": (_HASL, 0.7), "osp": (_OSP, 0.45)}
_SOLDER = np.array([0.80, 0.80, 0.78], np.float32)
_TIN = np.array([0.74, 0.74, 0.72], np.float32)
_RES_TOP = np.array([0.06, 0.06, 0.06], np.float32)
_RES_MARK = np.array([0.52, 0.52, 0.50], np.float32)
_ALUMINA = np.array([0.88, 0.87, 0.82], np.float32)
_MLCC = np.array([0.60, 0.48, 0.32], np.float32)
_MOULD = np.array([0.08, 0.08, 0.09], np.float32)
_MOULD_MARK = np.array([0.24, 0.24, 0.24], np.float32)

# Relative albedo texture of the solder mask per noise scale (fine 9 µm, med 40 µm,
# coarse 0.5 mm): weak, as real mask, but enough for a focus measure most of the time.
_MASK_TEX = dict(fine=0.07, med=0.05, coarse=0.05)
_Z_MASK_TRACE = 0.018
_Z_SILK = 0.012
_Z_LAMINATE = -0.020
_SOLDER_COAT = 0.006


def parse_defects(spec: str | None, *, board: Board | None = None) -> dict[str, str]:
    """Parse ``"R3.1:insufficient,U1.4:bridge"`` into ``{"R3.1": "insufficient", ...}``.

    Parameters
    ----------
    spec : str or None
        Comma-separated ``JOINT:CLASS`` items; empty or None gives ``{}``.
    board : Board, optional
        When given, joint ids are checked against it.

    Raises
    ------
    InputError
        Bad syntax, a joint named twice, an unknown class (the classes are listed) or,
        with ``board``, an unknown joint id (a few valid ids are listed).
    """
    if spec is None:
        return {}
    if not isinstance(spec, str):
        raise InputError(f"defects must be a string like 'R3.1:insufficient'; got {spec!r}")
    out: dict[str, str] = {}
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        m = re.fullmatch(r"([^\s:,]+\.[^\s:,]+)\s*:\s*([A-Za-z_]+)", item)
        if m is None:
            raise InputError(f"bad defect {item!r}: expected JOINT:CLASS, e.g. "
                             f"'R3.1:insufficient'")
        jid, cls = m.group(1), m.group(2).lower()
        if jid in out:
            raise InputError(f"joint {jid} is given two defects ({out[jid]}, {cls})")
        out[jid] = cls
    _check_defects(out, board)
    return out


def _check_defects(defects: Mapping[str, str], board: Board | None) -> None:
    for jid, cls in defects.items():
        if cls not in DEFECTS:
            raise InputError(f"unknown defect class {cls!r} for joint {jid}; classes: "
                             f"{', '.join(DEFECTS)}")
    if board is None:
        return
    ids = {j.id: j for j in board.joints()}
    per_comp: dict[str, list[tuple[str, str]]] = {}
    for jid, cls in defects.items():
        if jid not in ids:
            some = list(ids)[:8]
            raise InputError(f"unknown joint {jid!r} on board {board.name}; valid ids are "
                             f"like {', '.join(some)}")
        comp = board.component(ids[jid].component)
        if cls in _GULLWING_ONLY and comp.kind != "gullwing":
            raise InputError(f"{jid}: {cls} applies to gull-wing leads only; "
                             f"{comp.ref} is a {comp.kind} part")
        if cls in _CHIP_ONLY and comp.kind != "chip":
            raise InputError(f"{jid}: {cls} applies to 2-terminal chips only; "
                             f"{comp.ref} is a {comp.kind} part")
        if cls != "ok":
            per_comp.setdefault(comp.ref, []).append((jid, cls))
    for ref, items in per_comp.items():
        levels = [c for _, c in items if c in _COMPONENT_LEVEL]
        if levels and len(items) > 1:
            desc = ", ".join(f"{j}:{c}" for j, c in items)
            raise InputError(f"component {ref}: {levels[0]} applies to the whole component "
                             f"and cannot be combined with other defects on it ({desc})")


def board_shape(board: Board, *, pixel_size_mm: float, offset_mm=(0.0, 0.0),
                rotate_deg: float = 0.0) -> tuple[int, int]:
    """Default image shape ``(H, W)`` that holds ``board`` for any placement within
    ±2 mm / ±5° (or the given larger ones), with 0.5 mm to spare on every side."""
    bw, bh = board.size_mm
    a = math.radians(max(abs(float(rotate_deg)), MAX_ROTATE_DEG))
    ox = max(abs(float(offset_mm[0])), MAX_OFFSET_MM)
    oy = max(abs(float(offset_mm[1])), MAX_OFFSET_MM)
    w_mm = bw * math.cos(a) + bh * math.sin(a) + 2 * ox + 2 * _MARGIN_MM
    h_mm = bw * math.sin(a) + bh * math.cos(a) + 2 * oy + 2 * _MARGIN_MM
    return int(math.ceil(h_mm / pixel_size_mm)) + 1, int(math.ceil(w_mm / pixel_size_mm)) + 1


def board_scene(board: Board | str | os.PathLike, *, defects: Mapping[str, str] | None = None,
                pixel_size_mm: float = 0.015, shape: tuple[int, int] | None = None,
                offset_mm: tuple[float, float] | None = None, rotate_deg: float | None = None,
                seed: int = 0, params: Mapping[str, Mapping[str, Any]] | None = None,
                finish: str = "enig",
                fillet_curvature: tuple[float, float] | None = None,
                ) -> tuple[Scene, dict[str, Any]]:
    """Render a reference board into a scene, with defects, placed in the field of view.

    Parameters
    ----------
    board : Board or path
        The reference board (a path is loaded with :func:`~smdinspect.inspect.load_board`).
    defects : dict, optional
        ``{joint_id: class}`` with classes from :data:`DEFECTS` (see :func:`parse_defects`).
        Joint-level: ``missing`` (no solder: bare pad, the termination sits on it),
        ``insufficient`` (fillet 30–40 % of nominal, below the band minimum), ``excess``
        (convex fillet bulging over the end cap / burying the lead foot, above the band
        maximum), ``bridge`` (a solder ridge over the mask to the neighbouring pad of the
        same component: the other end along a body side for chips, the next lead on the
        same side for gull-wing parts), ``lifted_lead`` (gull-wing only: foot raised
        0.10–0.20 mm, solder left as a low dome on the pad).
        Component-level (requested on any one joint, labels every joint of the part):
        ``tombstone`` (chips only: the part stands up 60–85° on the other end; the
        requested joint's end is the lifted one), ``component_missing`` (no part, reflowed
        solder bumps on the pads), ``component_shifted`` (the part displaced across its
        pads so the termination overhangs the pad's side by 60–80 % of its width,
        fillets follow the part).
    params : dict, optional
        ``{joint_id: {name: value}}``: the severity of a defect instead of the seeded
        draw (see :data:`SEVERITY`): ``lift_mm`` (lifted_lead), ``tilt_deg`` (tombstone,
        5–90°, on the lifted joint), ``fraction`` (insufficient: fillet height as a
        fraction of the band minimum), ``over_mm`` and ``style`` ("cap": solder over the
        end cap, the default; "convex": a bulging fillet only) for excess, ``height_mm``
        and ``width_mm`` (bridge), ``overhang_frac`` (component_shifted: side overhang of
        the termination over its pad as a fraction of the termination width) and
        ``rotate_deg`` (component_shifted: the part also turned) and ``direction`` (+1 or
        -1: which way across its pads).
    finish : str
        Pad finish, one of :data:`FINISHES` (``"enig"``, ``"hasl"``, ``"osp"``).
    fillet_curvature : (lo, hi), optional
        Chip fillets (good and insufficient ones) as constant-curvature menisci
        (:func:`arc_fillet`, what surface tension makes), each with its curvature drawn
        uniformly in [lo, hi] (0: a straight wedge, 1: the most curved arc meeting pad
        and end face at contact angles of 0 or more). Default: the parabola
        ``F·(1 − s)²``.
    pixel_size_mm : float
        Object-side pixel size, mm.
    shape : (H, W), optional
        Image shape; default :func:`board_shape` (fits any default placement).
    offset_mm : (dx, dy), optional
        Board centre relative to the image centre, world mm. Default: uniform in ±2 mm
        from ``seed``.
    rotate_deg : float, optional
        Board rotation, counter-clockwise degrees. Default: uniform in ±5° from ``seed``.
    seed : int
        Seeds the placement, textures and defect details; same seed, same arrays.

    Returns
    -------
    scene : Scene
        ``height_mm`` (H, W) float32 above the board top, RGB ``albedo``, ``specular``.
    labels : dict
        The truth: board name and file, pixel size, image shape, seed, placement
        (``offset_mm``, ``rotate_deg``, ``board_to_world`` 3×3 with
        ``WORLD = R·BOARD + t``) and one entry per joint with ``id``, ``component``,
        ``class`` and ``true_height_mm`` (the highest rendered solder surface inside the
        pad outline, 0 when none), plus ``in_view`` and, where they apply,
        ``bridge_to`` / ``bridged_by``, ``lifted`` (tombstone end) and ``shift_mm``;
        ``severity`` (the drawn parameters of a defect), ``beyond_limit`` (the defect is
        past the IPC-A-610 Class 2 limit of :data:`SEVERITY`; False for ok joints),
        ``accept`` (every verdict that names it right) and ``field`` ("in", "partial",
        "out": how much of the component's body and pads lies inside the image).

    Notes
    -----
    Placement: ``WORLD (x, y) = R(rotate_deg) · BOARD (x, y) + t`` with ``t`` chosen so
    the board centre lands at the image centre plus ``offset_mm``; WORLD is the frame of
    :class:`~smdinspect.sff.Surface` (``x = col·p``, ``y = (H − 1 − row)·p``).
    """
    if not isinstance(board, Board):
        if isinstance(board, (str, os.PathLike)):
            board = load_board(board)
        else:
            raise InputError(f"board must be a Board or a board file path; got "
                             f"{type(board).__name__}")
    p = _positive(pixel_size_mm, "pixel_size_mm")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be an integer >= 0; got {seed!r}")
    defects = dict(defects or {})
    for k, val in defects.items():
        if not isinstance(k, str) or not isinstance(val, str):
            raise InputError(f"defects must map joint ids to class names; got {k!r}: {val!r}")
    _check_defects(defects, board)
    params = {str(k): dict(v) for k, v in (params or {}).items()}
    for k in params:
        if k not in defects:
            raise InputError(f"params for joint {k!r}, which has no defect; give it one in "
                             f"defects")
    if finish not in FINISHES:
        raise InputError(f"finish must be one of {', '.join(FINISHES)}; got {finish!r}")

    rng = np.random.default_rng([int(seed), 0x5EED])
    draw = rng.uniform(-1.0, 1.0, 3)
    if offset_mm is None:
        off = (float(draw[0] * MAX_OFFSET_MM), float(draw[1] * MAX_OFFSET_MM))
    else:
        try:
            off = (float(offset_mm[0]), float(offset_mm[1]))
        except (TypeError, ValueError, IndexError):
            raise InputError(f"offset_mm must be (dx, dy); got {offset_mm!r}") from None
        if len(offset_mm) != 2 or not all(math.isfinite(o) for o in off):
            raise InputError(f"offset_mm must be two finite numbers; got {offset_mm!r}")
    if rotate_deg is None:
        rot = float(draw[2] * MAX_ROTATE_DEG)
    else:
        if isinstance(rotate_deg, bool) or not isinstance(rotate_deg, (int, float)) or \
                not math.isfinite(rotate_deg):
            raise InputError(f"rotate_deg must be a finite number; got {rotate_deg!r}")
        rot = float(rotate_deg)
    if shape is None:
        shape = board_shape(board, pixel_size_mm=p, offset_mm=off, rotate_deg=rot)
    try:
        hh, ww = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (H, W); got {shape!r}") from None
    if hh < 16 or ww < 16:
        raise InputError(f"shape must be at least (16, 16); got {shape!r}")
    if hh * ww > _MAX_PIXELS:
        raise InputError(f"image of {hh} x {ww} px is too large (> {_MAX_PIXELS} px); use a "
                         f"larger pixel_size_mm or give shape")

    cv = _Canvas((hh, ww), p, board, off, rot, seed)
    cv.finish = finish
    plan = _plan(board, defects, rng, params)
    plan["arc"] = {}
    if fillet_curvature is not None:
        try:
            k_lo, k_hi = (float(x) for x in fillet_curvature)
        except (TypeError, ValueError):
            raise InputError(f"fillet_curvature must be (lo, hi); got "
                             f"{fillet_curvature!r}") from None
        if not 0.0 <= k_lo <= k_hi <= 1.0:
            raise InputError(f"fillet_curvature must satisfy 0 <= lo <= hi <= 1; got "
                             f"{fillet_curvature!r}")
        arc_rng = np.random.default_rng([int(seed), 0xA4C])  # the other draws stay as they were
        for comp in board.components:
            if comp.kind == "chip":
                for j in comp.joints:
                    plan["arc"][j.id] = float(arc_rng.uniform(k_lo, k_hi))
    cv.draw_board(plan)
    for comp in board.components:
        cv.draw_component(comp, plan)
    labels = cv.labels(plan)
    labels.update({"seed": int(seed), "finish": finish,
                   "fiducials": len(board.fiducials)})
    scene = Scene(height_mm=cv.z, albedo=np.clip(cv.rgb, 0.0, 1.0),
                  pixel_size_mm=p, specular=np.clip(cv.spec, 0.0, 1.0), name=board.name,
                  meta={"generator": "board_scene", "board": board.name,
                        "board_file": board.source, "placement": labels["placement"],
                        "defects": dict(defects), "seed": int(seed), "finish": finish,
                        "fillet_curvature": (None if fillet_curvature is None
                                             else [k_lo, k_hi])})
    return scene, labels


# --------------------------------------------------------------------------------------
# Defect plan: per-joint fillet heights and per-component states, drawn before rendering.
# --------------------------------------------------------------------------------------


#: Severity of each defect class: the parameter that sets it (``params`` of
#: :func:`board_scene`), its realistic range (what :func:`random_board_case` draws) and
#: the IPC-A-610 Class 2 limit past which it is a defect (our reading, in the
#: parameter's unit; ``direction`` +1: larger is worse, -1: smaller is worse):
#:
#: * lifted_lead, lift of the foot (mm): the simulator leaves the solder as a 40–70 µm
#:   dome, so a foot raised by 50 µm or more has lost contact (no wetting: defect).
#: * tombstone, tilt of the body (deg): at 10° the raised end of the smallest part
#:   (0402) stands 0.17 mm off its pad, above any solder dome: an open joint.
#: * insufficient, fillet height as a fraction of the band minimum: below 1.
#: * excess, height above the band maximum (mm): above 0.
#: * bridge, height of the solder web over the mask (mm): any web joining two pads.
#: * component_shifted, side overhang of the termination (lead) beyond its pad as a
#:   fraction of the termination (lead) width: IPC-A-610 Class 2 allows 50 %.
#: * missing, component_missing: always.
SEVERITY: dict[str, dict[str, Any]] = {
    "lifted_lead": {"param": "lift_mm", "range": (0.05, 0.40), "limit": 0.05, "direction": 1},
    "tombstone": {"param": "tilt_deg", "range": (5.0, 90.0), "limit": 10.0, "direction": 1},
    "insufficient": {"param": "fraction", "range": (0.0, 0.90), "limit": 1.0, "direction": -1},
    "excess": {"param": "over_mm", "range": (0.02, 0.20), "limit": 0.0, "direction": 1},
    "bridge": {"param": "height_mm", "range": (0.06, 0.30), "limit": 0.0, "direction": 1},
    "component_shifted": {"param": "overhang_frac", "range": (0.2, 1.0), "limit": 0.5,
                          "direction": 1},
}


def _pad_width_across(comp: Component, j: Joint) -> tuple[int, float]:
    """(lateral axis, pad width across the part's pad axis) of joint ``j``."""
    loc = comp.to_local([j.center_mm])[0]
    axis, _ = _pad_axis(loc, comp.body_length_mm, comp.body_width_mm, comp.kind)
    ext = comp.to_local(j.polygon_mm)
    lateral = 1 - axis
    return lateral, float(np.ptp(ext[:, lateral]))


def _termination_width(comp: Component, lateral: int) -> float:
    if comp.kind == "gullwing" and comp.lead:
        return float(comp.lead["width_mm"])
    return float(comp.body_width_mm if lateral == 1 else comp.body_length_mm)


def _plan(board: Board, defects: dict[str, str], rng: np.random.Generator,
          params: dict[str, dict[str, Any]] | None = None) -> dict:
    params = params or {}
    joint_cls = {j.id: "ok" for j in board.joints()}
    comp_state: dict[str, dict[str, Any]] = {}
    extra: dict[str, dict[str, Any]] = {j.id: {} for j in board.joints()}
    severity: dict[str, dict[str, Any]] = {}

    def given(jid: str, key: str, drawn: Any) -> Any:
        # Draw first, then override: a seed gives the same scene with or without params.
        return params.get(jid, {}).get(key, drawn)

    for comp in board.components:
        state: dict[str, Any] = {"defect": None}
        for j in comp.joints:
            cls = defects.get(j.id, "ok")
            if cls in _COMPONENT_LEVEL:
                state = {"defect": cls, "joint": j.id}
        if state["defect"] == "tombstone":
            state["theta_deg"] = float(given(state["joint"], "tilt_deg",
                                             float(rng.uniform(60.0, 85.0))))
            if not 0.0 < state["theta_deg"] <= 90.0:
                raise InputError(f"{state['joint']}: tilt_deg must be in (0, 90]; got "
                                 f"{state['theta_deg']}")
            severity[comp.ref] = {"tilt_deg": state["theta_deg"]}
        if state["defect"] == "component_shifted":
            lateral, pad_w = _pad_width_across(comp, comp.joints[0])
            sign = float(rng.choice([-1.0, 1.0]))
            draw = float(rng.uniform(0.33, 0.40))
            sign = float(np.sign(params.get(state["joint"], {}).get("direction", sign)) or sign)
            w_t = _termination_width(comp, lateral)
            # Default: the termination overhangs its pad's side by 60–80 % of its width,
            # past the IPC-A-610 Class 2 limit (50 %).
            mag = (0.6 + (draw - 0.33) / 0.07 * 0.2) * w_t + (pad_w - w_t) / 2
            jid = state["joint"]
            if "overhang_frac" in params.get(jid, {}):
                mag = float(params[jid]["overhang_frac"]) * w_t + (pad_w - w_t) / 2
            shift = np.zeros(2)
            shift[lateral] = sign * mag
            state["shift_local"] = shift
            state["rotate_deg"] = float(given(jid, "rotate_deg", 0.0))
            severity[comp.ref] = {"overhang_frac": max(mag - (pad_w - w_t) / 2, 0.0) / w_t,
                                  "shift_mm": mag, "rotate_deg": state["rotate_deg"]}
        comp_state[comp.ref] = state
        for j in comp.joints:
            cls = state["defect"] or defects.get(j.id, "ok")
            joint_cls[j.id] = cls
    fillet: dict[str, float] = {}
    for j in board.joints():
        cls = joint_cls[j.id]
        nominal, lo, hi = j.nominal_height_mm, j.min_height_mm, j.max_height_mm
        if cls == "insufficient":
            f = min(rng.uniform(0.30, 0.40) * nominal, 0.75 * lo)
            f = float(given(j.id, "fraction", f / lo)) * lo
            severity[j.id] = {"fraction": f / lo}
        elif cls == "excess":
            f = hi + float(given(j.id, "over_mm", rng.uniform(0.08, 0.14)))
            extra[j.id]["style"] = str(given(j.id, "style", "cap"))
            if extra[j.id]["style"] not in ("cap", "convex"):
                raise InputError(f"{j.id}: excess style must be 'cap' or 'convex'; got "
                                 f"{extra[j.id]['style']!r}")
            severity[j.id] = {"over_mm": f - hi, "style": extra[j.id]["style"]}
        elif cls in ("missing", "lifted_lead", "component_missing"):
            f = 0.0
        else:
            f = float(np.clip(nominal * rng.uniform(0.92, 1.08), lo * 1.25, hi * 0.9))
        fillet[j.id] = float(f)
        if cls in ("lifted_lead",):
            lift = float(given(j.id, "lift_mm", float(rng.uniform(0.10, 0.20))))
            extra[j.id]["lift_mm"] = lift
            # The solder left on the pad stays below the raised foot's underside.
            extra[j.id]["dome_mm"] = min(float(rng.uniform(0.04, 0.07)),
                                         0.03 + 0.6 * lift)
            severity[j.id] = {"lift_mm": lift}
        if cls == "component_missing":
            extra[j.id]["dome_mm"] = float(rng.uniform(0.06, 0.10))
        if cls == "tombstone" and comp_state[j.component].get("joint") == j.id:
            comp = board.component(j.component)
            extra[j.id]["lifted"] = True
            dome = float(rng.uniform(0.05, 0.09))
            raise_mm = comp.body_length_mm * math.sin(math.radians(
                comp_state[comp.ref]["theta_deg"]))
            extra[j.id]["dome_mm"] = min(dome, 0.5 * raise_mm + comp.standoff_mm)
    bridges: dict[str, str] = {}
    for jid, cls in defects.items():
        if cls == "bridge":
            comp = board.component(board.joint(jid).component)
            partner = _bridge_partner(comp, board.joint(jid))
            bridges[jid] = partner
            extra[jid]["bridge_to"] = partner
            extra[partner].setdefault("bridged_by", jid)
            frac = float(rng.uniform(0.0, 1.0))
            extra[jid]["bridge_frac"] = frac
            extra[jid]["bridge_side"] = float(rng.choice([-1.0, 1.0]))
            if comp.kind == "chip":
                hb, wb = 0.12 + 0.08 * frac, 0.26
            else:
                lead = comp.lead
                hb = lead["solder_thickness_mm"] + lead["thickness_mm"] + 0.02 + 0.06 * frac
                wb = 2 * min(0.3, lead["foot_length_mm"] / 2)
            extra[jid]["bridge_height_mm"] = float(given(jid, "height_mm", hb))
            extra[jid]["bridge_width_mm"] = float(given(jid, "width_mm", wb))
            severity[jid] = {"height_mm": extra[jid]["bridge_height_mm"],
                             "width_mm": extra[jid]["bridge_width_mm"]}
    return {"joint_cls": joint_cls, "comp": comp_state, "fillet": fillet, "extra": extra,
            "bridges": bridges, "rng": rng, "severity": severity}


def _beyond_limit(cls: str, severity: Mapping[str, Any]) -> bool:
    """Whether a defect of ``cls`` with ``severity`` is past its limit (:data:`SEVERITY`)."""
    if cls == "ok":
        return False
    spec = SEVERITY.get(cls)
    if spec is None or spec["param"] not in severity:
        return True                     # missing, component_missing: always a defect
    v = float(severity[spec["param"]])
    return bool(v > spec["limit"]) if spec["direction"] > 0 else bool(v < spec["limit"])


#: Below this fillet height (mm) an insufficient joint is as good as missing: a verdict
#: of ``missing`` names it right too (the inspector's ``missing_height_mm``).
_MISSING_LIKE_MM = 0.04


def _accept(entry: dict, j: Joint, plan) -> set[str]:
    """Verdicts that name a joint right: its class, ``bridge`` on a bridge's partner,
    ``missing`` for an insufficient joint with (almost) no fillet."""
    out = {entry["class"]}
    if "bridged_by" in entry:
        out.add("bridge")
    if entry["class"] == "insufficient" and plan["fillet"][j.id] < _MISSING_LIKE_MM:
        out.add("missing")
    return out


def _bridge_partner(comp: Component, joint: Joint) -> str:
    """The neighbouring pad a bridge from ``joint`` runs to.

    Chips: the other end. Gull-wing: the nearest pad on the same side of the body.
    """
    others = [j for j in comp.joints if j.id != joint.id]
    if comp.kind == "chip":
        return others[0].id
    same = [j for j in others if np.allclose(j.outward, joint.outward, atol=1e-6)]
    cand = same or others
    c = np.array(joint.center_mm)
    d = [float(np.hypot(*(np.array(j.center_mm) - c))) for j in cand]
    return cand[int(np.argmin(d))].id


# --------------------------------------------------------------------------------------
# The canvas: world-frame arrays and the drawing of every layer.
# --------------------------------------------------------------------------------------


class _Canvas:
    def __init__(self, shape, p, board: Board, off, rot, seed) -> None:
        import cv2  # noqa: F401  (fail early if OpenCV is missing)

        self.shape = shape
        self.H, self.W = shape
        self.p = p
        self.board = board
        self.off = off
        self.rot = rot
        a = math.radians(rot)
        c, s = math.cos(a), math.sin(a)
        self.R = np.array([[c, -s], [s, c]])
        bw, bh = board.size_mm
        centre = np.array([(self.W - 1) / 2 * p, (self.H - 1) / 2 * p])
        self.t = centre + np.array(off) - self.R @ np.array([bw / 2, bh / 2])
        # board (x, y) → pixel (col, row)
        self.A = np.array([[c / p, -s / p, self.t[0] / p],
                           [-s / p, -c / p, self.H - 1 - self.t[1] / p]])
        self.z = np.zeros(shape, np.float32)
        self.rgb = np.zeros(shape + (3,), np.float32)
        self.spec = np.zeros(shape, np.float32)
        self.solder = np.zeros(shape, bool)
        self.jmap = np.zeros(shape, np.uint16)
        self.joints = board.joints()
        self.jindex = {j.id: k + 1 for k, j in enumerate(self.joints)}
        self.seed = int(seed)
        self._textures()

    # -- coordinates ---------------------------------------------------------------
    def to_px(self, pts_board) -> np.ndarray:
        pts = np.asarray(pts_board, np.float64).reshape(-1, 2)
        return pts @ self.A[:, :2].T + self.A[:, 2]

    def window(self, pts_board, margin_mm: float):
        px = self.to_px(pts_board)
        m = margin_mm / self.p + 2
        c0 = int(max(math.floor(px[:, 0].min() - m), 0))
        c1 = int(min(math.ceil(px[:, 0].max() + m) + 1, self.W))
        r0 = int(max(math.floor(px[:, 1].min() - m), 0))
        r1 = int(min(math.ceil(px[:, 1].max() + m) + 1, self.H))
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def board_xy(self, win):
        r0, r1, c0, c1 = win
        rows, cols = np.mgrid[r0:r1, c0:c1].astype(np.float64)
        x = cols * self.p - self.t[0]
        y = (self.H - 1 - rows) * self.p - self.t[1]
        # board = Rᵀ (world − t)
        bx = self.R[0, 0] * x + self.R[1, 0] * y
        by = self.R[0, 1] * x + self.R[1, 1] * y
        return bx, by

    # -- textures ------------------------------------------------------------------
    def _noise(self, k: int, sigma_mm: float, *, coarse: bool = False) -> np.ndarray:
        """Unit Gaussian texture of correlation ``sigma_mm``, fixed to the board.

        It is drawn once for the board in its own frame (the default field of
        :func:`board_shape`, the board at its centre, unturned) and read through the
        placement: a re-placed board shows the same texture under each of its parts, as
        a real board does, and a crop of the field the same as the whole field (drawn in
        image coordinates, every placement showed new texture under a joint, and a
        gauge study of re-placed sweeps counted that against the gauge). A fine texture
        (under 1.5 px) is drawn on a grid ``FINE`` times finer and read at the pixel
        centres, so that a placement does not blur it (read from the pixel grid, a
        half-pixel shift took 40 % of the Laplacian energy of the 0.6-px textures).
        """
        import cv2

        gen = np.random.default_rng([self.seed, 0x7E47, k])
        sig = max(sigma_mm / self.p, 0.6)
        hs, ws = self._own_shape
        warp = self._own_warp
        if coarse and sig > 4:
            f = sig / 2.0
            small = (max(int(hs / f) + 2, 4), max(int(ws / f) + 2, 4))
            n = gen.standard_normal(small).astype(np.float32)
            n = cv2.GaussianBlur(n, (0, 0), 2.0)
            n = cv2.resize(n, (ws, hs), interpolation=cv2.INTER_CUBIC)
            u = 1
        else:
            u = 1 if sig >= 1.5 else self.FINE
            n = gen.standard_normal((u * hs, u * ws)).astype(np.float32)
            # OpenCV's kernel sampled on the pixel grid at σ 0.6 px passes twice the
            # continuous Gaussian's amplitude at Nyquist; the slightly narrower σ keeps
            # the textures' Laplacian energy that of the former draw (within 8 % for
            # σ 0.6-1.2 px)
            narrow = 0.925 + 0.075 * min(max((sig - 0.6) / 0.4, 0.0), 1.0) if u > 1 else 1.0
            n = cv2.GaussianBlur(n, (0, 0), sig * u * narrow)
        if warp is not None or u > 1:
            # pixel x -> the board's own pixel (warp) -> its sample u·x + u//2 there
            m = np.hstack([np.eye(2), np.zeros((2, 1))]) if warp is None else warp
            m = m * u
            m[:, 2] += u // 2
            n = cv2.warpAffine(n, m, (self.W, self.H),
                               flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT_101)
        n -= n.mean()
        sd = float(n.std())
        return n / sd if sd > 0 else n

    #: Oversampling of the fine textures (see :meth:`_noise`).
    FINE = 3

    def _board_warp(self, own_shape: tuple[int, int]) -> np.ndarray | None:
        """2×3 map from this placement's pixels to the board's own frame (a field of
        ``own_shape``, the board at its centre, unturned); None when they coincide."""
        bw, bh = self.board.size_mm
        p = self.p
        hs, ws = own_shape
        t0 = np.array([(ws - 1) / 2 * p, (hs - 1) / 2 * p]) - np.array([bw / 2, bh / 2])
        lin0 = np.array([[1 / p, 0.0], [0.0, -1 / p]])
        a0 = np.array([t0[0] / p, hs - 1 - t0[1] / p])
        lin, a = self.A[:, :2], self.A[:, 2]
        if own_shape == self.shape and np.allclose(lin, lin0, atol=1e-12) and \
                np.allclose(a, a0, atol=1e-9):
            return None
        m = lin0 @ np.linalg.inv(lin)
        return np.hstack([m, (a0 - m @ a)[:, None]])

    def _textures(self) -> None:
        self._own_shape = board_shape(self.board, pixel_size_mm=self.p)
        self._own_warp = self._board_warp(self._own_shape)
        self.n_fine = self._noise(1, 0.009)
        self.n_med = self._noise(2, 0.04)
        self.n_coarse = self._noise(3, 0.5, coarse=True)
        self.n_grain = self._noise(4, 0.011)
        self.n_grain2 = self._noise(5, 0.02)

    def tex(self, win, name):
        r0, r1, c0, c1 = win
        return getattr(self, name)[r0:r1, c0:c1]

    # -- compositing ---------------------------------------------------------------
    def put(self, win, z_new, rgb_new, spec_new, valid, *, solder: bool = False,
            force: bool = False) -> None:
        r0, r1, c0, c1 = win
        zc = self.z[r0:r1, c0:c1]
        m = valid if force else (valid & (z_new > zc))
        if not m.any():
            return
        zc[m] = np.asarray(z_new, np.float32)[m] if np.ndim(z_new) else z_new
        rc = self.rgb[r0:r1, c0:c1]
        rc[m] = rgb_new[m] if np.ndim(rgb_new) == 3 else rgb_new
        sc = self.spec[r0:r1, c0:c1]
        sc[m] = spec_new[m] if np.ndim(spec_new) == 2 else spec_new
        self.solder[r0:r1, c0:c1][m] = solder

    def colour(self, win, base, *, fine=0.0, med=0.0, coarse=0.0, grain=0.0) -> np.ndarray:
        f = 1.0
        if fine:
            f = f + fine * self.tex(win, "n_fine")
        if med:
            f = f + med * self.tex(win, "n_med")
        if coarse:
            f = f + coarse * self.tex(win, "n_coarse")
        if grain:
            f = f + grain * self.tex(win, "n_grain")
        f = np.asarray(f, np.float32)
        if f.ndim == 0:
            r0, r1, c0, c1 = win
            f = np.full((r1 - r0, c1 - c0), float(f), np.float32)
        return f[..., None] * base[None, None, :]

    def full(self):
        return (0, self.H, 0, self.W)

    # -- 2D drawing helpers (OpenCV in pixel coordinates, 1/16 px precision) ---------
    def _pts16(self, pts_board) -> np.ndarray:
        return np.round(self.to_px(pts_board) * 16).astype(np.int32)

    def fill_poly(self, img, pts_board, value) -> None:
        import cv2

        cv2.fillPoly(img, [self._pts16(pts_board)], value, lineType=cv2.LINE_8, shift=4)

    def polyline(self, img, pts_board, value, width_mm, closed=False) -> None:
        import cv2

        th = max(int(round(width_mm / self.p)), 1)
        cv2.polylines(img, [self._pts16(pts_board)], closed, value, thickness=th,
                      lineType=cv2.LINE_8, shift=4)

    def text_mask(self, text, centre_board, angle_deg, height_mm, weight=0.12):
        """uint8 full-frame mask of ``text`` centred at a board point, rotated."""
        import cv2

        font = cv2.FONT_HERSHEY_SIMPLEX
        (tw, th), base = cv2.getTextSize(text, font, 1.0, 2)
        scale_px = height_mm / self.p / th           # glyph px per font unit at p
        sup = 4.0 if scale_px < 2 else 1.0          # draw small text supersampled
        fs = scale_px * sup
        thick = max(int(round(fs * 2 * (weight / 0.12) * 0.5 + 0.5)), 1)
        pad = thick + 2
        pw = int(tw * fs) + 2 * pad
        ph = int((th + base) * fs) + 2 * pad
        patch = np.zeros((ph, pw), np.uint8)
        cv2.putText(patch, text, (pad, pad + int(th * fs)), font, fs, 255, thick,
                    cv2.LINE_AA)
        # patch pixel (pc, pr) → text mm: ((pc − pw/2)·q, (ph/2 − pr)·q), q = p / sup
        q = self.p / sup
        a = math.radians(angle_deg)
        rt = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        lin = rt @ np.array([[q, 0.0], [0.0, -q]])
        off = np.asarray(centre_board, float) - lin @ np.array([pw / 2, ph / 2])
        M = np.zeros((2, 3))
        M[:, :2] = self.A[:, :2] @ lin
        M[:, 2] = self.A[:, :2] @ off + self.A[:, 2]
        corners = np.array([[0, 0], [pw, 0], [pw, ph], [0, ph]], float)
        cpx = corners @ M[:, :2].T + M[:, 2]
        c0 = int(max(math.floor(cpx[:, 0].min()) - 1, 0))
        c1 = int(min(math.ceil(cpx[:, 0].max()) + 2, self.W))
        r0 = int(max(math.floor(cpx[:, 1].min()) - 1, 0))
        r1 = int(min(math.ceil(cpx[:, 1].max()) + 2, self.H))
        out = np.zeros(self.shape, np.uint8)
        if c0 >= c1 or r0 >= r1:
            return out
        M2 = M.copy()
        M2[:, 2] -= [c0, r0]
        out[r0:r1, c0:c1] = cv2.warpAffine(patch, M2, (c1 - c0, r1 - r0),
                                           flags=cv2.INTER_AREA if sup > 1 else
                                           cv2.INTER_LINEAR)
        return out

    # -- the bare board --------------------------------------------------------------
    def draw_board(self, plan) -> None:
        import cv2

        full = self.full()
        rng = np.random.default_rng([self.seed, 0xB0A2D])
        # Solder mask everywhere (the board sits in a panel of the same mask).
        self.z[:] = 0.0015 * self.n_med
        self.rgb[:] = self.colour(full, _MASK, **_MASK_TEX)
        self.spec[:] = 0.12

        # Copper traces and tented vias under the mask: raised, lighter green. A trace
        # never passes near a pad other than its own or near a fiducial.
        keep = [(j.id, j.polygon_mm.min(axis=0), j.polygon_mm.max(axis=0))
                for j in self.joints]
        keep += [(f.id, np.array([f.x_mm, f.y_mm]) - f.diameter_mm,
                  np.array([f.x_mm, f.y_mm]) + f.diameter_mm) for f in self.board.fiducials]

        def clear(path, width, own=None):
            pts = []
            for a, b in zip(path[:-1], path[1:]):
                n = max(int(np.hypot(*(b - a)) / 0.05), 1)
                pts.append(a + (b - a) * np.linspace(0, 1, n + 1)[:, None])
            pts = np.vstack(pts)
            m = width / 2 + 0.12
            for kid, lo, hi in keep:
                if kid == own:
                    continue
                if np.any((pts[:, 0] > lo[0] - m) & (pts[:, 0] < hi[0] + m)
                          & (pts[:, 1] > lo[1] - m) & (pts[:, 1] < hi[1] + m)):
                    return False
            return True

        trace = np.zeros(self.shape, np.uint8)
        vias = []
        for comp in self.board.components:
            for j in comp.joints:
                if rng.random() < 0.25:
                    continue
                out = np.array(j.outward)
                c = np.array(j.center_mm)
                ext = float(np.max((j.polygon_mm - c) @ out))
                w_mm = rng.uniform(0.12, 0.2) if comp.kind == "gullwing" else \
                    rng.uniform(0.18, 0.3)
                for _ in range(4):
                    l1 = ext + rng.uniform(0.35, 1.0)
                    turn = np.array([-out[1], out[0]]) * rng.choice([-1.0, 1.0])
                    p1 = c + out * l1
                    p2 = p1 + turn * rng.uniform(0.2, 1.2)
                    if clear([c + out * ext, p1, p2], w_mm + 0.5, own=j.id):
                        self.polyline(trace, [c, p1, p2], 255, w_mm)
                        if rng.random() < 0.6:
                            vias.append(p2)
                        break
        for v in vias:
            self.fill_poly(trace, _circle(v, 0.25), 255)
        bw, bh = self.board.size_mm
        # A few long traces across the board (power routing) where they find room.
        for _ in range(12):
            y = rng.uniform(0.05, 0.95) * bh
            wt = rng.uniform(0.25, 0.4)
            path = [np.array([-3.0, y]), np.array([bw + 3.0, y])]
            if clear(path, wt):
                self.polyline(trace, path, 255, wt)
        tr = trace.astype(np.float32) / 255.0
        tr_h = cv2.GaussianBlur(tr, (0, 0), max(0.02 / self.p, 0.5))
        self.z += _Z_MASK_TRACE * tr_h
        mix = tr[..., None]
        self.rgb[:] = self.rgb * (1 - mix) + self.colour(full, _MASK_TRACE, **_MASK_TEX) * mix
        drill = np.zeros(self.shape, np.uint8)
        for v in vias:
            self.fill_poly(drill, _circle(v, 0.1), 255)
        dm = drill > 0
        self.z[dm] -= 0.03
        self.rgb[dm] *= 0.55

        # Silkscreen: outlines, reference designators, pin-1 marks, board name.
        silk = np.zeros(self.shape, np.uint8)
        for comp in self.board.components:
            loc = np.vstack([comp.to_local(j.polygon_mm) for j in comp.joints]
                            + [comp.to_local(comp.body_polygon_mm())])
            lo = loc.min(axis=0) - 0.18
            hi = loc.max(axis=0) + 0.18
            rect = [[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]
            self.polyline(silk, comp.to_board(rect), 255, 0.10, closed=True)
            if comp.kind == "gullwing":
                self.fill_poly(silk, _circle(comp.to_board([[lo[0] - 0.2, lo[1] - 0.2]])[0],
                                             0.12), 255)
            ang = comp.rotation_deg % 360.0
            up = (90.0 < ang <= 270.0)
            text_y = (lo[1] - 0.32) if not up else (hi[1] + 0.32)
            text_centre = comp.to_board([[0.0, text_y if comp.kind == "chip" else
                                          lo[1] - 0.32]])[0]
            text_ang = comp.rotation_deg + (180.0 if up else 0.0)
            silk |= self.text_mask(comp.ref, text_centre, text_ang, 0.4)
        silk |= self.text_mask(self.board.name, [bw / 2, -0.45], 0.0, 0.35)
        sm = silk.astype(np.float32)[..., None] / 255.0
        self.rgb[:] = self.rgb * (1 - sm) + self.colour(full, _SILK, fine=0.06) * sm
        self.z += _Z_SILK * sm[..., 0]
        self.spec[:] = self.spec * (1 - sm[..., 0]) + 0.03 * sm[..., 0]

        # Mask openings (bare laminate), then ENIG pads and fiducials in them.
        pads = np.zeros(self.shape, np.uint8)
        for j in self.joints:
            self.fill_poly(pads, j.polygon_mm, 255)
            self.fill_poly(self.jmap, j.polygon_mm, self.jindex[j.id])
        fid = np.zeros(self.shape, np.uint8)
        fid_open = np.zeros(self.shape, np.uint8)
        for f in self.board.fiducials:
            self.fill_poly(fid, _circle((f.x_mm, f.y_mm), f.diameter_mm / 2), 255)
            self.fill_poly(fid_open, _circle((f.x_mm, f.y_mm), f.diameter_mm), 255)
        r = max(int(round(0.06 / self.p)), 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        opening = (cv2.dilate(pads, kernel) > 0) | (fid_open > 0)
        lam = self.colour(full, _LAMINATE, fine=0.08, med=0.06)
        self.z[opening] = _Z_LAMINATE + 0.002 * self.n_fine[opening]
        self.rgb[opening] = lam[opening]
        self.spec[opening] = 0.05
        # Trace copper is exposed where it runs through an opening.
        metal = (pads > 0) | (fid > 0) | (opening & (trace > 0) & (drill == 0))
        colour, shine = FINISHES[getattr(self, "finish", "enig")]
        finish = self.colour(full, colour, fine=0.05, med=0.03)
        self.z[metal] = 0.0005 * self.n_fine[metal]
        if getattr(self, "finish", "enig") == "hasl":
            # Hot-air levelled solder: an uneven pillow of 5–10 µm over the copper.
            pill = cv2.GaussianBlur(metal.astype(np.float32), (0, 0),
                                    max(0.05 / self.p, 0.5))
            self.z[metal] += (0.005 + 0.005 * np.clip(self.n_coarse[metal], -1, 1)) * \
                np.clip(2 * pill[metal] - 0.5, 0, 1)
        self.rgb[metal] = finish[metal]
        self.spec[metal] = shine
        self.solder[:] = False

    # -- components ------------------------------------------------------------------
    def draw_component(self, comp: Component, plan) -> None:
        state = plan["comp"][comp.ref]
        shift_local = state.get("shift_local", np.zeros(2))
        shift_board = _rot(comp.rotation_deg) @ shift_local
        centre = np.array([comp.x_mm, comp.y_mm]) + shift_board
        pts = [j.polygon_mm for j in comp.joints] + [comp.body_polygon_mm() + shift_board]
        if comp.kind == "gullwing":
            s = comp.lead["span_mm"] / 2
            hl, hw = comp.body_length_mm / 2, comp.body_width_mm / 2
            pts.append(comp.to_board([[-max(hl, s), -max(hw, s)], [max(hl, s), max(hw, s)]])
                       + shift_board)
        extent = np.vstack(pts)
        margin = 0.3 + (comp.body_height_mm if state["defect"] == "tombstone" else 0.0)
        win = self.window(extent, margin)
        if win is None:
            return
        bx, by = self.board_xy(win)
        # Local coordinates of the (possibly shifted and turned) part.
        a = math.radians(comp.rotation_deg + state.get("rotate_deg", 0.0))
        ca, sa = math.cos(a), math.sin(a)
        dx, dy = bx - centre[0], by - centre[1]
        u = ca * dx + sa * dy
        v = -sa * dx + ca * dy
        ctx = _Ctx(self, win, comp, plan, u, v, centre)
        if comp.kind == "chip":
            _draw_chip(ctx)
        else:
            _draw_gullwing(ctx)

    # -- truth -----------------------------------------------------------------------
    def field_state(self, comp: Component, state: dict) -> str:
        """"in", "partial" or "out": the component's body (where it stands: ``state``
        holds a shifted part's ``shift_local`` and ``rotate_deg``) and pads against the
        image."""
        body = comp.body_polygon_mm()
        if "shift_local" in state:
            hl, hw = comp.body_length_mm / 2, comp.body_width_mm / 2
            corners = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
            turned = corners @ _rot(state.get("rotate_deg", 0.0)).T + state["shift_local"]
            body = np.vstack([body, comp.to_board(turned)])
        pts = np.vstack([body] + [j.polygon_mm for j in comp.joints])
        px = self.to_px(pts)
        inside = (px[:, 0] >= 0) & (px[:, 0] <= self.W - 1) & (px[:, 1] >= 0) & \
            (px[:, 1] <= self.H - 1)
        return "in" if inside.all() else ("out" if not inside.any() and not
                                          self._overlaps(px) else "partial")

    def _overlaps(self, px) -> bool:
        lo, hi = px.min(axis=0), px.max(axis=0)
        return bool(lo[0] <= self.W - 1 and hi[0] >= 0 and lo[1] <= self.H - 1 and hi[1] >= 0)

    def labels(self, plan) -> dict[str, Any]:
        bw, bh = self.board.size_mm
        joints = []
        for j in self.joints:
            k = self.jindex[j.id]
            m = (self.jmap == k)
            in_view = bool(m.any())
            sm = m & self.solder
            h = float(self.z[sm].max()) if sm.any() else 0.0
            entry = {"id": j.id, "component": j.component, "class": plan["joint_cls"][j.id],
                     "true_height_mm": round(max(h, 0.0), 5), "in_view": in_view}
            ex = plan["extra"][j.id]
            for key in ("bridge_to", "bridged_by", "lifted"):
                if key in ex:
                    entry[key] = ex[key]
            st = plan["comp"][j.component]
            if "shift_local" in st:
                comp = self.board.component(j.component)
                sb = _rot(comp.rotation_deg) @ st["shift_local"]
                entry["shift_mm"] = [round(float(sb[0]), 5), round(float(sb[1]), 5)]
            if "theta_deg" in st:
                entry["tilt_deg"] = round(st["theta_deg"], 3)
            sev = plan["severity"].get(j.id) or plan["severity"].get(j.component) or {}
            entry["severity"] = {k: (round(float(v), 5) if not isinstance(v, str) else v)
                                 for k, v in sev.items()}
            entry["beyond_limit"] = _beyond_limit(entry["class"], entry["severity"])
            entry["accept"] = sorted(_accept(entry, j, plan))
            entry["field"] = self.field_state(self.board.component(j.component), st)
            joints.append(entry)
        T = np.eye(3)
        T[:2, :2] = self.R
        T[:2, 2] = self.t
        return {"board": self.board.name, "board_file": self.board.source,
                "pixel_size_mm": self.p, "image_shape": [self.H, self.W],
                "placement": {"offset_mm": [self.off[0], self.off[1]],
                              "rotate_deg": self.rot,
                              "board_to_world": T.tolist()},
                "joints": joints}


class _Ctx:
    """Everything the component painters need about one component's window."""

    def __init__(self, cv: _Canvas, win, comp: Component, plan, u, v, centre) -> None:
        self.cv, self.win, self.comp, self.plan, self.u, self.v = cv, win, comp, plan, u, v
        self.centre = centre
        self.state = plan["comp"][comp.ref]
        r0, r1, c0, c1 = win
        self.jmap = cv.jmap[r0:r1, c0:c1]
        self.rng = np.random.default_rng([cv.seed, 0xC0, cv.jindex[comp.joints[0].id]])

    def to_local(self, pts_board) -> np.ndarray:
        a = math.radians(self.comp.rotation_deg + self.state.get("rotate_deg", 0.0))
        d = np.asarray(pts_board, float).reshape(-1, 2) - self.centre
        return np.column_stack([math.cos(a) * d[:, 0] + math.sin(a) * d[:, 1],
                                -math.sin(a) * d[:, 0] + math.cos(a) * d[:, 1]])

    def pad_mask(self, j: Joint) -> np.ndarray:
        return self.jmap == self.cv.jindex[j.id]

    def joint_axes(self, j: Joint):
        """(axis, sign, lateral centre) of the joint in the part's nominal local frame."""
        loc = self.comp.to_local([j.center_mm])[0]
        axis, sign = _pad_axis(loc, self.comp.body_length_mm, self.comp.body_width_mm,
                               self.comp.kind)
        return axis, sign, float(loc[1 - axis])

    def wq(self, axis: int, sign: int, q0: float = 0.0):
        uv = (self.u, self.v)
        return sign * uv[axis], uv[1 - axis] - q0

    def pad_extent(self, j: Joint, axis: int, sign: int, q0: float = 0.0):
        loc = self.to_local(j.polygon_mm)
        w = sign * loc[:, axis]
        q = loc[:, 1 - axis] - q0
        return float(w.min()), float(w.max()), float(q.min()), float(q.max())

    def put_solder(self, z, valid) -> None:
        cv = self.cv
        zz = z + 0.0025 * cv.tex(self.win, "n_grain")
        rgb = cv.colour(self.win, _SOLDER, grain=0.18, med=0.04)
        spec = np.clip(0.75 + 0.15 * cv.tex(self.win, "n_grain2"), 0.3, 1.0)
        cv.put(self.win, zz, rgb, spec, valid & (z > 0), solder=True)


# --------------------------------------------------------------------------------------
# Shapes.
# --------------------------------------------------------------------------------------


def _positive(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or \
            not math.isfinite(value) or value <= 0:
        raise InputError(f"{name} must be a number > 0; got {value!r}")
    return float(value)


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _circle(c, r, n: int = 48) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)])


def _rounded_top(d, top, r):
    """Height of a flat top ``top`` whose edge (distance ``d`` ≥ 0 inside) is rounded."""
    dd = np.clip(d, 0.0, r)
    return top - (r - np.sqrt(np.maximum(r * r - (r - dd) ** 2, 0.0)))


def _fillet(s, F, convex: bool):
    s = np.minimum(s, 1.0)
    if convex:
        return F * np.maximum(1.0 - s * s, 0.0) ** 0.6
    return F * (1.0 - s) ** 2


def _dome(w, q, extent, h):
    """Reflowed solder pillow over a pad: flat-topped, falling to 0 at the pad edge."""
    w0, w1, q0, q1 = extent
    a, b = (w1 - w0) / 2, (q1 - q0) / 2
    tw = np.clip(1 - ((w - (w0 + w1) / 2) / a) ** 4, 0, None)
    tq = np.clip(1 - ((q - (q0 + q1) / 2) / b) ** 4, 0, None)
    return h * np.sqrt(tw * tq)


def _text_code(rng) -> str:
    digits = "0123456789"
    return "".join(rng.choice(list(digits), 2)) + str(rng.integers(0, 6))


# --------------------------------------------------------------------------------------
# Chips.
# --------------------------------------------------------------------------------------


def _draw_chip(ctx: _Ctx) -> None:
    cv, comp, plan, win = ctx.cv, ctx.comp, ctx.plan, ctx.win
    u, v = ctx.u, ctx.v
    hl, hw = comp.body_length_mm / 2, comp.body_width_mm / 2
    t = comp.termination_length_mm
    G, H = comp.standoff_mm, comp.body_height_mm
    state = ctx.state
    defect = state["defect"]

    # Solder of each joint.
    for j in comp.joints:
        cls = plan["joint_cls"][j.id]
        ex = plan["extra"][j.id]
        axis, sign, _ = ctx.joint_axes(j)
        w, q = ctx.wq(axis, sign)
        pad = ctx.pad_mask(j)
        extent = ctx.pad_extent(j, axis, sign)
        if cls == "component_missing" or ex.get("lifted"):
            ctx.put_solder(_dome(w, q, extent, ex["dome_mm"]), pad)
            continue
        if cls == "missing":
            continue
        F = plan["fillet"][j.id]
        w_in, w_out, q_lo, q_hi = extent
        d_toe = max(w_out - hl, 0.04)
        d_qp = max(q_hi - hw, 0.04)
        d_qm = max(-hw - q_lo, 0.04)
        s_t = np.clip((w - hl) / d_toe, 0, None)
        s_q = np.clip(np.where(q >= 0, (q - hw) / d_qp, (-hw - q) / d_qm), 0, None)
        s_i = np.clip(((hl - t) - w) / 0.06, 0, None)
        s = np.sqrt(s_t ** 2 + s_q ** 2 + s_i ** 2)
        convex = cls == "excess"
        k = plan["arc"].get(j.id)
        z = _fillet(s, F, convex) if convex or k is None else arc_fillet(s, F, d_toe, k)
        z = np.where(pad, np.maximum(z, _SOLDER_COAT), 0.0)
        if convex and ex.get("style", "cap") == "cap":
            # Solder over the end cap, rising to F at the end face.
            on_cap = (w >= hl - t) & (w <= hl) & (np.abs(q) <= hw)
            frac = np.clip(1 - ((hl - w) / t) ** 2, 0, 1)
            lat = np.sqrt(np.clip(1 - (q / hw) ** 4, 0, 1))
            cap = (G + H) + (F - G - H) * np.sqrt(frac) * lat + 0.01 * lat
            z = np.where(on_cap, np.maximum(z, cap), z)
        ctx.put_solder(z, pad | (z > 0))
        if cls == "bridge":
            side = ex["bridge_side"]
            half = ex["bridge_width_mm"] / 2
            # The web wets the body's side: its inner edge lies just under the body.
            qc = side * (hw + max(0.03, 0.8 * half))
            hb = ex["bridge_height_mm"]
            uu = u if axis == 0 else v
            vv = v if axis == 0 else u
            taper = np.clip((hl + 0.15 - np.abs(uu)) / 0.15, 0, 1)
            ridge = hb * np.clip(1 - ((vv - qc) / half) ** 2, 0, None) * taper
            ctx.put_solder(ridge, ridge > 0)

    if defect == "component_missing":
        return

    body_rgb = _RES_TOP if comp.style == "resistor" else _MLCC
    body_tex = dict(fine=0.35, med=0.1) if comp.style == "resistor" else \
        dict(fine=0.1, med=0.06, coarse=0.04)
    if defect == "tombstone":
        _draw_tombstone(ctx, body_rgb, body_tex)
        return

    inside = (np.abs(u) <= hl) & (np.abs(v) <= hw)
    d = np.minimum(hl - np.abs(u), hw - np.abs(v))
    cap = np.abs(u) > hl - t
    z_body = _rounded_top(d, G + H, 0.03)
    z_cap = _rounded_top(d, G + H + 0.004, 0.05)
    z = np.where(cap, z_cap, z_body)
    rgb = np.where(cap[..., None], cv.colour(win, _TIN, fine=0.15, med=0.05),
                   cv.colour(win, body_rgb, **body_tex))
    spec = np.where(cap, 0.5, 0.08 if comp.style == "resistor" else 0.1)
    if comp.style == "resistor" and comp.body_length_mm >= 1.5:
        code = _text_code(ctx.rng)
        mark = ctx.cv.text_mask(code, ctx.centre, comp.rotation_deg,
                                0.45 * comp.body_width_mm)
        r0, r1, c0, c1 = win
        mk = (mark[r0:r1, c0:c1].astype(np.float32) / 255.0)[..., None] * (~cap)[..., None]
        rgb = rgb * (1 - mk) + cv.colour(win, _RES_MARK, fine=0.1) * mk
    cv.put(win, z.astype(np.float32), rgb, spec, inside)


def _draw_tombstone(ctx: _Ctx, body_rgb, body_tex) -> None:
    cv, comp, win = ctx.cv, ctx.comp, ctx.win
    u, v = ctx.u, ctx.v
    hl, hw = comp.body_length_mm / 2, comp.body_width_mm / 2
    t = comp.termination_length_mm
    G, H = comp.standoff_mm, comp.body_height_mm
    lifted = comp._joint(ctx.state["joint"])
    _, s, _ = ctx.joint_axes(lifted)           # +1: the +u end lifts
    phi = math.radians(ctx.state["theta_deg"]) * s
    P = np.array([-s * hl, G])
    Rp = np.array([[math.cos(phi), -math.sin(phi)], [math.sin(phi), math.cos(phi)]])
    orig = np.array([[-hl, G], [hl, G], [hl, G + H], [-hl, G + H]])
    rc = (orig - P) @ Rp.T + P
    edges = [(0, 1, "bottom"), (1, 2, "end"), (2, 3, "top"), (3, 0, "end")]
    zmax = np.full(u.shape, -np.inf)
    kind = np.zeros(u.shape, np.int8)          # 1 body top, 2 body bottom, 3 tin
    for a, b, name in edges:
        ua, za = rc[a]
        ub, zb = rc[b]
        if abs(ub - ua) < 1e-9:
            continue
        tau = (u - ua) / (ub - ua)
        ok = (tau >= 0) & (tau <= 1)
        z = za + tau * (zb - za)
        ou = orig[a, 0] + tau * (orig[b, 0] - orig[a, 0])
        if name == "end":
            k = np.full(u.shape, 3, np.int8)
        else:
            k = np.where(np.abs(ou) > hl - t, 3, 1 if name == "top" else 2).astype(np.int8)
        better = ok & (z > zmax)
        zmax = np.where(better, z, zmax)
        kind = np.where(better, k, kind)
    valid = np.isfinite(zmax) & (np.abs(v) <= hw)
    dv = hw - np.abs(v)
    z = np.where(valid, _rounded_top(dv, np.where(valid, zmax, 0.0), 0.03), 0.0)
    bottom_rgb = _ALUMINA if comp.style == "resistor" else _MLCC
    rgb = np.where((kind == 3)[..., None], cv.colour(win, _TIN, fine=0.15, med=0.05),
                   np.where((kind == 2)[..., None], cv.colour(win, bottom_rgb, fine=0.08),
                            cv.colour(win, body_rgb, **body_tex)))
    spec = np.where(kind == 3, 0.5, 0.08)
    cv.put(win, z.astype(np.float32), rgb, spec, valid)


# --------------------------------------------------------------------------------------
# Gull-wing parts.
# --------------------------------------------------------------------------------------


def _draw_gullwing(ctx: _Ctx) -> None:
    cv, comp, plan, win = ctx.cv, ctx.comp, ctx.plan, ctx.win
    u, v = ctx.u, ctx.v
    lead = comp.lead
    b2 = lead["width_mm"] / 2
    T = lead["thickness_mm"]
    G = lead["solder_thickness_mm"]
    toe = lead["span_mm"] / 2
    w_h = toe - lead["foot_length_mm"]
    exit_h = lead["exit_height_mm"]
    defect = ctx.state["defect"]

    for j in comp.joints:
        cls = plan["joint_cls"][j.id]
        ex = plan["extra"][j.id]
        axis, sign, q0 = ctx.joint_axes(j)
        w, q = ctx.wq(axis, sign, q0)
        pad = ctx.pad_mask(j)
        extent = ctx.pad_extent(j, axis, sign, q0)
        w_in, w_out, q_lo, q_hi = extent
        if cls in ("component_missing", "lifted_lead"):
            ctx.put_solder(_dome(w, q, extent, ex["dome_mm"]), pad)
        elif cls != "missing":
            F = plan["fillet"][j.id]
            f_toe_nom = G + 0.6 * T
            if cls == "excess":
                f_toe = 0.85 * F
            elif cls == "insufficient":
                f_toe = f_toe_nom * F / max(j.nominal_height_mm, 1e-6)
            else:
                f_toe = min(f_toe_nom, F)
            dqp = max(q_hi - b2, 0.03)
            dqm = max(-b2 - q_lo, 0.03)
            s_q = np.clip(np.where(q >= 0, (q - b2) / dqp, (-b2 - q) / dqm), 0, None)
            s_t = np.clip((w - toe) / max(w_out - toe, 0.04), 0, None)
            s_h = np.clip((w_h - w) / max(w_h - w_in, 0.04), 0, None)
            s = np.sqrt(s_q ** 2 + s_t ** 2 + s_h ** 2)
            frac = np.clip((w - w_h) / max(toe - w_h, 1e-6), 0, 1)
            Fw = F + (f_toe - F) * frac
            z = _fillet(s, 1.0, cls == "excess") * Fw
            z = np.where(pad, np.maximum(z, _SOLDER_COAT), 0.0)
            ctx.put_solder(z, pad)
        if cls == "bridge":
            partner = comp._joint(ex["bridge_to"])
            p_axis, p_sign, p_q0 = ctx.joint_axes(partner)
            dq = p_q0 - q0 if (p_axis, p_sign) == (axis, sign) else 0.0
            wc = (w_h + toe) / 2
            half = ex["bridge_width_mm"] / 2
            hb = ex["bridge_height_mm"]
            qa, qb = min(0.0, dq), max(0.0, dq)
            along = np.clip(np.minimum(q - qa, qb - q) / 0.05 + 1, 0, 1)
            mid = (qa + qb) / 2
            # The web sags a little midway between the leads.
            sag = 1 - 0.15 * np.clip(1 - np.abs(q - mid) / max((qb - qa) / 2, 1e-6), 0, 1)
            ridge = hb * np.clip(1 - ((w - wc) / half) ** 2, 0, None) * along * sag
            ctx.put_solder(ridge, ridge > 0)

    if defect == "component_missing":
        return

    # Mould body with drafted rim, pin-1 dimple and laser marking.
    hl, hw = comp.body_length_mm / 2, comp.body_width_mm / 2
    H = comp.body_height_mm
    inside = (np.abs(u) <= hl) & (np.abs(v) <= hw)
    d = np.minimum(hl - np.abs(u), hw - np.abs(v))
    rim = 0.12
    z = exit_h + (H - exit_h) * np.sqrt(np.clip(d / rim, 0, 1))
    rd = 0.075 * min(2 * hl, 2 * hw)
    dc = (-hl + 2.2 * rd, -hw + 2.2 * rd)
    rho2 = ((u - dc[0]) ** 2 + (v - dc[1]) ** 2) / rd ** 2
    dimple = rho2 < 1
    z = np.where(dimple, z - 0.025 * (1 - rho2), z)
    rgb = cv.colour(win, _MOULD, fine=0.4, med=0.12)
    rgb = np.where(dimple[..., None], cv.colour(win, _MOULD * 1.3, fine=0.08), rgb)
    spec = np.where(dimple, 0.25, 0.06)
    name = {"SOIC-8": "LM358", "SOIC-16": "74HC595", "TSSOP-8": "24C02"}.get(comp.package,
                                                                              "MCU32")
    mark = cv.text_mask(name, comp.to_board([[0.0, 0.12 * hw]])[0] + (ctx.centre - [comp.x_mm,
                        comp.y_mm]), comp.rotation_deg, min(0.16 * 2 * hw, 0.6))
    mark |= cv.text_mask(f"{ctx.rng.integers(10, 99)}{chr(65 + ctx.rng.integers(0, 26))}",
                         comp.to_board([[0.0, -0.35 * hw]])[0] + (ctx.centre - [comp.x_mm,
                         comp.y_mm]), comp.rotation_deg, min(0.12 * 2 * hw, 0.45))
    r0, r1, c0, c1 = win
    mk = (mark[r0:r1, c0:c1].astype(np.float32) / 255.0)[..., None] * (d > rim)[..., None]
    rgb = rgb * (1 - mk) + cv.colour(win, _MOULD_MARK, fine=0.2) * mk
    cv.put(win, z.astype(np.float32), rgb, spec, inside)

    # Leads: shoulder out of the mould, knee, descent, heel and foot.
    tin = cv.colour(win, _TIN, fine=0.15, med=0.05)
    for j in comp.joints:
        ex = plan["extra"][j.id]
        axis, sign, q0 = ctx.joint_axes(j)
        w, q = ctx.wq(axis, sign, q0)
        hb_ = (comp.body_width_mm if axis == 1 else comp.body_length_mm) / 2
        lift = ex.get("lift_mm", 0.0)
        z_foot = G + lift + T
        z_sh = exit_h + T / 2
        sh = min(0.06, 0.3 * max(w_h - hb_, 0.0))
        w1 = hb_ + sh
        span = max(w_h - w1, 1e-3)
        tt = np.clip((w - w1) / span, 0, 1)
        zl = z_foot + (z_sh - z_foot) * 0.5 * (1 + np.cos(np.pi * tt))
        r_toe = T / 2
        over = np.clip(w - (toe - r_toe), 0, r_toe)
        zl = zl - (r_toe - np.sqrt(np.maximum(r_toe ** 2 - over ** 2, 0)))
        zl = _rounded_top(b2 - np.abs(q), zl, 0.04)
        valid = (np.abs(q) <= b2) & (w >= hb_ - 0.01) & (w <= toe)
        cv.put(win, zl.astype(np.float32), tin, 0.5, valid)


# --------------------------------------------------------------------------------------
# Randomised cases (inspection benchmark and tests).
# --------------------------------------------------------------------------------------

#: Seeds for tuning the verdict rules and for the figures reported (kept apart).
TUNING_SEEDS = range(0, 1000)
TEST_SEEDS = range(10000, 11000)


def _classes_for(comp: Component) -> tuple[str, ...]:
    common = ("missing", "insufficient", "excess", "bridge", "component_missing",
              "component_shifted")
    return common + (("lifted_lead",) if comp.kind == "gullwing" else ("tombstone",))


def _draw_severity(cls: str, comp: Component, rng: np.random.Generator) -> dict[str, Any]:
    spec = SEVERITY.get(cls)
    out: dict[str, Any] = {}
    if spec is not None:
        lo, hi = spec["range"]
        out[spec["param"]] = float(rng.uniform(lo, hi))
    if cls == "excess":
        out["style"] = str(rng.choice(["cap", "convex"]))
    if cls == "bridge":
        if comp.kind == "chip":
            out["width_mm"] = float(rng.uniform(0.10, 0.40))
        else:
            out["width_mm"] = float(rng.uniform(0.15, float(comp.lead["foot_length_mm"])))
    if cls == "component_shifted":
        out["rotate_deg"] = float(rng.choice([0.0, 1.0]) * rng.uniform(-8.0, 8.0))
    return out


def _free_direction(board: Board, comp: Component, sev: dict, rng) -> float:
    """+1 or -1: a direction across its pads in which the part, shifted by ``sev``,
    lands on no other part's body or pads (0 when neither does)."""
    from ..inspect._board import polygons_overlap

    lateral, pad_w = _pad_width_across(comp, comp.joints[0])
    w_t = _termination_width(comp, lateral)
    mag = float(sev["overhang_frac"]) * w_t + (pad_w - w_t) / 2
    others = [p for c in board.components if c.ref != comp.ref
              for p in [c.body_polygon_mm()] + [j.polygon_mm for j in c.joints]]
    first = float(rng.choice([-1.0, 1.0]))
    for sign in (first, -first):
        shift = np.zeros(2)
        shift[lateral] = sign * mag
        moved = comp.body_polygon_mm() + _rot(comp.rotation_deg) @ shift
        # The body grown by 0.1 mm: a part pushed against its neighbour is not a case.
        c = moved.mean(axis=0)
        grown = c + (moved - c) * (1 + 0.2 / max(comp.body_width_mm, 0.2))
        if not any(polygons_overlap(grown, o) for o in others):
            return sign
    return 0.0


def random_board_case(board: Board | str | os.PathLike, seed: int, *,
                      defect_probability: float = 0.45,
                      classes: tuple[str, ...] | None = None,
                      pixel_size_mm: float = 0.02) -> dict[str, Any]:
    """Draw one randomised inspection case on ``board`` from ``seed``.

    Every component gets, with ``defect_probability``, one defect class that applies to
    it (``classes`` limits the choice), at a severity drawn over :data:`SEVERITY`'s
    realistic range; joint-level classes go to one joint of the part (a bridge's
    partner stays a good joint). The case also draws the pad finish (ENIG, HASL, OSP),
    whether the board has fiducials, the lighting (specular gain, shininess,
    ambient), the lens (one case in four ordinary, reconstructed with alignment), the
    placement, in one case in four an image that cuts into the board so parts
    stand at or across the field edge, the imaging (depth of field, in-focus blur,
    sensor noise, flicker and stage wobble) and the chip fillets' profile.

    Returns
    -------
    dict
        ``board`` (the Board, without fiducials when so drawn; inspect against this
        one), ``defects`` and ``params`` (for :func:`board_scene`), ``finish``,
        ``fiducials`` (bool), ``lighting`` (keyword arguments of
        :class:`~smdinspect.synth.Lighting`), ``lens`` ("telecentric" or "ordinary"),
        ``offset_mm``, ``rotate_deg``, ``shape`` (H, W), ``edge`` (bool), ``seed``,
        ``pixel_size_mm``, ``imaging`` (pupil scale, in-focus blur and sensor; render
        with :func:`case_imaging`), ``fillet_curvature`` (chip fillets as circular arcs
        with curvatures in that range, in three cases in four; None: the parabola). Use
        :func:`board_scene` with ``**scene_kwargs(case)``.
    """
    import dataclasses

    if not isinstance(board, Board):
        board = load_board(board)
    p = _positive(pixel_size_mm, "pixel_size_mm")
    rng = np.random.default_rng([int(seed), 0xCA5E])
    defects: dict[str, str] = {}
    params: dict[str, dict[str, Any]] = {}
    taken: set[str] = set()
    for comp in board.components:
        if rng.random() >= defect_probability:
            continue
        options = [c for c in _classes_for(comp) if classes is None or c in classes]
        if not options:
            continue
        cls = str(rng.choice(options))
        free = [j for j in comp.joints if j.id not in taken]
        if not free:
            continue
        j = free[int(rng.integers(0, len(free)))]
        if cls == "bridge":
            partner = _bridge_partner(comp, j)
            if partner in taken or partner in defects:
                continue
            taken.add(partner)
        defects[j.id] = cls
        taken.add(j.id)
        if cls in _COMPONENT_LEVEL:
            taken.update(jj.id for jj in comp.joints)
        sev = _draw_severity(cls, comp, rng)
        if cls == "component_shifted":
            sev["direction"] = _free_direction(board, comp, sev, rng)
            if sev["direction"] == 0:      # it would land on a neighbour either way
                del defects[j.id]
                continue
        if sev:
            params[j.id] = sev
    finish = str(rng.choice(list(FINISHES)))
    fiducials = bool(rng.random() < 0.5)
    if not fiducials:
        board = dataclasses.replace(board, fiducials=())
    lighting = {"specular_gain": float(rng.uniform(1.0, 3.0)),
                "shininess": float(rng.uniform(15.0, 60.0)),
                "ambient": float(rng.uniform(0.1, 0.3))}
    lens = "ordinary" if rng.random() < 0.25 else "telecentric"
    rot = float(rng.uniform(-MAX_ROTATE_DEG, MAX_ROTATE_DEG))
    off = np.array(rng.uniform(-MAX_OFFSET_MM, MAX_OFFSET_MM, 2))
    shape = board_shape(board, pixel_size_mm=p, offset_mm=tuple(off), rotate_deg=rot)
    edge = bool(rng.random() < 0.25)
    if edge:
        # Cut into the parts' extent on one side by 0.1–0.6 mm.
        H, W = shape
        side = int(rng.integers(0, 4))          # 0 right, 1 left, 2 top, 3 bottom
        depth = float(rng.uniform(0.1, 0.6))
        axis = 0 if side < 2 else 1
        off[axis] = float(rng.uniform(-0.5, 0.5))
        a = math.radians(rot)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        bw, bh = board.size_mm
        pts = np.vstack([np.vstack([c.body_polygon_mm()] + [j.polygon_mm for j in c.joints])
                         for c in board.components])
        rel = (pts - [bw / 2, bh / 2]) @ R.T          # world, relative to the board centre
        size = (W - 1) * p if axis == 0 else (H - 1) * p
        centre = size / 2 + off[axis]                 # board centre in the old image
        sgn = 1.0 if side in (0, 2) else -1.0
        reach = float((sgn * rel[:, axis]).max())
        other = float((-sgn * rel[:, axis]).max())
        # Keep [a, b] of the old image: cut `depth` into the parts on one side, keep
        # 1 mm beyond them on the other (the board centre stays near the image centre,
        # inside the registration's search).
        if sgn > 0:
            a, b = max(0.0, centre - other - 1.0), centre + reach - depth
        else:
            a, b = centre - reach + depth, min(size, centre + other + 1.0)
        new_n = max(int((b - a) / p) + 1, 64)
        new_size = (new_n - 1) * p
        off[axis] = (centre - a) - new_size / 2
        if axis == 0:
            shape = (H, new_n)
        else:
            shape = (new_n, W)
            off[1] = off[1]
    # The imaging, drawn last (the cases' parts, defects and placements do not depend on
    # it): a pupil 0.35–1.4 times the default cone (at 20 µm/px a depth of field of
    # 0.06–0.23 mm, so a focus peak spans ~1.5–5 frames of the benchmarks' 0.05 mm
    # step), in-focus blur, and a sensor from a bright, quiet one to small pixels in
    # poor light.
    imaging = {"aperture_scale": float(np.exp(rng.uniform(math.log(0.35), math.log(1.4)))),
               "sigma0_px": float(rng.uniform(0.2, 0.8)),
               "sensor": {"full_well_e": float(np.exp(rng.uniform(math.log(4e3),
                                                                  math.log(3e4)))),
                          "read_noise_e": float(rng.uniform(3.0, 12.0)),
                          "exposure": float(rng.uniform(0.55, 0.9)),
                          "flicker": float(rng.uniform(0.0, 0.03)),
                          "jitter_px": float(rng.uniform(0.0, 0.15))}}
    # The chip fillets' profile, from its own stream (every draw above stays as it was):
    # in three cases in four constant-curvature menisci, what surface tension makes
    # (arc_fillet), each joint's curvature drawn between a shallow arc and the most
    # curved one; else the parabola F·(1 − s)².
    arc_rng = np.random.default_rng([int(seed), 0xF111E7])
    fillet_curvature = ((float(arc_rng.uniform(0.3, 0.8)), 1.0)
                        if arc_rng.random() < 0.75 else None)
    return {"board": board, "defects": defects, "params": params, "finish": finish,
            "fiducials": fiducials, "lighting": lighting, "lens": lens,
            "offset_mm": (float(off[0]), float(off[1])), "rotate_deg": rot,
            "shape": tuple(int(x) for x in shape), "edge": edge, "seed": int(seed),
            "pixel_size_mm": p, "imaging": imaging, "fillet_curvature": fillet_curvature}


def case_imaging(case: Mapping[str, Any]):
    """(:class:`~smdinspect.optics.Optics`, :class:`~smdinspect.synth.SensorConfig`) of a
    :func:`random_board_case`: its lens, pixel size, pupil, in-focus blur and sensor."""
    import dataclasses

    from ..optics import Optics
    from ._render import SensorConfig

    im = case["imaging"]
    base = Optics.for_pixel_size(case["pixel_size_mm"], telecentric=case["lens"] == "telecentric")
    optics = dataclasses.replace(base, aperture_mm=base.aperture_mm * im["aperture_scale"],
                                 sigma0_px=im["sigma0_px"])
    return optics, SensorConfig(**im["sensor"])


def case_gather_stack(case: Mapping[str, Any], scene, z_mm, out, *, optics=None,
                      sensor=None):
    """Photograph a :func:`random_board_case`'s scene with the independent gather model
    (:func:`~smdinspect.synth._suite.gather_board_stack`) at ``z_mm`` into ``out``: the
    case's optics and sensor (:func:`case_imaging`, or those given), vignetting 0–0.3
    and a Gaussian or disc PSF drawn from a stream of the case's own (the draws of our
    own renderer's cases are unchanged). Returns the opened stack."""
    from ._render import SensorConfig
    from ._suite import GatherNoise, gather_board_stack

    if optics is None:
        optics, sensor = case_imaging(case)
    sensor = sensor or SensorConfig()
    rng = np.random.default_rng([int(case["seed"]), 0x6A7])
    noise = GatherNoise(photons_full_scale=sensor.full_well_e,
                        read_noise=sensor.read_noise_e / sensor.full_well_e,
                        exposure=sensor.exposure, flicker=sensor.flicker,
                        vignetting=float(rng.uniform(0.0, 0.3)), bit_depth=sensor.bit_depth)
    return gather_board_stack(scene, z_mm, out, optics=optics, noise=noise,
                              seed=int(case["seed"]), psf=("gauss", "disc")[int(rng.integers(2))])


def scene_kwargs(case: Mapping[str, Any]) -> dict[str, Any]:
    """Keyword arguments of :func:`board_scene` for a :func:`random_board_case`."""
    return {k: case[k] for k in ("defects", "params", "finish", "offset_mm", "rotate_deg",
                                 "shape", "seed", "pixel_size_mm", "fillet_curvature")}
