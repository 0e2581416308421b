"""Reports of an inspection: report.json, joints.csv, junit.xml and report.html.

Every file is written atomically. ``report.html`` is self-contained: its pictures are
inline SVG over base64 PNGs (drawn by :mod:`._report_figures`: the overview with every
joint's id, colour bars, crops with scale bars, height profiles against the acceptance
band; the 3D view as a JPEG) and the table sorts with a few lines of inline JavaScript.
A board that was not located gets a ``report.html`` too (:func:`not_located_html`).

``report.json`` schema (version 1)::

    {
      "schema": "smdinspect-report", "version": 1,
      "created": "2025-01-01T12:00:00+00:00", "smdinspect_version": "0.1.0",
      "status": "inspected",                      # or "not_located"
      "passed": true, "exit_code": 0,             # 0 no defect, 1 defects, 3 not located
      "board": {"name": "demo_board", "source": "references/demo_board.json",
                "size_mm": [9.5, 9.5]},
      "measurement": {"shape": [H, W], "pixel_size_mm": 0.02, "coverage": 0.93,
                      "step_mm": 0.05, "source": "stacks/b1",
                      "calibration": null},       # or {"z_scale": {...}, "focal_plane": {...}}
      "registration": {"method": "coarse+features", "converged": true, "reason": "",
                       "transform": [[c, -s, tx], [s, c, ty], [0, 0, 1]],   # WORLD = T·BOARD
                       "rotation_deg": 2.5, "translation_mm": [tx, ty],
                       "offset_mm": [dx, dy],      # board centre − image centre
                       "score": 0.97, "fitness": 0.99, "rmse_mm": 0.012},
      "plane": {"a": ..., "b": ..., "c_mm": ..., "tilt_deg": ..., "inlier_fraction": ...,
                "rmse_mm": ..., "n_inliers": ...},
      "summary": {"joints": 18, "defects": 2, "unreliable": 1,
                  "by_verdict": {"ok": 15, "missing": 0, ...}},
      "config": {...every InspectConfig field...},
      "components": [{"ref", "kind", "package", "verdict", "reason", "present_fraction",
                      "body_height_mm", "offset_mm": [dx, dy], "tilt_deg",
                      "reliable_fraction"}, ...],
      "joints": [{"id": "R1.1", "component": "R1", "pad_number": "1",
                  "termination": "chip_end",
                  "position_mm": {"x", "y"},        # pad centre, BOARD frame
                  "world_mm": {"x", "y"},           # where it was found, WORLD frame
                  "measured": {"max_height_mm", "mean_height_mm", "uncertainty_mm",
                               "mean_uncertainty_mm", "volume_mm3",
                               "volume_uncertainty_mm3", "area_mm2",
                               "area_uncertainty_mm2", "reliable_fraction", "n_pixels",
                               "max_method", "lead_height_mm", "foot_height_mm",
                               "side_height_mm", "cap_excess_mm", "fillet_reach",
                               "gap_height_mm", "bare_fraction"},
                  "expected": {"nominal_height_mm", "min_height_mm", "max_height_mm"},
                  "verdict": "ok", "reason": "..."}, ...]
    }

Numbers that could not be measured are ``null``.
"""

from __future__ import annotations

import csv
import datetime as _dt
import io
import logging
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import numpy as np

from .. import __version__, _atomic
from ._config import Verdict
from ._report_figures import (
    PadMark,
    colour_bar_svg,
    colourise,
    crop_svg,
    esc,
    height_range,
    jpeg_data_uri,
    joint_profile,
    overview_svg,
    profile_svg,
    resize,
    rgb_css,
)
from ._result import InspectionResult

__all__ = ["REPORT_FILES", "report_dict", "write_reports"]

log = logging.getLogger(__name__)

REPORT_SCHEMA = "smdinspect-report"
REPORT_VERSION = 1
REPORT_FILES = ("report.json", "joints.csv", "junit.xml", "report.html")

#: RGB colour of each verdict in the pictures and the table.
COLOURS = {
    "ok": (46, 160, 67),
    "unreliable": (150, 150, 150),
    "missing": (220, 38, 38),
    "insufficient": (245, 130, 32),
    "excess": (160, 60, 200),
    "bridge": (230, 0, 120),
    "lifted_lead": (0, 150, 220),
    "tombstone": (200, 160, 0),
    "component_missing": (120, 40, 20),
    "component_shifted": (240, 200, 40),
}

CSV_COLUMNS = (
    "id", "component", "pad_number", "termination", "x_mm", "y_mm", "world_x_mm",
    "world_y_mm", "measured_max_mm", "measured_mean_mm", "uncertainty_mm", "volume_mm3",
    "volume_uncertainty_mm3", "area_mm2", "area_uncertainty_mm2", "reliable_fraction",
    "lead_height_mm", "gap_height_mm", "expected_nominal_mm", "expected_min_mm",
    "expected_max_mm", "verdict", "reason",
)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def report_dict(result: InspectionResult, *, source: str | None = None) -> dict[str, Any]:
    """The ``report.json`` document of ``result`` (see the module docstring)."""
    counts = result.counts()
    board_size = result.meta.get("board_size_mm")
    return {
        "schema": REPORT_SCHEMA,
        "version": REPORT_VERSION,
        "created": _now(),
        "smdinspect_version": __version__,
        "status": "inspected",
        "passed": result.passed,
        "exit_code": result.exit_code,
        "board": {"name": result.board, "source": result.board_source,
                  "size_mm": list(board_size) if board_size else None},
        "measurement": {"shape": list(result.shape), "pixel_size_mm": result.pixel_size_mm,
                        "coverage": round(result.coverage, 4),
                        "step_mm": _num(result.meta.get("step_mm")), "source": source,
                        "calibration": result.meta.get("calibration"),
                        "beyond_sweep": result.meta.get("beyond_sweep")},
        "registration": result.registration.to_dict(),
        "plane": {k: (round(v, 6) if isinstance(v, float) else v)
                  for k, v in result.plane.to_dict().items()},
        "summary": {"joints": len(result.joints), "defects": len(result.defects),
                    "unreliable": counts["unreliable"], "by_verdict": counts},
        "config": result.config.to_dict(),
        "components": [c.to_dict() for c in result.components],
        "joints": [j.to_dict() for j in result.joints],
    }


def _calibration_text(calibration: dict[str, Any] | None) -> str:
    """The ``report.html`` line for the rig calibration applied (``--calibration``)."""
    parts = []
    fp = (calibration or {}).get("focal_plane")
    if fp is not None:
        tilt = fp.get("tilt_deg")
        tilt = f"tilt {tilt:.3f}°, " if isinstance(tilt, (int, float)) else ""
        parts.append(f"focal plane corrected ({tilt}sag "
                     f"{1000 * float(fp.get('curvature_sag_mm') or 0.0):.1f} µm)")
    zs = (calibration or {}).get("z_scale")
    if zs is not None:
        parts.append(f"z scaled × {float(zs.get('scale', 1.0)):.4f}")
    return "; ".join(parts) or "none"


def _beyond_text(beyond: dict[str, Any] | None) -> str:
    """The ``report.html`` measurement line's note on the field beyond the sweep's ends
    (``summary.json`` → ``beyond_sweep``), from the share the reconstruction warns at."""
    from ..sff._reconstruct import BEYOND_SWEEP_ENDS, BEYOND_SWEEP_WARN

    notes = [f"{100 * share:.0f} % of the field is sharpest on its {end} frame, beyond the sweep"
             for key, end, _ in BEYOND_SWEEP_ENDS
             if (share := float((beyond or {}).get(key) or 0.0)) >= BEYOND_SWEEP_WARN]
    return ("; " + "; ".join(notes) + " (not measured: extend the sweep)") if notes else ""


def not_located_dict(board, registration, *, reason: str, source: str | None = None,
                     shape=None, pixel_size_mm=None) -> dict[str, Any]:
    """A ``report.json`` for a board that could not be located (exit code 3)."""
    return {
        "schema": REPORT_SCHEMA, "version": REPORT_VERSION, "created": _now(),
        "smdinspect_version": __version__, "status": "not_located", "passed": False,
        "exit_code": 3, "reason": reason,
        "board": {"name": board.name, "source": str(getattr(board, "source", "")),
                  "size_mm": list(board.size_mm)},
        "measurement": {"shape": list(shape) if shape else None,
                        "pixel_size_mm": pixel_size_mm, "source": source},
        "registration": registration.to_dict() if registration is not None else None,
        "joints": [],
    }


def _num(v):
    if v is None:
        return None
    v = float(v)
    return round(v, 6) if math.isfinite(v) else None


# --------------------------------------------------------------------------------------
# CSV and JUnit.
# --------------------------------------------------------------------------------------


def joints_csv(result: InspectionResult) -> str:
    """``joints.csv``: one row per joint, columns :data:`CSV_COLUMNS` (mm, mm², mm³)."""
    from ._spc_report import safe_cell

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for j in result.joints:
        row = []
        for col in CSV_COLUMNS:
            v = getattr(j, col)
            if isinstance(v, Verdict):
                v = v.value
            elif isinstance(v, float):
                v = "" if not math.isfinite(v) else f"{v:.6g}"
            else:
                v = safe_cell(v)  # ids and reasons come from board files: no formulas
            row.append(v)
        w.writerow(row)
    return buf.getvalue()


def junit_xml(result: InspectionResult) -> str:
    """``junit.xml``: one test case per joint; a defect is a failure, unreliable is skipped."""
    suite = ET.Element("testsuite", {
        "name": f"smdinspect.{result.board}",
        "tests": str(len(result.joints)),
        "failures": str(len(result.defects)),
        "errors": "0",
        "skipped": str(len(result.unreliable)),
        "time": f"{float(result.meta.get('seconds', 0.0)):.3f}",
        "timestamp": _now(),
    })
    props = ET.SubElement(suite, "properties")
    reg = result.registration
    for k, v in (("board_source", result.board_source), ("registration_method", reg.method),
                 ("rotation_deg", f"{reg.rotation_deg:.4f}"), ("fitness", f"{reg.fitness:.4f}"),
                 ("rmse_mm", f"{reg.rmse_mm:.5f}")):
        ET.SubElement(props, "property", {"name": k, "value": str(v)})
    for j in result.joints:
        case = ET.SubElement(suite, "testcase", {
            "classname": f"{result.board}.{j.component}", "name": j.id, "time": "0"})
        if j.is_defect:
            f = ET.SubElement(case, "failure", {"type": j.verdict.value,
                                                "message": f"{j.verdict.value}: {j.reason}"})
            f.text = _joint_text(j)
        elif j.verdict is Verdict.UNRELIABLE:
            ET.SubElement(case, "skipped", {"message": f"unreliable: {j.reason}"})
        else:
            out = ET.SubElement(case, "system-out")
            out.text = _joint_text(j)
    suites = ET.Element("testsuites", {"name": "smdinspect", "tests": suite.get("tests"),
                                       "failures": suite.get("failures"),
                                       "skipped": suite.get("skipped"), "errors": "0"})
    suites.append(suite)
    ET.indent(suites)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(suites, encoding="unicode") + "\n"


def _joint_text(j) -> str:
    return (f"max height {_fmt(j.measured_max_mm)} mm ± {_fmt(j.uncertainty_mm)} "
            f"(band {j.expected_min_mm:.3f}..{j.expected_max_mm:.3f}, nominal "
            f"{j.expected_nominal_mm:.3f}); mean {_fmt(j.measured_mean_mm)} mm; volume "
            f"{_fmt(j.volume_mm3, 5)} mm3; area {_fmt(j.area_mm2, 4)} mm2; reliable "
            f"{j.reliable_fraction:.0%}")


def _fmt(v: float, nd: int = 3) -> str:
    return f"{v:.{nd}f}" if math.isfinite(v) else "n/a"


# --------------------------------------------------------------------------------------
# HTML.
# --------------------------------------------------------------------------------------

#: Display size of the board overview (longest side, CSS px) and of the side pictures.
OVERVIEW_PX = 760  # with the side column (height map, 3D view) on a 1366 px screen
SIDE_PX = 440
#: Margin around a joint in its crop (mm) and the profile's reach beyond the pad.
CROP_MARGIN_MM = 0.15
PROFILE_MARGIN_MM = 0.3


def _colour(verdict: str) -> tuple[int, int, int]:
    return COLOURS.get(verdict, (150, 150, 150))


def _aif_rgb(surface) -> np.ndarray:
    img = np.asarray(surface.aif)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(np.round(img.astype(np.float32) * 255), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img[:, :, :3]


@dataclass(frozen=True)
class _JointView:
    """Where a joint lies in the image and the line its height profile follows."""

    centre: np.ndarray  # (col, row) px
    axis: np.ndarray  # unit vector along the profile (A → B), px
    start: np.ndarray  # A, (col, row) px
    end: np.ndarray  # B
    pad_s_mm: tuple[float, float]  # the pad's extent along the profile, from A
    along_fillet: bool  # False: across the pad, through the gaps to its neighbours
    box: tuple[int, int, int, int]  # crop (c0, r0, c1, r1), end exclusive
    local: np.ndarray  # (H, W) bool mask of the crop: the joint's own pixels


def _principal_axes(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = poly - poly.mean(axis=0)
    if len(poly) == 4:  # a rectangle (or close): its edges are the axes
        e = poly[1] - poly[0]
    else:
        w, v = np.linalg.eigh(q.T @ q)
        e = v[:, int(np.argmax(w))]
    e = e / max(float(np.hypot(*e)), 1e-12)
    return e, np.array([-e[1], e[0]])


def _joint_views(result: InspectionResult) -> dict[str, _JointView]:
    """Profile line and crop of every joint with an outline (see :class:`_JointView`).

    The profile runs along the pad axis that points away from the component's centre
    (from the body to the toe: the way a fillet falls off), through the pad centre and
    ``PROFILE_MARGIN_MM`` (or half the pad) beyond both ends. A bridge's profile runs
    across the pad instead, through the gaps, to the neighbouring pads' centres.
    """
    p = result.pixel_size_mm
    H, W = result.shape
    polys = {j.id: np.asarray(j.polygon_px, np.float64) for j in result.joints
             if j.polygon_px is not None and len(j.polygon_px) >= 3}
    centres = {k: v.mean(axis=0) for k, v in polys.items()}
    by_comp: dict[str, list[np.ndarray]] = {}
    for j in result.joints:
        if j.id in centres:
            by_comp.setdefault(j.component, []).append(centres[j.id])
    views = {}
    for j in result.joints:
        if j.id not in polys:
            continue
        poly, c = polys[j.id], centres[j.id]
        e1, e2 = _principal_axes(poly)
        sib = by_comp[j.component]
        out = c - np.mean(sib, axis=0) if len(sib) > 1 else np.zeros(2)
        if float(np.hypot(*out)) > 1e-6:
            axis = e1 if abs(out @ e1) >= abs(out @ e2) else e2
            axis = axis if out @ axis >= 0 else -axis
        else:  # one pad: its longer axis, pointing right / down
            ext1, ext2 = np.ptp((poly - c) @ e1), np.ptp((poly - c) @ e2)
            axis = e1 if ext1 >= ext2 else e2
            axis = axis if axis[0] + 1e-9 * axis[1] >= 0 else -axis
        along_fillet = j.verdict is not Verdict.BRIDGE
        if not along_fillet:
            axis = np.array([-axis[1], axis[0]])
        a = (poly - c) @ axis
        a0, a1 = float(a.min()), float(a.max())
        if along_fillet:
            m = max(PROFILE_MARGIN_MM / p, 0.5 * (a1 - a0))
            s_a, s_b = a0 - m, a1 + m
        else:
            others = [v for k, v in centres.items() if k != j.id]
            d_nn = min((float(np.hypot(*(v - c))) for v in others), default=0.0)
            half = max(a1 - a0, 0.0) / 2
            reach = min(max(half + PROFILE_MARGIN_MM / p, d_nn), half + 2.0 / p)
            s_a, s_b = -reach, reach
        start, end = c + s_a * axis, c + s_b * axis
        pts = np.vstack([poly, start, end])
        lo_pt, hi_pt = pts.min(axis=0) - CROP_MARGIN_MM / p, pts.max(axis=0) + CROP_MARGIN_MM / p
        # Widen the short side to 3/4 of the long one: a thin strip shows too little around.
        grow = np.maximum(0.75 * np.max(hi_pt - lo_pt) - (hi_pt - lo_pt), 0.0) / 2
        lo_pt, hi_pt = lo_pt - grow, hi_pt + grow
        c0, r0 = np.floor(lo_pt).astype(int)
        c1, r1 = np.ceil(hi_pt).astype(int) + 1
        c0, r0, c1, r1 = max(int(c0), 0), max(int(r0), 0), min(int(c1), W), min(int(r1), H)
        if c1 - c0 < 2 or r1 - r0 < 2:
            continue
        cc, rr = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
        rel = np.stack([cc - c[0], rr - c[1]], axis=-1)
        pa, pb = rel @ axis, rel @ np.array([-axis[1], axis[0]])
        b = (poly - c) @ np.array([-axis[1], axis[0]])
        e = 0.1 / p
        if along_fillet:  # the pad and a little around it
            local = (pa >= a0 - e) & (pa <= a1 + e) & (pb >= b.min() - e) & (pb <= b.max() + e)
        else:  # the profile's strip through the middle of the pad and the gaps
            mid, quarter = 0.5 * (b.min() + b.max()), 0.25 * (b.max() - b.min())
            local = (pa >= s_a) & (pa <= s_b) & (np.abs(pb - mid) <= quarter)
        views[j.id] = _JointView(
            centre=c, axis=axis, start=start, end=end,
            pad_s_mm=((a0 - s_a) * p, (a1 - s_a) * p), along_fillet=along_fillet,
            box=(c0, r0, c1, r1), local=local)
    return views


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.2em;color:#222}
h1{font-size:1.5em;margin:0 0 .2em}h2{font-size:1.15em;margin:1.4em 0 .5em}
h3{font-size:1em;margin:0 0 .3em}
.pass{color:#2e7d32;font-weight:bold}.fail{color:#c62828;font-weight:bold}
.figs{display:flex;flex-wrap:wrap;gap:18px;align-items:flex-start}.figs figure{margin:0}
figure svg,figure img{max-width:100%;height:auto}
figcaption{font-size:.85em;color:#555;max-width:820px}
.side{display:flex;flex-direction:column;gap:14px;max-width:520px}
.withbar{display:flex;align-items:flex-start;gap:4px}
table{border-collapse:collapse;font-size:.85em}th,td{border:1px solid #ddd;padding:2px 6px;text-align:right}
th{background:#f3f3f3}table.sortable th{cursor:pointer;user-select:none}td.l,th.l{text-align:left}
tr:target{outline:2px solid #1565c0}
.chip{display:inline-block;width:.8em;height:.8em;border-radius:2px;margin-right:4px;vertical-align:middle}
.look a{margin-right:.2em}.look li{margin:.15em 0}
.card{border:1px solid #ddd;border-left-width:8px;padding:8px 10px;margin:0 0 14px;max-width:1100px}
.card:target{box-shadow:0 0 0 3px #90caf9}
.card .reason{margin:.1em 0 .3em;font-weight:600}.card .nums{margin:0 0 .5em;font-size:.85em;color:#444}
.panels{display:flex;flex-wrap:wrap;gap:14px;align-items:flex-start}
.cap{font-size:.8em;color:#555;margin:.4em 0 0;max-width:1000px}
.kv td{text-align:left}
.why{font-size:1.1em;background:#fdecea;border-left:6px solid #c62828;padding:8px 12px;max-width:1000px}
svg text{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif}
svg .jl text{font-size:11px;font-weight:bold}
svg .tick{font-size:10px;fill:#333}svg .cbl,svg .axl{font-size:10.5px;fill:#333}
svg .note{font-size:10px;paint-order:stroke;stroke:#fff;stroke-width:3px}svg .panel{font-size:11.5px;font-weight:bold;fill:#222}
svg .end{font-size:9px;font-weight:bold;fill:#000}svg .sb{font-size:10px;fill:#fff;font-weight:bold}
"""

_JS = """
document.querySelectorAll('table.sortable th').forEach(function(th, i){
  th.addEventListener('click', function(){
    var tb = th.closest('table').tBodies[0], rows = Array.from(tb.rows);
    var asc = th.dataset.dir !== 'asc'; th.dataset.dir = asc ? 'asc' : 'desc';
    rows.sort(function(a, b){
      var x = a.cells[i].dataset.v !== undefined ? a.cells[i].dataset.v : a.cells[i].textContent;
      var y = b.cells[i].dataset.v !== undefined ? b.cells[i].dataset.v : b.cells[i].textContent;
      var nx = parseFloat(x), ny = parseFloat(y);
      var c = (!isNaN(nx) && !isNaN(ny)) ? nx - ny : String(x).localeCompare(String(y));
      return asc ? c : -c;
    });
    rows.forEach(function(r){ tb.appendChild(r); });
  });
});
"""


def _page_head(title: str) -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>")


def _chip(verdict: str) -> str:
    return f"<span class='chip' style='background:{rgb_css(_colour(verdict))}'></span>"


def _height_figure(height: np.ndarray, reliable: np.ndarray, scale: float, marks, *,
                   caption: str, aria: str, joints=None) -> str:
    """The height map figure. With ``joints`` the colours stop at the highest nominal
    joint height when the map's robust range goes beyond it: a 0.1-0.3 mm fillet is not
    one dark colour next to a 1.5 mm body, which is clipped to the top colour."""
    lo, hi = height_range(height[reliable & np.isfinite(height)])
    note = "0.5–99.8 percentile of the reliable pixels; beyond it clipped"
    nominal = [j.expected_nominal_mm for j in joints or () if np.isfinite(j.expected_nominal_mm)]
    if nominal and lo < max(nominal) < hi:
        hi = max(nominal)
        note = ("from the 0.5 percentile of the reliable pixels to the highest nominal joint "
                "height, so the fillets take the scale; taller parts clipped")
    pic = resize(colourise(height, reliable, lo, hi), scale)
    svg = overview_svg(pic, marks, labels=False, css_class="heightmap", aria=aria)
    bar = colour_bar_svg(lo, hi, height_px=pic.shape[0], uid="cb-board")
    return (f"<figure><div class='withbar'>{svg}{bar}</div><figcaption>{caption} "
            f"Colour scale {lo:.3f} … {hi:.3f} mm ({note}); unreliable pixels dimmed."
            "</figcaption></figure>")


def _view3d_figure(view3d: np.ndarray | None, note: str) -> str:
    if view3d is None:
        return f"<figure><figcaption>3D view not available: {esc(note)}</figcaption></figure>"
    s = min(1.0, 900 / max(view3d.shape[:2]))
    img = resize(view3d, s)
    w = min(SIDE_PX + 74, img.shape[1])  # as wide as the height map with its colour bar
    return (f"<figure><img class='view3d' alt='3D view of the measured surface' width='{w}' "
            f"src='{jpeg_data_uri(img)}'><figcaption>3D view of the reconstructed surface "
            "(textured with the all-in-focus image; the vertical exaggeration is written on "
            "it; faded: filled in, not measured).</figcaption></figure>")


def _overview_marks(result: InspectionResult, scale: float, href) -> list[PadMark]:
    views = _joint_views(result)
    marks = []
    # Defects first, then unreliable, then ok: the first placed label gets the best spot.
    rank = {True: 0, False: 2}
    order = sorted(range(len(result.joints)), key=lambda k: (
        1 if result.joints[k].verdict is Verdict.UNRELIABLE else rank[result.joints[k].is_defect], k))
    for k in order:
        j = result.joints[k]
        if j.polygon_px is None or len(j.polygon_px) < 3:
            continue
        poly = (np.asarray(j.polygon_px, np.float64) + 0.5) * scale
        v = views.get(j.id)
        out = (0.0, -1.0)
        if v is not None:
            ax = v.axis if v.along_fillet else np.array([v.axis[1], -v.axis[0]])
            out = (float(ax[0]), float(ax[1]))
        marks.append(PadMark(polygon=poly, label=j.id, colour=_colour(j.verdict.value),
                             href=href(k), tooltip=f"{j.id}: {j.verdict.value} — {j.reason}",
                             outward=out))
    return marks


def _joint_card(k: int, j, view: _JointView | None, result: InspectionResult,
                aif: np.ndarray, reliable: np.ndarray) -> str:
    col = _colour(j.verdict.value)
    p = result.pixel_size_mm
    nums = [f"max height {_fmt(j.measured_max_mm)} ± {_fmt(j.uncertainty_mm)} mm",
            f"band {j.expected_min_mm:.3f}–{j.expected_max_mm:.3f} mm (nominal "
            f"{j.expected_nominal_mm:.3f})",
            f"mean {_fmt(j.measured_mean_mm)} mm", f"volume {_fmt(j.volume_mm3, 4)} mm³",
            f"area {_fmt(j.area_mm2, 3)} mm²", f"reliable {j.reliable_fraction:.0%}"]
    if math.isfinite(j.gap_height_mm):
        nums.append(f"gap height {j.gap_height_mm:.3f} mm")
    if math.isfinite(j.lead_height_mm):
        nums.append(f"lead height {j.lead_height_mm:.3f} mm")
    parts = [f"<div class='card' id='joint-{k}' data-joint='{esc(j.id)}' "
             f"style='border-left-color:{rgb_css(col)}'>",
             f"<h3>{_chip(j.verdict.value)}{esc(j.id)} — {esc(j.verdict.value)} "
             f"<small>({esc(j.component)}, pad {esc(j.pad_number)}, {esc(j.termination)}; "
             f"<a href='#row-{k}'>table row</a>)</small></h3>",
             f"<p class='reason'>{esc(j.reason)}</p>",
             f"<p class='nums'>{esc('; '.join(nums))}</p>"]
    if view is None or result.height_above_mm is None:
        parts.append("<p class='cap'>No picture: the joint's pad lies outside the image.</p></div>")
        return "".join(parts)
    height = result.height_above_mm
    c0, r0, c1, r1 = view.box
    sub_h, sub_rel = height[r0:r1, c0:c1], reliable[r0:r1, c0:c1]
    vals = sub_h[view.local & sub_rel & np.isfinite(sub_h)]
    lo, hi = height_range(vals, lo_pct=1.0, hi_pct=99.0, min_span_mm=0.05)
    lo = min(lo, 0.0)
    # Up to 1.5 x the top of the band (or of the measured max): a body edge inside the
    # pad saturates instead of taking the colours from the fillet.
    top = max(j.expected_max_mm, j.measured_max_mm if math.isfinite(j.measured_max_mm) else 0.0)
    hi = max(min(hi, 1.5 * top), j.expected_max_mm)
    hpic = colourise(height, reliable, lo, hi)  # only the crop is shown
    line = (view.start, view.end)
    poly = np.asarray(j.polygon_px, np.float64)
    ends = ("A", "B")
    img_svg = crop_svg(aif, view.box, polygon_px=poly, line_px=line, pixel_size_mm=p,
                       title="image", outline=col, ends=ends)
    h_svg = crop_svg(hpic, view.box, polygon_px=poly, line_px=line, pixel_size_mm=p,
                     title="height", outline=(255, 255, 255), ends=ends)
    crop_h = int(img_svg.split("height='", 1)[1].split("'", 1)[0])
    bar = colour_bar_svg(lo, hi, height_px=crop_h, band=(j.expected_min_mm, j.expected_max_mm),
                         uid=f"cb-{k}")
    s_mm, z_mm = joint_profile(height, reliable, view.start, view.end, pixel_size_mm=p)
    extra = [("gap", j.gap_height_mm)] if not view.along_fillet else []
    prof = profile_svg(s_mm, z_mm, pad_mm=view.pad_s_mm,
                       band_mm=(j.expected_min_mm, j.expected_max_mm),
                       nominal_mm=j.expected_nominal_mm, measured_mm=j.measured_max_mm,
                       uncertainty_mm=j.uncertainty_mm, colour=col, uid=f"clip-{k}", ends=ends,
                       extra_marks=extra)
    how = ("from the component body (A) over the pad to its toe (B)" if view.along_fillet else
           "across the pad (A → B), through the gaps to the neighbouring pads")
    parts.append(f"<div class='panels'>{img_svg}<div class='withbar'>{h_svg}{bar}</div>{prof}</div>")
    parts.append(f"<p class='cap'>Height colours: this joint's own range, {lo:.3f} … {hi:.3f} mm. "
                 f"Profile {how}.</p></div>")
    return "".join(parts)


def report_html(result: InspectionResult, *, source: str | None = None,
                max_side: int = OVERVIEW_PX, view3d: np.ndarray | None = None,
                view3d_note: str = "no 3D view was rendered") -> str:
    """The self-contained ``report.html`` document of an inspected board.

    Parameters
    ----------
    result : InspectionResult
    source : str, optional
        What the measurement came from (shown in the header).
    max_side : int
        Longest side of the board overview, in CSS pixels.
    view3d : (H, W, 3) uint8, optional
        The 3D view (RGB) to show, e.g. the reconstruction's ``view3d.png``.
    view3d_note : str
        Said instead when ``view3d`` is None.
    """
    surface = result.surface
    reg = result.registration
    counts = result.counts()
    status = "<span class='pass'>PASS</span>" if result.passed else "<span class='fail'>FAIL</span>"
    look = [k for k, j in enumerate(result.joints) if j.is_defect] + \
        [k for k, j in enumerate(result.joints) if j.verdict is Verdict.UNRELIABLE]
    has_card = set(look)

    def href(k: int) -> str:
        return f"#joint-{k}" if k in has_card else f"#row-{k}"

    parts = [_page_head(f"smdinspect — {result.board}")]
    parts.append(f"<h1>{esc(result.board)}: {status}</h1>")
    parts.append(f"<p>{len(result.joints)} joints: {len(result.defects)} defective, "
                 f"{counts['unreliable']} unreliable (not judged: look at them). "
                 + (f"Source: {esc(source)}; " if source else "") +
                 f"board file {esc(result.board_source)}; "
                 f"smdinspect {esc(__version__)}, {esc(_now())}.</p>")
    items = []
    for title, ks in (("Defects", [k for k in look if result.joints[k].is_defect]),
                      ("Unreliable", [k for k in look if not result.joints[k].is_defect])):
        if ks:
            links = ", ".join(f"<a href='#joint-{k}'>{esc(result.joints[k].id)}</a> "
                              f"{_chip(result.joints[k].verdict.value)}{esc(result.joints[k].verdict.value)}"
                              for k in ks)
            items.append(f"<li><b>{title}:</b> {links}</li>")
    if items:
        parts.append("<ul class='look'>" + "".join(items) + "</ul>")
    parts.append(
        "<table class='kv'>"
        f"<tr><th class='l'>registration</th><td>{esc(reg.method)}, rotation {reg.rotation_deg:+.3f}°, "
        f"board centre offset ({reg.offset_mm[0]:+.3f}, {reg.offset_mm[1]:+.3f}) mm</td></tr>"
        f"<tr><th class='l'>match</th><td>score {reg.score:.3f}, fitness {reg.fitness:.3f}, "
        f"inlier RMSE {reg.rmse_mm * 1000:.1f} µm</td></tr>"
        f"<tr><th class='l'>board plane</th><td>tilt {result.plane.tilt_deg:.3f}°, RMSE "
        f"{result.plane.rmse_mm * 1000:.1f} µm, {result.plane.inlier_fraction:.0%} inliers</td></tr>"
        f"<tr><th class='l'>measurement</th><td>{result.shape[1]}×{result.shape[0]} px at "
        f"{result.pixel_size_mm * 1000:.1f} µm/px, {result.coverage:.0%} reliable"
        f"{esc(_beyond_text(result.meta.get('beyond_sweep')))}</td></tr>"
        f"<tr><th class='l'>rig calibration</th><td>{esc(_calibration_text(result.meta.get('calibration')))}</td></tr>"
        "</table>")
    legend = " ".join(f"{_chip(v.value)}{esc(v.value)} ({counts.get(v.value, 0)})" for v in Verdict)
    parts.append(f"<p>{legend}</p>")
    pictures = surface is not None and result.height_above_mm is not None
    aif_full = reliable = None
    if pictures:
        aif_full = _aif_rgb(surface)
        reliable = np.asarray(surface.reliable, bool) & np.isfinite(result.height_above_mm)
        scale = min(1.0, max_side / max(result.shape))
        marks = _overview_marks(result, scale, href)
        over_pic = resize(aif_full, scale)
        over_w = over_pic.shape[1]
        over = overview_svg(over_pic, marks, labels=True, aria="board overview with joint ids")
        side = min(1.0, SIDE_PX / max(result.shape))
        parts.append("<h2>Board</h2><div class='figs'>"
                     f"<figure style='max-width:{over_w}px'>{over}<figcaption>All-in-focus image; every pad outlined and "
                     "labelled in its verdict's colour (click a label for the joint).</figcaption>"
                     "</figure><div class='side'>")
        parts.append(_height_figure(result.height_above_mm, reliable, side,
                                    _overview_marks(result, side, href),
                                    caption="Height above the board plane.", aria="height map",
                                    joints=result.joints))
        parts.append(_view3d_figure(view3d, view3d_note))
        parts.append("</div></div>")
    if look:
        views = _joint_views(result) if pictures else {}
        parts.append(f"<h2>Joints to look at ({len(look)})</h2>")
        parts.append(
            "<p class='cap'>Each joint: its verdict and reason, the numbers, then the "
            "all-in-focus image and the height map around it (pad outlined, the profile line "
            "A → B, a scale bar), the height map's colour bar in the joint's own height range "
            "(green bracket: the acceptance band; higher parts such as a body top saturate), "
            "and the height profile along A → B: the median of the reliable pixels of a "
            "3-pixel strip, broken where none is reliable, against the acceptance band over "
            "the pad (green; dotted: nominal) and the measured max ± its uncertainty (in the "
            "verdict's colour).</p>")
        for k in look:
            j = result.joints[k]
            if pictures:
                parts.append(_joint_card(k, j, views.get(j.id), result, aif_full, reliable))
            else:
                parts.append(_joint_card(k, j, None, result, None, None))
    # Table.
    heads = [("id", "l"), ("component", "l"), ("verdict", "l"), ("max mm", ""), ("± mm", ""),
             ("band mm", ""), ("mean mm", ""), ("volume mm³", ""), ("area mm²", ""),
             ("reliable", ""), ("x mm", ""), ("y mm", ""), ("reason", "l")]
    parts.append("<h2>All joints</h2><p>Click a column to sort.</p><table class='sortable'><thead><tr>"
                 + "".join(f"<th class='{c}'>{esc(h)}</th>" for h, c in heads) + "</tr></thead><tbody>")
    order = {v.value: i for i, v in enumerate([v for v in Verdict if v.is_defect] + [Verdict.UNRELIABLE, Verdict.OK])}
    for k, j in enumerate(result.joints):
        jid = f"<a href='#joint-{k}'>{esc(j.id)}</a>" if k in has_card else esc(j.id)
        parts.append(
            f"<tr id='row-{k}'>"
            f"<td class='l' data-v='{esc(j.id)}'>{jid}</td><td class='l'>{esc(j.component)}</td>"
            f"<td class='l' data-v='{order.get(j.verdict.value, 99)}'>{_chip(j.verdict.value)}"
            f"{esc(j.verdict.value)}</td>"
            f"<td data-v='{_v(j.measured_max_mm)}'>{_fmt(j.measured_max_mm)}</td>"
            f"<td data-v='{_v(j.uncertainty_mm)}'>{_fmt(j.uncertainty_mm)}</td>"
            f"<td data-v='{_v(j.expected_min_mm)}'>{j.expected_min_mm:.3f}–{j.expected_max_mm:.3f}</td>"
            f"<td data-v='{_v(j.measured_mean_mm)}'>{_fmt(j.measured_mean_mm)}</td>"
            f"<td data-v='{_v(j.volume_mm3)}'>{_fmt(j.volume_mm3, 4)}</td>"
            f"<td data-v='{_v(j.area_mm2)}'>{_fmt(j.area_mm2, 3)}</td>"
            f"<td data-v='{j.reliable_fraction:.4f}'>{j.reliable_fraction:.0%}</td>"
            f"<td>{j.x_mm:.3f}</td><td>{j.y_mm:.3f}</td><td class='l'>{esc(j.reason)}</td></tr>")
    parts.append("</tbody></table>")
    parts.append(f"<script>{_JS}</script></body></html>\n")
    return "".join(parts)


def _v(x: float) -> str:
    return f"{x:.6g}" if math.isfinite(x) else "-1e99"


def not_located_html(board, registration, *, reason: str, surface=None,
                     source: str | None = None, max_side: int = OVERVIEW_PX,
                     view3d: np.ndarray | None = None,
                     view3d_note: str = "no 3D view was rendered") -> str:
    """The ``report.html`` of a board that could not be located: why, and what was seen.

    Shows the reason, the registration's numbers, the all-in-focus image with the best
    placement the registration found (rejected; dashed) and the measured height map
    (heights above the sweep's base, not levelled: no board plane was fitted against
    the board), and the 3D view.
    """
    from ._geometry import apply2d, world_to_pixel

    parts = [_page_head(f"smdinspect — {board.name}: not located")]
    parts.append(f"<h1>{esc(board.name)}: <span class='fail'>NOT LOCATED</span></h1>")
    parts.append(f"<p class='why' id='reason'><b>Why:</b> {esc(reason)}</p>")
    parts.append("<p>No joint was judged: joints are never measured against a placement "
                 "that failed its checks (exit code 3). Check that the board file is the "
                 "board that was measured, that the board lies in the field of view, and "
                 "that the sweep covers the board's heights (the pictures below show what "
                 "was measured). " + (f"Source: {esc(source)}; " if source else "") + "board file "
                 f"{esc(getattr(board, 'source', ''))}; smdinspect {esc(__version__)}, "
                 f"{esc(_now())}.</p>")
    rows = []
    if registration is not None:
        reg = registration
        rows += [("registration", f"{reg.method}: {'located' if reg.converged else 'rejected'}"
                  + (f" ({reg.reason})" if reg.reason else "")),
                 ("best placement", f"rotation {reg.rotation_deg:+.3f}°, board centre offset "
                  f"({reg.offset_mm[0]:+.3f}, {reg.offset_mm[1]:+.3f}) mm"),
                 ("match", f"score {reg.score:.3f}, fitness {reg.fitness:.3f}, inlier RMSE "
                  f"{reg.rmse_mm * 1000:.1f} µm")]
    else:
        rows.append(("registration", "not attempted"))
    if surface is not None:
        H, W = surface.shape
        p = surface.pixel_size_mm
        rows.append(("measurement", f"{W}×{H} px" + (f" at {p * 1000:.1f} µm/px" if p else "")
                     + f", {float(np.mean(surface.reliable)):.0%} reliable"))
    rows.append(("board", f"{board.size_mm[0]:g} × {board.size_mm[1]:g} mm, "
                 f"{len(board.components)} components, {len(board.joints())} joints"))
    parts.append("<table class='kv'>" + "".join(f"<tr><th class='l'>{esc(k)}</th><td>{esc(v)}</td></tr>"
                                                 for k, v in rows) + "</table>")
    if surface is not None:
        aif = _aif_rgb(surface)
        height = np.asarray(surface.height_mm, np.float64)
        reliable = np.asarray(surface.reliable, bool) & np.isfinite(height)
        scale = min(1.0, max_side / max(height.shape))
        extra = ""
        T = getattr(registration, "transform", None)
        p = surface.pixel_size_mm
        if T is not None and p and np.all(np.isfinite(T)):
            def px(poly_mm):
                pts = world_to_pixel(apply2d(np.asarray(T), poly_mm), shape=height.shape,
                                     pixel_size_mm=p)
                return " ".join(f"{x:.1f},{y:.1f}" for x, y in (pts + 0.5) * scale)

            pads = "".join(f"<polygon points='{px(j.polygon_mm)}'/>" for j in board.joints())
            extra = ("<g fill='none' stroke='#ff9800' stroke-width='1.5' stroke-dasharray='5 3'>"
                     f"<title>best placement found (rejected)</title>"
                     f"<polygon points='{px(board.outline_mm())}' stroke-width='2.5'/>{pads}</g>")
        over_pic = resize(aif, scale)
        over_w = over_pic.shape[1]
        over = overview_svg(over_pic, [], labels=False, extra=extra, aria="all-in-focus image")
        parts.append("<h2>What was measured</h2><div class='figs'>"
                     f"<figure style='max-width:{over_w}px'>{over}<figcaption>All-in-focus image"
                     + ("; orange dashed: the board outline and pads at the best placement "
                        "the registration found, which failed its checks" if extra else "")
                     + ".</figcaption></figure>")
        side = min(1.0, SIDE_PX / max(height.shape))
        parts.append("<div class='side'>")
        parts.append(_height_figure(height, reliable, side, [],
                                    caption="Measured height above the sweep's base (not levelled).",
                                    aria="height map"))
        parts.append(_view3d_figure(view3d, view3d_note))
        parts.append("</div></div>")
    parts.append("</body></html>\n")
    return "".join(parts)


# --------------------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------------------


def _read_rgb(path: Path) -> np.ndarray | None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if img is None else np.ascontiguousarray(img[:, :, ::-1])


def _view3d(surface, view3d_png: str | os.PathLike | None) -> tuple[np.ndarray | None, str]:
    """The 3D view for the report: ``view3d_png`` if given and readable, else the one of
    the reconstruction the surface was loaded from, else rendered now (with
    :func:`smdinspect.sff.render_view3d_png`). Returns (RGB or None, why not)."""
    if surface is None:
        return None, "no surface"
    cands = [Path(view3d_png)] if view3d_png is not None else []
    loaded = (getattr(surface, "meta", None) or {}).get("loaded_from")
    if loaded:
        cands.append(Path(loaded) / "view3d.png")
    for c in cands:
        if c.is_file():
            img = _read_rgb(c)
            if img is not None:
                return img, ""
    try:
        from ..sff import render_view3d_png

        with tempfile.TemporaryDirectory(prefix="smdinspect-view3d-") as tmp:
            path = Path(tmp) / "view3d.png"
            render_view3d_png(surface, path)
            img = _read_rgb(path)
        return img, "" if img is not None else "the rendered picture could not be read"
    except Exception as exc:  # noqa: BLE001 - a missing picture must not lose the report
        log.warning("3D view for the report not rendered: %s", exc)
        return None, f"{type(exc).__name__}: {exc}"


def write_reports(result: InspectionResult, out_dir: str | os.PathLike, *,
                  source: str | None = None, html_report: bool = True,
                  view3d_png: str | os.PathLike | None = None) -> dict[str, Path]:
    """Write ``report.json``, ``joints.csv``, ``junit.xml`` and ``report.html`` atomically.

    Parameters
    ----------
    result : InspectionResult
    out_dir : path
    source : str, optional
        What the measurement came from.
    html_report : bool
        Write ``report.html`` too.
    view3d_png : path, optional
        The reconstruction's ``view3d.png`` to show in ``report.html``; without it (or
        when it cannot be read) the one next to a loaded reconstruction is used, or the
        view is rendered from ``result.surface``.

    Returns
    -------
    dict
        File name → path.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "joints.csv": _atomic.write_text(out / "joints.csv", joints_csv(result)),
        "junit.xml": _atomic.write_text(out / "junit.xml", junit_xml(result)),
    }
    if html_report:
        img, note = _view3d(result.surface, view3d_png)
        paths["report.html"] = _atomic.write_text(
            out / "report.html", report_html(result, source=source, view3d=img, view3d_note=note))
    # report.json last: its presence says the set is complete.
    paths["report.json"] = _atomic.write_json(out / "report.json", report_dict(result, source=source))
    return paths


def write_not_located(out_dir: str | os.PathLike, board, registration, *, reason: str,
                      source: str | None = None, shape=None, pixel_size_mm=None,
                      surface=None, html_report: bool = True,
                      view3d_png: str | os.PathLike | None = None) -> dict[str, Path]:
    """Write ``report.json`` with ``"status": "not_located"`` and a ``report.html`` saying why.

    ``surface`` (the measurement) adds its pictures to ``report.html``; ``view3d_png``
    as in :func:`write_reports`. Returns file name → path.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    if html_report:
        img, note = _view3d(surface, view3d_png) if surface is not None else (None, "")
        paths["report.html"] = _atomic.write_text(
            out / "report.html", not_located_html(board, registration, reason=reason,
                                                  surface=surface, source=source, view3d=img,
                                                  view3d_note=note))
    doc = not_located_dict(board, registration, reason=reason, source=source, shape=shape,
                           pixel_size_mm=pixel_size_mm)
    paths["report.json"] = _atomic.write_json(out / "report.json", doc)
    return paths
