"""SPC across boards from their ``report.json`` files: ``spc.csv``, charts, HTML pages.

``analyse_reports(dirs)`` reads the board reports (see :mod:`._report` for the format),
builds one series per joint and per package/joint type for each metric of
:data:`METRICS`, and runs :mod:`._spc` on them; ``write_spc(analysis, out_dir)`` writes

``spc.csv``
    one row per (scope, key, metric): n, mean, σ, σ_within, band, Cp, Cpk, Pp, Ppk,
    centre line and limits, the rules that fired and at which board (columns
    :data:`SPC_COLUMNS`).
``spc_flags.csv``
    one row per rule hit: which series, board, rule and what the rule means.
``spc_values.csv``
    the values themselves, one row per (board, joint).
``charts/*.png``
    a control chart per joint (max height with its band, volume, area) and per type.
``spc.html``
    the table, flagged series first, with the charts.

The batch page (:func:`write_batch_page`) lists every board's verdict and links to it.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .. import _atomic
from ..errors import InputError
from ._spc import MAX_SUBGROUP, RULES, Capability, ControlChart, capability, \
    individuals_chart, xbar_r_chart

__all__ = [
    "METRICS",
    "SPC_COLUMNS",
    "BoardRecord",
    "SeriesResult",
    "SpcAnalysis",
    "analyse_reports",
    "find_reports",
    "safe_cell",
    "write_batch_page",
    "write_spc",
]

#: metric → (key in report.json "measured", unit, label). Only the max height has a
#: band (the joint's expected min/max height), so only it gets Cp/Cpk.
METRICS = {
    "max_height_mm": ("max_height_mm", "mm", "max height"),
    "volume_mm3": ("volume_mm3", "mm3", "volume"),
    "area_mm2": ("area_mm2", "mm2", "area"),
}

SPC_COLUMNS = (
    "scope", "key", "component", "package", "termination", "metric", "unit", "chart",
    "n_boards", "n", "mean", "sigma", "sigma_within", "lsl", "usl", "cp", "cpk", "pp", "ppk",
    "cl", "ucl", "lcl", "baseline_boards", "flags", "first_flag_board", "rules", "chart_png",
)
FLAG_COLUMNS = ("scope", "key", "metric", "board_index", "board", "value", "rule", "meaning")
VALUE_COLUMNS = ("board_index", "board", "board_verdict", "joint", "component", "package",
                 "termination", "verdict", "max_height_mm", "volume_mm3", "area_mm2",
                 "min_height_mm", "max_allowed_height_mm")


def safe_cell(value: Any) -> Any:
    """A CSV cell a spreadsheet will not run: text starting with ``= + - @`` (or a tab /
    carriage return) gets a leading ``'``. Numbers are left alone."""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value


@dataclass(frozen=True)
class BoardRecord:
    """One board's report, as SPC needs it."""

    label: str
    report_dir: Path
    created: str
    status: str
    passed: bool
    exit_code: int
    joints: tuple[dict[str, Any], ...]
    packages: dict[str, str]
    board_name: str


@dataclass(frozen=True)
class SeriesResult:
    """One series (a joint or a type, one metric) across the boards."""

    scope: str  # "joint" or "type"
    key: str
    metric: str
    component: str
    package: str
    termination: str
    values: np.ndarray  # (n_boards,) or (n_boards, k)
    capability: Capability
    chart: ControlChart
    chart_png: str = ""

    @property
    def flagged(self) -> bool:
        return bool(self.chart.hits)


@dataclass(frozen=True)
class SpcAnalysis:
    """Everything :func:`write_spc` writes."""

    boards: tuple[BoardRecord, ...]
    series: tuple[SeriesResult, ...]
    baseline: int
    skipped: tuple[str, ...] = field(default=())

    def flagged(self) -> list[SeriesResult]:
        return [s for s in self.series if s.flagged]

    def get(self, scope: str, key: str, metric: str = "max_height_mm") -> SeriesResult:
        for s in self.series:
            if (s.scope, s.key, s.metric) == (scope, key, metric):
                return s
        raise KeyError((scope, key, metric))


# ---------------------------------------------------------------------------------
# Reading.
# ---------------------------------------------------------------------------------


def _natural_key(text: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", text)]


def find_reports(paths: Sequence[str | os.PathLike], *, order: str = "name",
                 labels: Sequence[str] | None = None) -> list[tuple[str, Path]]:
    """The board report folders (holding ``report.json``) given or found under ``paths``.

    Parameters
    ----------
    paths : sequence of path
        Board report folders, or folders searched recursively (hidden folders and the
        batch's temporary folders are skipped).
    order : {"name", "given", "created"}
        Production order of the boards: natural sort of their labels (``board_9``
        before ``board_10``; default), the order found (each path's folders sorted), or
        the reports' ``created`` time.
    labels : sequence of str, optional
        One label per path; each path must then be a board report folder.

    Returns
    -------
    list of (label, folder)
        ``label`` is the folder's path relative to the path it was found under
        (its own name for a folder given directly).
    """
    if order not in ("name", "given", "created"):
        raise InputError(f"order must be 'name', 'given' or 'created'; got {order!r}")
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    if labels is not None and len(labels) != len(paths):
        raise InputError(f"labels must give one label per path; got {len(labels)} for "
                         f"{len(paths)} paths")
    found: list[tuple[str, Path]] = []
    seen: set[Path] = set()
    for n, p in enumerate(paths):
        root = Path(p)
        if not root.is_dir():
            raise InputError(f"report folder not found: {root}")
        if labels is not None:
            if not (root / "report.json").is_file():
                raise InputError(f"no report.json in {root}")
            cands = [(str(labels[n]), root)]
        elif (root / "report.json").is_file():
            cands = [(root.resolve().name, root)]
        else:
            cands = []
            for dirpath, dirnames, filenames in os.walk(root):
                dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
                if "report.json" in filenames:
                    here = Path(dirpath)
                    cands.append((here.relative_to(root).as_posix(), here))
            cands.sort(key=lambda c: _natural_key(c[0]))
        for label, folder in cands:
            real = folder.resolve()
            if real not in seen:
                seen.add(real)
                found.append((label, folder))
    if order == "name":
        found.sort(key=lambda c: _natural_key(c[0]))
    elif order == "created":
        found.sort(key=lambda c: _created(c[1]))
    return found


def _created(folder: Path) -> str:
    try:
        return str(json.loads((folder / "report.json").read_text(encoding="utf-8"))
                   .get("created", ""))
    except (OSError, ValueError, AttributeError):
        return ""


def _read_board(label: str, folder: Path) -> BoardRecord:
    path = folder / "report.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from None
    except ValueError as exc:
        raise InputError(f"{path} is not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("schema") != "smdinspect-report":
        raise InputError(f"{path} is not an smdinspect report (schema "
                         f"{doc.get('schema') if isinstance(doc, dict) else None!r})")
    joints = doc.get("joints") or []
    comps = doc.get("components") or []
    if not isinstance(joints, list) or not isinstance(comps, list):
        raise InputError(f"{path}: 'joints' and 'components' must be lists")
    packages = {str(c.get("ref")): str(c.get("package", "")) for c in comps
                if isinstance(c, dict)}
    return BoardRecord(
        label=label, report_dir=folder, created=str(doc.get("created", "")),
        status=str(doc.get("status", "")), passed=bool(doc.get("passed")),
        exit_code=int(doc.get("exit_code", 2) or 0),
        joints=tuple(j for j in joints if isinstance(j, dict)), packages=packages,
        board_name=str((doc.get("board") or {}).get("name", "")))


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f if math.isfinite(f) else math.nan


def analyse_reports(paths: Sequence[str | os.PathLike], *, order: str = "name",
                    baseline: int | None = None, labels: Sequence[str] | None = None
                    ) -> SpcAnalysis:
    """Read the board reports under ``paths`` and compute SPC for every joint and type.

    Parameters
    ----------
    paths : sequence of path
        See :func:`find_reports`.
    order : str
        Production order (see :func:`find_reports`).
    labels : sequence of str, optional
        Board labels, one per path (see :func:`find_reports`).
    baseline : int, optional
        Control limits from the first ``baseline`` boards (default: the first half,
        at least 8 boards, all of them when there are fewer than 8).

    Returns
    -------
    SpcAnalysis
        Boards that were not located (no joints) are listed in ``skipped`` and left
        out of the series.

    Raises
    ------
    InputError
        No report found, fewer than 2 inspected boards, or a report that cannot be read.
    """
    found = find_reports(paths, order=order, labels=labels)
    if not found:
        raise InputError("no report.json under " + ", ".join(str(p) for p in paths))
    boards, skipped = [], []
    for label, folder in found:
        rec = _read_board(label, folder)
        if rec.status != "inspected" or not rec.joints:
            skipped.append(label)
            continue
        boards.append(rec)
    if len(boards) < 2:
        raise InputError(f"SPC needs at least 2 inspected boards; found {len(boards)}"
                         + (f" ({len(skipped)} not located)" if skipped else ""))
    n = len(boards)
    if baseline is None:
        baseline = n if n < 8 else max(8, n // 2)
    elif isinstance(baseline, bool) or not isinstance(baseline, int) or baseline < 2:
        raise InputError(f"baseline must be an integer >= 2 (boards); got {baseline!r}")
    baseline = min(baseline, n)

    # every joint id seen, in board order of first appearance
    meta: dict[str, dict[str, Any]] = {}
    for b in boards:
        for j in b.joints:
            jid = str(j.get("id"))
            if jid not in meta:
                comp = str(j.get("component", ""))
                exp = j.get("expected") or {}
                meta[jid] = {"component": comp, "package": b.packages.get(comp, ""),
                             "termination": str(j.get("termination", "")),
                             "lsl": _num(exp.get("min_height_mm")),
                             "usl": _num(exp.get("max_height_mm"))}
    values = {m: {jid: np.full(n, np.nan) for jid in meta} for m in METRICS}
    for i, b in enumerate(boards):
        for j in b.joints:
            jid = str(j.get("id"))
            measured = j.get("measured") or {}
            for m, (key, _, _) in METRICS.items():
                values[m][jid][i] = _num(measured.get(key))

    series: list[SeriesResult] = []
    for jid, info in meta.items():
        for m in METRICS:
            x = values[m][jid]
            chart = individuals_chart(x, baseline=baseline)
            band = (info["lsl"], info["usl"]) if m == "max_height_mm" else (None, None)
            cap = capability(x, lsl=band[0], usl=band[1], sigma_within=chart.sigma)
            series.append(SeriesResult(scope="joint", key=jid, metric=m,
                                       component=info["component"], package=info["package"],
                                       termination=info["termination"], values=x,
                                       capability=cap, chart=chart))
    types: dict[str, list[str]] = {}
    for jid, info in meta.items():
        types.setdefault(f"{info['package'] or '?'}/{info['termination'] or '?'}", []).append(jid)
    for tkey, jids in types.items():
        info = meta[jids[0]]
        for m in METRICS:
            g = np.stack([values[m][j] for j in jids], axis=1)  # (boards, k)
            if 2 <= g.shape[1] <= MAX_SUBGROUP:
                chart = xbar_r_chart(g, baseline=baseline)
            else:  # one joint of the type, or more than an R chart handles: board means
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # a board without any
                    means = np.nanmean(g, axis=1)
                chart = individuals_chart(means, baseline=baseline)
            same_band = len({(meta[j]["lsl"], meta[j]["usl"]) for j in jids}) == 1
            band = ((info["lsl"], info["usl"]) if m == "max_height_mm" and same_band
                    else (None, None))
            flat = g[np.isfinite(g)]
            cap = capability(flat, lsl=band[0], usl=band[1], sigma_within=chart.sigma)
            series.append(SeriesResult(scope="type", key=tkey, metric=m, component="",
                                       package=info["package"], termination=info["termination"],
                                       values=g, capability=cap, chart=chart))
    return SpcAnalysis(boards=tuple(boards), series=tuple(series), baseline=baseline,
                       skipped=tuple(skipped))


# ---------------------------------------------------------------------------------
# Writing.
# ---------------------------------------------------------------------------------


def _f(v: float, nd: int = 6) -> str:
    return "" if v is None or not math.isfinite(v) else f"{v:.{nd}g}"


def _rules_text(s: SeriesResult, boards: Sequence[BoardRecord]) -> str:
    return ";".join(f"{h.rule}@{boards[h.index].label}" for h in s.chart.hits)


def _csv(columns: Sequence[str], rows: Iterable[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: safe_cell(r.get(k, "")) for k in columns})
    return buf.getvalue()


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "x"


def write_spc(analysis: SpcAnalysis, out_dir: str | os.PathLike, *, charts: bool = True
              ) -> dict[str, Path]:
    """Write ``spc.csv``, ``spc_flags.csv``, ``spc_values.csv``, ``charts/*.png`` and
    ``spc.html`` into ``out_dir`` (created; each file written atomically).

    Returns
    -------
    dict
        Name → path of what was written (``"spc.csv"``, ``"spc.html"``, ...).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    boards = analysis.boards
    written: dict[str, Path] = {}
    series = list(analysis.series)
    if charts:
        (out / "charts").mkdir(exist_ok=True)
        by_key: dict[tuple[str, str], list[SeriesResult]] = {}
        for s in series:
            by_key.setdefault((s.scope, s.key), []).append(s)
        names = {}
        for (scope, key), group in by_key.items():
            rel = f"charts/{scope}_{_slug(key)}.png"
            _chart_png(group, boards, out / rel, title=f"{scope} {key}")
            names[(scope, key)] = rel
        keep = {out / rel for rel in names.values()}
        for old in (out / "charts").glob("*.png"):  # charts of an earlier run's joints
            if old not in keep:
                old.unlink(missing_ok=True)
        series = [_with_png(s, names[(s.scope, s.key)]) for s in series]

    rows = []
    for s in series:
        c, ch = s.capability, s.chart
        first = ch.first_hit
        rows.append({
            "scope": s.scope, "key": s.key, "component": s.component, "package": s.package,
            "termination": s.termination, "metric": s.metric, "unit": METRICS[s.metric][1],
            "chart": ch.kind, "n_boards": len(boards), "n": c.n, "mean": _f(c.mean),
            "sigma": _f(c.sigma), "sigma_within": _f(c.sigma_within), "lsl": _f(c.lsl),
            "usl": _f(c.usl), "cp": _f(c.cp, 4), "cpk": _f(c.cpk, 4), "pp": _f(c.pp, 4),
            "ppk": _f(c.ppk, 4), "cl": _f(ch.cl), "ucl": _f(ch.ucl), "lcl": _f(ch.lcl),
            "baseline_boards": ch.baseline, "flags": len(ch.hits),
            "first_flag_board": "" if first is None else boards[first].label,
            "rules": _rules_text(s, boards), "chart_png": s.chart_png,
        })
    written["spc.csv"] = _atomic.write_text(out / "spc.csv", _csv(SPC_COLUMNS, rows))

    flags = []
    for s in series:
        for h in s.chart.hits:
            flags.append({"scope": s.scope, "key": s.key, "metric": s.metric,
                          "board_index": h.index, "board": boards[h.index].label,
                          "value": _f(float(s.chart.values[h.index])), "rule": h.rule,
                          "meaning": RULES[h.rule]})
    written["spc_flags.csv"] = _atomic.write_text(out / "spc_flags.csv",
                                                  _csv(FLAG_COLUMNS, flags))

    vrows = []
    for i, b in enumerate(boards):
        verdict = "pass" if b.passed else "fail"
        for j in b.joints:
            m, e = j.get("measured") or {}, j.get("expected") or {}
            comp = str(j.get("component", ""))
            vrows.append({"board_index": i, "board": b.label, "board_verdict": verdict,
                          "joint": j.get("id"), "component": comp,
                          "package": b.packages.get(comp, ""),
                          "termination": j.get("termination", ""),
                          "verdict": j.get("verdict", ""),
                          "max_height_mm": _f(_num(m.get("max_height_mm"))),
                          "volume_mm3": _f(_num(m.get("volume_mm3"))),
                          "area_mm2": _f(_num(m.get("area_mm2"))),
                          "min_height_mm": _f(_num(e.get("min_height_mm"))),
                          "max_allowed_height_mm": _f(_num(e.get("max_height_mm")))})
    written["spc_values.csv"] = _atomic.write_text(out / "spc_values.csv",
                                                   _csv(VALUE_COLUMNS, vrows))
    written["spc.html"] = _atomic.write_text(out / "spc.html",
                                             _spc_html(analysis, series, rows))
    return written


def _with_png(s: SeriesResult, rel: str) -> SeriesResult:
    from dataclasses import replace

    return replace(s, chart_png=rel)


def _chart_png(group: list[SeriesResult], boards: Sequence[BoardRecord], path: Path, *,
               title: str) -> None:
    """One PNG: a panel per metric with the points, centre line, 3σ limits, the band
    (max height) and the points where a run rule fired (red, with the rule numbers)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8.0, 2.1 * len(group) + 0.6), dpi=90)
    x = np.arange(1, len(boards) + 1)
    for k, s in enumerate(group):
        ax = fig.add_subplot(len(group), 1, k + 1)
        ch = s.chart
        unit = METRICS[s.metric][1]
        ax.plot(x, ch.values, "o-", color="#1f77b4", ms=3.5, lw=1)
        for y, style, lab in ((ch.cl, "-", "CL"), (ch.ucl, "--", "UCL"), (ch.lcl, "--", "LCL")):
            if math.isfinite(y):
                ax.axhline(y, color="#555", ls=style, lw=0.9)
                ax.annotate(f"{lab} {y:.4g}", (1.0, y), xycoords=("axes fraction", "data"),
                            fontsize=7, ha="left", va="center", color="#555")
        cap = s.capability
        for y, lab in ((cap.lsl, "LSL"), (cap.usl, "USL")):
            if math.isfinite(y):
                ax.axhline(y, color="#d62728", lw=1.2)
                ax.annotate(f"{lab} {y:.4g}", (1.0, y), xycoords=("axes fraction", "data"),
                            fontsize=7, ha="left", va="center", color="#d62728")
        hit_rules: dict[int, list[int]] = {}
        for h in ch.hits:
            hit_rules.setdefault(h.index, []).append(h.rule)
        for i, rules in hit_rules.items():
            ax.plot(x[i], ch.values[i], "o", color="#d62728", ms=6)
            ax.annotate(",".join(map(str, rules)), (x[i], ch.values[i]),
                        textcoords="offset points", xytext=(0, 6), fontsize=7,
                        ha="center", color="#d62728")
        if ch.baseline < len(boards):
            ax.axvline(ch.baseline + 0.5, color="#999", ls=":", lw=0.9)
        label = METRICS[s.metric][2] + (" (X̄)" if ch.kind == "xbar-r" else "")
        cpk = f", Cpk {cap.cpk:.2f}" if math.isfinite(cap.cpk) else ""
        ax.set_ylabel(f"{label} [{unit}]", fontsize=8)
        ax.set_title(f"{title}: {METRICS[s.metric][2]} — {ch.kind}{cpk}", fontsize=9,
                     loc="left")
        ax.tick_params(labelsize=7)
        ax.set_xlim(0.5, len(boards) + 0.5)
    fig.axes[-1].set_xlabel("board (production order)", fontsize=8)
    fig.subplots_adjust(left=0.1, right=0.86, top=0.95, bottom=0.08, hspace=0.55)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    _atomic.write_bytes(path, buf.getvalue())


_CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 6px;
text-align:right}td.t,th.t{text-align:left}tr.flag{background:#fde2e1}tr.fail{background:#fde2e1}
tr.error{background:#fff0c2}img{max-width:100%;border:1px solid #ddd;margin:4px 0}
.ok{color:#1a7f37}.bad{color:#c62828}"""


def _spc_html(analysis: SpcAnalysis, series: list[SeriesResult], rows: list[dict]) -> str:
    e = html.escape
    boards = analysis.boards
    order = sorted(range(len(series)), key=lambda i: (not series[i].flagged,
                                                      series[i].scope != "joint", i))
    head = ("<tr>" + "".join(f"<th class=t>{c}</th>" for c in ("scope", "key", "metric"))
            + "".join(f"<th>{c}</th>" for c in ("n", "mean", "σ", "σ within", "LSL", "USL",
                                                 "Cp", "Cpk", "flags"))
            + "<th class=t>first flag</th><th class=t>rules</th><th class=t>chart</th></tr>")
    body = []
    for i in order:
        s, r = series[i], rows[i]
        link = f'<a href="{e(s.chart_png)}">chart</a>' if s.chart_png else ""
        body.append(
            f'<tr class="{"flag" if s.flagged else ""}"><td class=t>{e(s.scope)}</td>'
            f"<td class=t>{e(s.key)}</td><td class=t>{e(s.metric)}</td>"
            + "".join(f"<td>{e(str(r[k]))}</td>" for k in ("n", "mean", "sigma", "sigma_within",
                                                          "lsl", "usl", "cp", "cpk", "flags"))
            + f"<td class=t>{e(r['first_flag_board'])}</td><td class=t>{e(r['rules'])}</td>"
              f"<td class=t>{link}</td></tr>")
    flagged_keys = []
    for s in series:
        if s.flagged and s.chart_png and s.chart_png not in flagged_keys:
            flagged_keys.append(s.chart_png)
    pics = "".join(f'<p><img src="{e(p)}" alt="{e(p)}"></p>' for p in flagged_keys)
    rules = "".join(f"<li>{k}: {e(v)}</li>" for k, v in RULES.items())
    n_flag = len({(s.scope, s.key) for s in series if s.flagged})
    skipped = (f"<p>Left out (not located): {e(', '.join(analysis.skipped))}</p>"
               if analysis.skipped else "")
    return (f"<!doctype html><html><head><meta charset=utf-8><title>SPC across "
            f"{len(boards)} boards</title><style>{_CSS}</style></head><body>"
            f"<h1>SPC across {len(boards)} boards</h1>"
            f"<p>Boards in production order: {e(', '.join(b.label for b in boards))}. "
            f"Control limits from the first {analysis.baseline} boards. "
            f"{n_flag} joint(s)/type(s) with a run rule firing. "
            f'<a href="spc.csv">spc.csv</a> · <a href="spc_flags.csv">spc_flags.csv</a> · '
            f'<a href="spc_values.csv">spc_values.csv</a></p>{skipped}'
            f"<table>{head}{''.join(body)}</table>"
            f"<h2>Charts of the flagged series</h2>{pics or '<p>none</p>'}"
            f"<h2>Run rules</h2><ul>{rules}</ul></body></html>\n")


def write_batch_page(path: str | os.PathLike, boards: Sequence[dict[str, Any]], *,
                     title: str = "smdinspect batch", spc: SpcAnalysis | None = None,
                     spc_dir: str = "spc", note: str = "") -> Path:
    """The batch's ``index.html``: every board's verdict (linked to its report) and,
    with ``spc``, the SPC summary linking ``spc_dir/spc.html``, ``spc.csv`` and the
    charts of the flagged joints.

    ``boards`` are the summary rows (``stack``, ``status``, ``exit_code``, ``joints``,
    ``defects``, ``unreliable``, ``reason``, ``report_dir``); links are relative to the
    page's folder.
    """
    e = html.escape
    page = Path(path)
    rows = []
    for b in boards:
        rel = Path(str(b.get("report_dir", "")))
        try:
            rel = rel.relative_to(page.parent.resolve())
        except ValueError:
            pass
        status = str(b.get("status", ""))
        link = rel.as_posix() + "/report.html"
        has_html = (page.parent / rel / "report.html").is_file()
        name = (f'<a href="{e(link)}">{e(str(b.get("stack", "")))}</a>' if has_html
                else e(str(b.get("stack", ""))))
        cls = {"ok": "", "defects": "fail", "error": "error"}.get(status, "")
        verdict = {"ok": '<span class="ok">PASS</span>',
                   "defects": '<span class="bad">FAIL</span>'}.get(status, "ERROR")
        rows.append(f'<tr class="{cls}"><td class=t>{name}</td><td class=t>{verdict}</td>'
                    f'<td>{e(str(b.get("exit_code", "")))}</td>'
                    + "".join(f'<td>{e("" if b.get(k) is None else str(b.get(k)))}</td>'
                              for k in ("joints", "defects", "unreliable"))
                    + f'<td class=t>{e(str(b.get("reason", "")))}</td></tr>')
    spc_html = ""
    if spc is not None:
        flagged = [s for s in spc.series if s.flagged]
        items = []
        for s in flagged:
            first = s.chart.first_hit
            when = spc.boards[first].label if first is not None else ""
            img = (f'<br><img src="{e(spc_dir + "/" + s.chart_png)}" alt="{e(s.key)}">'
                   if s.chart_png and s.scope == "joint" and s.metric == "max_height_mm" else "")
            cpk = f", Cpk {s.capability.cpk:.2f}" if math.isfinite(s.capability.cpk) else ""
            items.append(f"<li>{e(s.scope)} <b>{e(s.key)}</b> {e(METRICS[s.metric][2])}: "
                         f"rules {e(_rules_text(s, spc.boards))} (first at {e(when)}){cpk}"
                         f"{img}</li>")
        spc_html = (f'<h2>SPC across boards</h2><p><a href="{e(spc_dir)}/spc.html">SPC '
                    f'page</a> · <a href="{e(spc_dir)}/spc.csv">spc.csv</a> · '
                    f'<a href="{e(spc_dir)}/spc_flags.csv">spc_flags.csv</a></p>'
                    f"<p>{len(flagged)} series with a run rule firing (drift before "
                    f"defects):</p><ul>{''.join(items) or '<li>none</li>'}</ul>")
    elif note:
        spc_html = f"<h2>SPC across boards</h2><p>{e(note)}</p>"
    n_fail = sum(b.get("status") == "defects" for b in boards)
    n_err = sum(b.get("status") == "error" for b in boards)
    text = (f"<!doctype html><html><head><meta charset=utf-8><title>{e(title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{e(title)}</h1>"
            f"<p>{len(boards)} boards: {len(boards) - n_fail - n_err} pass, {n_fail} fail, "
            f"{n_err} errors. <a href=\"summary.csv\">summary.csv</a> · "
            f"<a href=\"junit.xml\">junit.xml</a></p>"
            "<table><tr><th class=t>board</th><th class=t>verdict</th><th>exit</th>"
            "<th>joints</th><th>defects</th><th>unreliable</th><th class=t>reason</th></tr>"
            f"{''.join(rows)}</table>{spc_html}</body></html>\n")
    return _atomic.write_text(page, text)
