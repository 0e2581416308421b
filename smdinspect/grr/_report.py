"""Writers of a gauge R&R study: ``grr.csv``, ``grr_values.csv``, ``grr.json``, ``grr.png``.

``grr.csv``
    one row per (scope, key, metric): the design (sweeps, operators, parts, readings),
    mean, repeatability / reproducibility / GR&R / part σ, the band, %GR&R of the
    tolerance and of the study variation, ndc and the AIAG rating
    (columns :data:`GRR_COLUMNS`).
``grr_values.csv``
    every reading, one row per (sweep, joint).
``grr.json``
    the same with each study's ANOVA table, the sweeps and the settings.
``grr.png``
    %GR&R of max height per joint and per type against the 10 % / 30 % lines, and each
    joint's readings around its mean.
"""

from __future__ import annotations

import io
import math
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from .. import __version__, _atomic
from ..inspect._spc_report import _csv, _f
from ._anova import ACCEPTABLE_PCT, MARGINAL_PCT
from ._study import GRR_METRICS, GrrRow, GrrStudy

__all__ = ["GRR_COLUMNS", "GRR_FILES", "VALUE_COLUMNS", "grr_dict", "write_grr"]

GRR_FILES = ("grr.csv", "grr_values.csv", "grr.json", "grr.png")

GRR_COLUMNS = (
    "scope", "key", "component", "package", "termination", "metric", "unit", "method",
    "n_sweeps", "n_operators", "n_parts", "n_joints", "n", "n_unreliable", "mean",
    "sigma_repeatability", "sigma_reproducibility", "sigma_grr", "sigma_part", "sigma_total",
    "cv_pct", "lsl", "usl", "tolerance", "pct_grr_tolerance", "pct_grr_study", "ndc",
    "rating", "interaction_p", "interaction_pooled",
)
VALUE_COLUMNS = ("sweep", "operator", "joint", "component", "package", "termination",
                 "max_height_mm", "volume_mm3", "area_mm2")




def _interaction_p(row: GrrRow) -> float:
    return next((t.p for t in row.gauge.anova if t.source == "part x operator"), math.nan)


def _row(study: GrrStudy, r: GrrRow) -> dict[str, Any]:
    g = r.gauge
    return {
        "scope": r.scope, "key": r.key, "component": r.component, "package": r.package,
        "termination": r.termination, "metric": r.metric, "unit": r.unit, "method": g.method,
        "n_sweeps": len(study.records), "n_operators": len(study.operators),
        "n_parts": g.n_parts, "n_joints": r.n_joints, "n": g.n, "n_unreliable": r.n_unreliable,
        "mean": _f(g.mean), "sigma_repeatability": _f(g.sigma_repeatability),
        "sigma_reproducibility": _f(g.sigma_reproducibility), "sigma_grr": _f(g.sigma_grr),
        "sigma_part": _f(g.sigma_part), "sigma_total": _f(g.sigma_total),
        "cv_pct": _f(r.cv_pct, 4), "lsl": _f(r.lsl), "usl": _f(r.usl),
        "tolerance": _f(g.tolerance), "pct_grr_tolerance": _f(g.pct_tolerance, 4),
        "pct_grr_study": _f(g.pct_study, 4), "ndc": _f(g.ndc), "rating": r.rating,
        "interaction_p": _f(_interaction_p(r), 4),
        "interaction_pooled": str(g.interaction_pooled).lower() if g.method == "crossed" else "",
    }


def grr_dict(study: GrrStudy, *, max_pct: float = MARGINAL_PCT) -> dict[str, Any]:
    """The study as the JSON object ``grr.json`` holds."""
    failing = study.failing(max_pct)
    return {
        "schema": "smdinspect-grr", "version": 1,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "smdinspect_version": __version__, "board": study.board_name,
        "settings": {"k_sigma": study.k_sigma, "include_unreliable": study.include_unreliable,
                     "fail_above_pct": max_pct, "acceptable_pct": ACCEPTABLE_PCT,
                     "marginal_pct": MARGINAL_PCT},
        "sweeps": [{"label": r.label, "operator": r.operator, "report": str(r.report_dir)}
                   for r in study.records],
        "operators": list(study.operators),
        "passed": not failing, "exit_code": 1 if failing else 0,
        "failing": [{"scope": r.scope, "key": r.key, "pct_grr_tolerance":
                     round(r.gauge.pct_tolerance, 3)} for r in failing],
        "studies": [{"scope": r.scope, "key": r.key, "metric": r.metric, "unit": r.unit,
                     "component": r.component, "package": r.package,
                     "termination": r.termination, "n_joints": r.n_joints,
                     "n_unreliable": r.n_unreliable, "rating": r.rating,
                     "band": [_j(r.lsl), _j(r.usl)], "cv_pct": _j(r.cv_pct),
                     **r.gauge.to_dict()} for r in study.rows],
    }


def _j(v: float):
    return float(v) if v is not None and math.isfinite(v) else None


def write_grr(study: GrrStudy, out_dir: str | os.PathLike, *, max_pct: float = MARGINAL_PCT,
              chart: bool = True) -> dict[str, Path]:
    """Write ``grr.csv``, ``grr_values.csv``, ``grr.json`` and ``grr.png`` into ``out_dir``
    (created; each file atomically).

    Returns
    -------
    dict
        File name → path of what was written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {
        "grr.csv": _atomic.write_text(out / "grr.csv", _csv(GRR_COLUMNS, (_row(study, r)
                                                                           for r in study.rows))),
        "grr_values.csv": _atomic.write_text(out / "grr_values.csv",
                                             _csv(VALUE_COLUMNS, _value_rows(study))),
        "grr.json": _atomic.write_json(out / "grr.json", grr_dict(study, max_pct=max_pct)),
    }
    if chart:
        written["grr.png"] = _atomic.write_bytes(out / "grr.png", _chart_png(study, max_pct))
    return written


def _value_rows(study: GrrStudy):
    for i, rec in enumerate(study.records):
        for jid, info in study.joint_meta.items():
            yield {"sweep": rec.label, "operator": rec.operator, "joint": jid,
                   "component": info["component"], "package": info["package"],
                   "termination": info["termination"],
                   **{m: _f(study.values[m][jid][i]) for m in GRR_METRICS}}


def _chart_png(study: GrrStudy, max_pct: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import numpy as np
    from matplotlib.figure import Figure

    colours = {"acceptable": "#2e7d32", "marginal": "#f9a825", "unacceptable": "#c62828",
               "n/a": "#9e9e9e"}
    joints = [r for r in study.rows if r.scope == "joint" and r.metric == "max_height_mm"]
    types = [r for r in study.rows if r.scope == "type" and r.metric == "max_height_mm"]
    bars = joints + types
    fig = Figure(figsize=(max(8.0, 0.32 * len(bars) + 2.0), 7.5), dpi=100)
    ax1, ax2 = fig.subplots(2, 1)
    x = np.arange(len(bars))
    pct = np.array([r.gauge.pct_tolerance for r in bars])
    ax1.bar(x, np.nan_to_num(pct), color=[colours[r.rating] for r in bars],
            edgecolor=["black" if r.scope == "type" else "none" for r in bars])
    for level, style in ((ACCEPTABLE_PCT, "--"), (MARGINAL_PCT, ":")):
        ax1.axhline(level, color="black", linestyle=style, linewidth=0.8)
    if max_pct not in (ACCEPTABLE_PCT, MARGINAL_PCT):
        ax1.axhline(max_pct, color="#c62828", linestyle="-", linewidth=0.8)
    for i in np.flatnonzero(~np.isfinite(pct)):
        ax1.text(i, 0.5, "n/a", ha="center", va="bottom", fontsize=7, rotation=90)
    ax1.set_xticks(x, [r.key for r in bars], rotation=90, fontsize=7)
    ax1.set_ylabel(f"%GR&R of tolerance ({study.k_sigma:g}σ)")
    ax1.set_title(f"{study.board_name}: max joint height, {len(study.records)} sweeps, "
                  f"{len(study.operators)} operator(s) (bars outlined: package/joint types; "
                  f"lines at {ACCEPTABLE_PCT:g} % and {MARGINAL_PCT:g} %)", fontsize=9)
    ax1.set_xlim(-0.6, len(bars) - 0.4)

    ops = list(study.operators)
    cmap = matplotlib.colormaps["tab10"]
    for i, r in enumerate(joints):
        v = study.values["max_height_mm"][r.key]
        dev_um = (v - np.nanmean(v)) * 1000.0 if np.isfinite(v).any() else v
        for k, o in enumerate(ops):
            sel = np.array([rec.operator == o for rec in study.records])
            ax2.plot(np.full(sel.sum(), i) + 0.12 * (k - (len(ops) - 1) / 2), dev_um[sel], "o",
                     ms=3.5, color=cmap(k % 10), label=o if i == 0 else None)
        half = 0.5 * r.tolerance * 1000.0 if math.isfinite(r.tolerance) else math.nan
        if math.isfinite(half):  # ±10 % of the band's half width: where 6σ = 10 % falls
            ax2.plot([i - 0.35, i + 0.35], [0.1 * half] * 2, color="0.6", linewidth=0.8)
            ax2.plot([i - 0.35, i + 0.35], [-0.1 * half] * 2, color="0.6", linewidth=0.8)
    ax2.axhline(0.0, color="black", linewidth=0.6)
    ax2.set_xticks(np.arange(len(joints)), [r.key for r in joints], rotation=90, fontsize=7)
    ax2.set_xlim(-0.6, len(bars) - 0.4)
    ax2.set_ylabel("max height − joint mean (µm)")
    ax2.set_title("readings per sweep (grey: ±5 % of the band, the 3σ of a 10 % gauge)",
                  fontsize=9)
    if len(ops) > 1:
        ax2.legend(title="operator", fontsize=7, loc="upper right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
