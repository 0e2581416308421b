"""Reports of an inspection: report.json, joints.csv, junit.xml and report.html.

Every file is written atomically. ``report.html`` is self-contained: its pictures are
base64 PNGs in the page and the table sorts with a few lines of inline JavaScript.

``report.json`` schema (version 1)::

    {
      "schema": "smdinspect-report", "version": 1,
      "created": "2025-01-01T12:00:00+00:00", "smdinspect_version": "0.1.0",
      "status": "inspected",                      # or "not_located"
      "passed": true, "exit_code": 0,             # 0 no defect, 1 defects, 3 not located
      "board": {"name": "demo_board", "source": "references/demo_board.json",
                "size_mm": [9.5, 9.5]},
      "measurement": {"shape": [H, W], "pixel_size_mm": 0.02, "coverage": 0.93,
                      "step_mm": 0.05, "source": "stacks/b1"},
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

import base64
import csv
import datetime as _dt
import html
import io
import math
import os
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import numpy as np

from .. import __version__, _atomic
from ._config import Verdict
from ._result import InspectionResult

__all__ = ["REPORT_FILES", "report_dict", "write_reports"]

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
                        "step_mm": _num(result.meta.get("step_mm")), "source": source},
        "registration": result.registration.to_dict(),
        "plane": {k: (round(v, 6) if isinstance(v, float) else v)
                  for k, v in result.plane.to_dict().items()},
        "summary": {"joints": len(result.joints), "defects": len(result.defects),
                    "unreliable": counts["unreliable"], "by_verdict": counts},
        "config": result.config.to_dict(),
        "components": [c.to_dict() for c in result.components],
        "joints": [j.to_dict() for j in result.joints],
    }


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


def _png_b64(rgb: np.ndarray) -> str:
    import cv2

    img = np.ascontiguousarray(rgb[:, :, ::-1]) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes uint8
        raise OSError("could not encode a report picture")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _aif_rgb(surface) -> np.ndarray:
    img = np.asarray(surface.aif)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(np.round(img.astype(np.float32) * 255), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img


def _height_rgb(level: np.ndarray, reliable: np.ndarray) -> tuple[np.ndarray, float, float]:
    import matplotlib

    vals = level[reliable]
    lo, hi = (float(np.percentile(vals, 0.5)), float(np.percentile(vals, 99.8))) if vals.size else (0.0, 1.0)
    hi = max(hi, lo + 1e-3)
    cmap = matplotlib.colormaps["viridis"]
    rgb = (cmap(np.clip((level - lo) / (hi - lo), 0, 1))[:, :, :3] * 255).astype(np.uint8)
    rgb[~reliable] = (rgb[~reliable] * 0.25 + 40).astype(np.uint8)
    return rgb, lo, hi


def _scale_for(shape, max_side: int) -> float:
    return min(1.0, max_side / max(shape))


def _draw_outlines(rgb: np.ndarray, result: InspectionResult, scale: float, thickness: int = 1) -> np.ndarray:
    import cv2

    out = np.ascontiguousarray(rgb.copy())
    for j in result.joints:
        if j.polygon_px is None:
            continue
        pts = np.round((np.asarray(j.polygon_px) + 0.5) * scale * 16).astype(np.int32)
        cv2.polylines(out, [pts], True, COLOURS[j.verdict.value], thickness, cv2.LINE_AA, shift=4)
    return out


def _resize(rgb: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    if scale == 1.0:
        return rgb
    h, w = rgb.shape[:2]
    return cv2.resize(rgb, (max(1, round(w * scale)), max(1, round(h * scale))),
                      interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)


def _crop(rgb: np.ndarray, poly_px: np.ndarray, pad_px: int, size: int = 160) -> np.ndarray:
    import cv2

    H, W = rgb.shape[:2]
    c0, r0 = np.floor(poly_px.min(axis=0)).astype(int) - pad_px
    c1, r1 = np.ceil(poly_px.max(axis=0)).astype(int) + pad_px
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, W), min(r1, H)
    sub = rgb[r0:r1, c0:c1]
    if sub.size == 0:
        return np.zeros((size, size, 3), np.uint8)
    s = size / max(sub.shape[:2])
    sub = cv2.resize(sub, (max(1, round(sub.shape[1] * s)), max(1, round(sub.shape[0] * s))),
                     interpolation=cv2.INTER_NEAREST if s > 1 else cv2.INTER_AREA)
    pts = np.round((poly_px - [c0, r0] + 0.5) * s * 16).astype(np.int32)
    sub = np.ascontiguousarray(sub)
    cv2.polylines(sub, [pts], True, (255, 255, 255), 1, cv2.LINE_AA, shift=4)
    return sub


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.2em;color:#222}
h1{font-size:1.4em;margin:0 0 .2em}h2{font-size:1.1em;margin:1.2em 0 .4em}
.pass{color:#2e7d32;font-weight:bold}.fail{color:#c62828;font-weight:bold}
.figs{display:flex;flex-wrap:wrap;gap:12px}.figs figure{margin:0}
figcaption{font-size:.85em;color:#555}
table{border-collapse:collapse;font-size:.85em}th,td{border:1px solid #ddd;padding:2px 6px;text-align:right}
th{background:#f3f3f3;cursor:pointer;user-select:none}td.l,th.l{text-align:left}
.chip{display:inline-block;width:.8em;height:.8em;border-radius:2px;margin-right:4px;vertical-align:middle}
.crops{display:flex;flex-wrap:wrap;gap:10px}.crop{border:1px solid #ddd;padding:4px;font-size:.8em;max-width:340px}
.kv td{text-align:left}
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


def report_html(result: InspectionResult, *, source: str | None = None, max_side: int = 900) -> str:
    """The self-contained ``report.html`` document."""
    surface = result.surface
    e = html.escape
    reg = result.registration
    counts = result.counts()
    status = ('<span class="pass">PASS</span>' if result.passed else '<span class="fail">FAIL</span>')
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>smdinspect — {e(result.board)}</title>"
             f"<style>{_CSS}</style></head><body>"]
    parts.append(f"<h1>{e(result.board)}: {status}</h1>")
    parts.append(f"<p>{len(result.joints)} joints: {len(result.defects)} defective, "
                 f"{counts['unreliable']} unreliable (not judged). "
                 f"Source: {e(str(source or ''))}; board file {e(result.board_source)}; "
                 f"smdinspect {e(__version__)}, {e(_now())}.</p>")
    parts.append("<table class='kv'>"
                 f"<tr><th class='l'>registration</th><td>{e(reg.method)}, rotation {reg.rotation_deg:+.3f}°, "
                 f"board centre offset ({reg.offset_mm[0]:+.3f}, {reg.offset_mm[1]:+.3f}) mm</td></tr>"
                 f"<tr><th class='l'>match</th><td>score {reg.score:.3f}, fitness {reg.fitness:.3f}, "
                 f"inlier RMSE {reg.rmse_mm * 1000:.1f} µm</td></tr>"
                 f"<tr><th class='l'>board plane</th><td>tilt {result.plane.tilt_deg:.3f}°, RMSE "
                 f"{result.plane.rmse_mm * 1000:.1f} µm, {result.plane.inlier_fraction:.0%} inliers</td></tr>"
                 f"<tr><th class='l'>measurement</th><td>{result.shape[1]}×{result.shape[0]} px at "
                 f"{result.pixel_size_mm * 1000:.1f} µm/px, {result.coverage:.0%} reliable</td></tr>"
                 "</table>")
    legend = " ".join(f"<span class='chip' style='background:rgb{COLOURS[v]}'></span>{e(v)}"
                      f" ({counts[v]})" for v in COLOURS)
    parts.append(f"<p>{legend}</p>")
    pictures = surface is not None and result.height_above_mm is not None
    if pictures:
        aif_full = _aif_rgb(surface)
        hfull, lo, hi = _height_rgb(result.height_above_mm, np.asarray(surface.reliable, bool))
        scale = _scale_for(result.shape, max_side)
        aif = _draw_outlines(_resize(aif_full, scale), result, scale, 2)
        hpic = _draw_outlines(_resize(hfull, scale), result, scale, 1)
        parts.append("<div class='figs'>"
                     f"<figure><img alt='all-in-focus image' src='data:image/png;base64,{_png_b64(aif)}'>"
                     "<figcaption>All-in-focus image; pads outlined in their verdict's colour.</figcaption></figure>"
                     f"<figure><img alt='height map' src='data:image/png;base64,{_png_b64(hpic)}'>"
                     f"<figcaption>Height above the board plane, {lo:.2f} (dark) … {hi:.2f} mm (yellow); "
                     "unreliable pixels dimmed.</figcaption></figure></div>")
    # Table.
    heads = [("id", "l"), ("component", "l"), ("verdict", "l"), ("max mm", ""), ("± mm", ""),
             ("band mm", ""), ("mean mm", ""), ("volume mm³", ""), ("area mm²", ""),
             ("reliable", ""), ("x mm", ""), ("y mm", ""), ("reason", "l")]
    parts.append("<h2>Joints</h2><p>Click a column to sort.</p><table class='sortable'><thead><tr>"
                 + "".join(f"<th class='{c}'>{e(h)}</th>" for h, c in heads) + "</tr></thead><tbody>")
    order = {v.value: i for i, v in enumerate([v for v in Verdict if v.is_defect] + [Verdict.UNRELIABLE, Verdict.OK])}
    for j in result.joints:
        col = COLOURS[j.verdict.value]
        parts.append(
            "<tr>"
            f"<td class='l'>{e(j.id)}</td><td class='l'>{e(j.component)}</td>"
            f"<td class='l' data-v='{order[j.verdict.value]}'><span class='chip' style='background:rgb{col}'></span>"
            f"{e(j.verdict.value)}</td>"
            f"<td data-v='{_v(j.measured_max_mm)}'>{_fmt(j.measured_max_mm)}</td>"
            f"<td data-v='{_v(j.uncertainty_mm)}'>{_fmt(j.uncertainty_mm)}</td>"
            f"<td data-v='{j.expected_min_mm}'>{j.expected_min_mm:.3f}–{j.expected_max_mm:.3f}</td>"
            f"<td data-v='{_v(j.measured_mean_mm)}'>{_fmt(j.measured_mean_mm)}</td>"
            f"<td data-v='{_v(j.volume_mm3)}'>{_fmt(j.volume_mm3, 4)}</td>"
            f"<td data-v='{_v(j.area_mm2)}'>{_fmt(j.area_mm2, 3)}</td>"
            f"<td data-v='{j.reliable_fraction:.4f}'>{j.reliable_fraction:.0%}</td>"
            f"<td>{j.x_mm:.3f}</td><td>{j.y_mm:.3f}</td><td class='l'>{e(j.reason)}</td></tr>")
    parts.append("</tbody></table>")
    # Crops of the failing joints.
    bad = [j for j in result.joints if j.is_defect and j.polygon_px is not None]
    if bad and pictures:
        pad_px = int(round(0.6 / result.pixel_size_mm))
        parts.append("<h2>Failing joints</h2><div class='crops'>")
        for j in bad:
            a = _crop(aif_full, np.asarray(j.polygon_px), pad_px)
            h = _crop(hfull, np.asarray(j.polygon_px), pad_px)
            parts.append(f"<div class='crop'><b>{e(j.id)}</b> — {e(j.verdict.value)}<br>"
                         f"<img alt='{e(j.id)} image' src='data:image/png;base64,{_png_b64(a)}'> "
                         f"<img alt='{e(j.id)} height' src='data:image/png;base64,{_png_b64(h)}'><br>"
                         f"{e(j.reason)}</div>")
        parts.append("</div>")
    parts.append(f"<script>{_JS}</script></body></html>\n")
    return "".join(parts)


def _v(x: float) -> str:
    return f"{x:.6g}" if math.isfinite(x) else "-1e99"


# --------------------------------------------------------------------------------------
# Writing.
# --------------------------------------------------------------------------------------


def write_reports(result: InspectionResult, out_dir: str | os.PathLike, *,
                  source: str | None = None, html_report: bool = True) -> dict[str, Path]:
    """Write ``report.json``, ``joints.csv``, ``junit.xml`` and ``report.html`` atomically.

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
        paths["report.html"] = _atomic.write_text(out / "report.html", report_html(result, source=source))
    # report.json last: its presence says the set is complete.
    paths["report.json"] = _atomic.write_json(out / "report.json", report_dict(result, source=source))
    return paths


def write_not_located(out_dir: str | os.PathLike, board, registration, *, reason: str,
                      source: str | None = None, shape=None, pixel_size_mm=None) -> Path:
    """Write a ``report.json`` with ``"status": "not_located"`` (and nothing else)."""
    doc = not_located_dict(board, registration, reason=reason, source=source, shape=shape,
                           pixel_size_mm=pixel_size_mm)
    return _atomic.write_json(Path(out_dir) / "report.json", doc)

