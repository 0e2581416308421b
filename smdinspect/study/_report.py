"""Tables, figures and the written summary of the texture study.

Files written into the study's ``--out`` (every one atomically):

``texture_study.csv``
    One row per scene × texture × noise × operator × fit (see ``METRICS``).
``texture_study.json``
    The settings, the timings and every number of the summary.
``texture_study.png``
    RMSE and coverage against contrast per operator family (each family's best
    operator, SML dashed), one column per sensor-noise level.
``texture_study_ranking.csv`` / ``texture_study_ranking.png``
    Operators ranked by mean score; the heat map shows each operator's score per
    noise level × contrast.
``texture_study.md``
    The written summary: ranking, winners per regime, where no operator can, how well
    the confidence says so, the fits, and ``--operator auto`` checked leave-one-out.
``operator_table.json``
    The table ``--operator auto`` reads (copy it over ``smdinspect/study/operator_table.json``
    to ship it).
"""

from __future__ import annotations

import csv
import io
import logging
import math
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ._auto import DEFAULT_OPERATOR, OperatorTable, choose_for_features
from ._features import TextureFeatures
from ._texture import METRICS, WRONG_WEIGHT, TextureStudy

__all__ = ["analyse_study", "build_operator_table", "write_study"]

log = logging.getLogger(__name__)

#: A cell where no operator (with any fit) gets this share of pixels within 1 Δd,
#: reliable or not, is one where depth cannot be recovered.
RECOVERABLE = 0.5
#: Below this share of pixels right and reliable, a regime's best operator is "none".
NOTHING = 0.05
#: Texture kinds that cover the whole surface (marks and grain are sparse by design).
DENSE_KINDS = ("band", "weave")
FAMILIES = ("laplacian", "gradient", "statistics", "wavelet", "dct", "miscellaneous")
_COLOURS = {"laplacian": "tab:blue", "gradient": "tab:orange", "statistics": "tab:green",
            "wavelet": "tab:red", "dct": "tab:purple", "miscellaneous": "tab:brown"}


def _mean(values: Iterable[float]) -> float:
    a = np.array([v for v in values if v is not None], np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def _median(values: Iterable[float]) -> float:
    a = np.array([v for v in values if v is not None], np.float64)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else math.nan


def _clean(obj: Any) -> Any:
    """JSON-safe: NaN/inf → None, numpy scalars → Python, floats rounded."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return round(v, 5) if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _default_fit(study: TextureStudy) -> str:
    return "power" if "power" in study.config.fits else study.config.fits[0]


def _by(rows: list[dict], *keys: str) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        out[tuple(r[k] for k in keys)].append(r)
    return out


def build_operator_table(study: TextureStudy) -> OperatorTable:
    """The ``--operator auto`` table of a study: features and scores of every cell."""
    ops = tuple(study.config.operators)
    keys, feats = [], []
    score = {f: [] for f in study.config.fits}
    good = {f: [] for f in study.config.fits}
    for doc in study.cells:
        keys.append(doc["key"])
        feats.append(_features(doc).vector())
        rows = {(r["fit"], r["operator"]): r for r in doc["rows"]}
        for f in study.config.fits:
            score[f].append([rows[(f, op)]["score"] for op in ops])
            good[f].append([rows[(f, op)]["good_share"] for op in ops])
    x = np.array(feats, np.float64)
    scale = x.std(axis=0) if len(x) > 1 else np.ones(x.shape[1])
    meta = {"generated_by": "smdinspect study texture", "settings": study.config.to_dict(),
            "fingerprint": study.config.fingerprint(), "cells": len(keys),
            "wrong_weight": WRONG_WEIGHT, "focus_ms_1mpx": dict(study.focus_ms)}
    return OperatorTable(ops, tuple(keys), x, np.maximum(scale, 1e-3),
                         {f: np.array(v, np.float64) for f, v in score.items()},
                         {f: np.array(v, np.float64) for f, v in good.items()}, meta=meta)


def _features(doc: dict) -> TextureFeatures:
    return TextureFeatures(**doc["features"])


def _ranking(rows: list[dict], fit: str, size_px: int, focus_ms: dict) -> list[dict]:
    out = []
    for (op,), rs in _by([r for r in rows if r["fit"] == fit], "operator").items():
        ms = _median(r["ms_per_frame"] for r in rs)
        out.append({
            "operator": op, "family": rs[0]["family"], "fit": fit,
            "score": _mean(r["score"] for r in rs),
            "good_share": _mean(r["good_share"] for r in rs),
            "coverage": _mean(r["coverage"] for r in rs),
            # pooled over pixels: wrong reliable pixels / reliable pixels
            "wrong_share": _pooled_wrong(rs),
            "rmse_steps": _median(r["rmse_steps"] for r in rs if r["coverage"] >= 0.05),
            "bias_steps": _median(r["bias_steps"] for r in rs if r["coverage"] >= 0.05),
            "confidence_auc": _median(r["confidence_auc"] for r in rs),
            "ms_per_frame": ms, "focus_ms_1mpx": focus_ms.get(op, math.nan),
            "wins": 0,
        })
    out.sort(key=lambda r: -r["score"])
    for i, r in enumerate(out):
        r["rank"] = i + 1
    return out


def _pooled_wrong(rs: list[dict]) -> float:
    cov = np.array([r["coverage"] for r in rs], np.float64)
    wrong = np.nan_to_num(np.array([r["wrong_share"] if r["wrong_share"] is not None
                                    else math.nan for r in rs], np.float64))
    return float((cov * wrong).sum() / cov.sum()) if cov.sum() > 0 else math.nan


def _best(rs: list[dict]) -> tuple[str, dict[str, float]]:
    """Operator with the best mean score over ``rs`` and every operator's mean score."""
    scores = {op: _mean(r["score"] for r in g) for (op,), g in _by(rs, "operator").items()}
    return max(scores, key=lambda op: (scores[op], op == DEFAULT_OPERATOR)), scores


def _winners(rows: list[dict], fit: str, keys: tuple[str, ...]) -> list[dict]:
    out = []
    for key, rs in sorted(_by([r for r in rows if r["fit"] == fit], *keys).items()):
        op, scores = _best(rs)
        good = {o: _mean(r["good_share"] for r in g) for (o,), g in _by(rs, "operator").items()}
        out.append({**dict(zip(keys, key)), "best": op if good[op] >= NOTHING else None,
                    "best_operator": op, "best_score": scores[op],
                    "best_good_share": good[op], "sml_score": scores.get(DEFAULT_OPERATOR),
                    "sml_good_share": good.get(DEFAULT_OPERATOR),
                    "recoverable": _mean(max(r["recoverable_share"] for r in g)
                                         for _, g in _by(rs, "key").items())})
    return out


def _crossing(xs: list[float], ys: list[float], level: float) -> float | None | str:
    """Lowest x above which ys stays >= level (log-interpolated); "never" or None (always)."""
    if not xs:
        return "never"
    if all(y >= level for y in ys):
        return None  # at or below the smallest contrast studied
    if ys[-1] < level:
        return "never"
    i = max(i for i in range(len(ys)) if ys[i] < level)
    x0, x1, y0, y1 = math.log(xs[i]), math.log(xs[i + 1]), ys[i], ys[i + 1]
    return float(math.exp(x0 + (level - y0) * (x1 - x0) / (y1 - y0)))


def analyse_study(study: TextureStudy) -> dict:
    """Every number of the summary (see :func:`write_study`)."""
    cfg = study.config
    rows = study.rows()
    fit = _default_fit(study)
    ranking = {f: _ranking(rows, f, cfg.size_px, study.focus_ms) for f in cfg.fits}
    fam_best = {}
    for fam in FAMILIES:
        members = [r for r in ranking[fit] if r["family"] == fam]
        if members:
            fam_best[fam] = members[0]["operator"]
    dense = [r for r in rows if r["texture"] in DENSE_KINDS] or rows

    # winners
    regimes = _winners(rows, fit, ("read_noise", "contrast", "freq_cyc_px"))
    by_kind = _winners(rows, fit, ("texture", "read_noise"))
    for w in regimes:
        for r in ranking[fit]:
            if r["operator"] == w["best"]:
                r["wins"] += 1

    # the contrast below which each family's (best operator's) coverage falls under 50 %
    thresholds: dict[str, dict] = {}
    for fam, op in fam_best.items():
        thresholds[fam] = {"operator": op}
        for n in cfg.read_noises:
            cs = list(cfg.contrasts)
            cov = [_mean(r["coverage"] for r in dense if r["operator"] == op and r["fit"] == fit
                         and r["read_noise"] == n and r["contrast"] == c) for c in cs]
            thresholds[fam][f"{n:g}"] = _crossing(cs, cov, 0.5)
    if DEFAULT_OPERATOR in cfg.operators:
        thresholds["sml (default)"] = {"operator": DEFAULT_OPERATOR, **{
            f"{n:g}": _crossing(list(cfg.contrasts), [
                _mean(r["coverage"] for r in dense if r["operator"] == DEFAULT_OPERATOR
                      and r["fit"] == fit and r["read_noise"] == n and r["contrast"] == c)
                for c in cfg.contrasts], 0.5) for n in cfg.read_noises}}

    # where no operator can, and what the confidence says there: judged on the dense
    # textures only (on sparse ones most pixels have nothing to measure by design)
    per_cell = _by(dense, "key")
    lost = {k for (k,), rs in per_cell.items()
            if max(r["recoverable_share"] for r in rs) < RECOVERABLE}
    fit_rows = [r for r in rows if r["fit"] == fit]
    dense_fit = [r for r in dense if r["fit"] == fit]
    lost_rows = [r for r in dense_fit if r["key"] in lost]
    kept_rows = [r for r in dense_fit if r["key"] not in lost]
    sparse = [r for r in fit_rows if r["texture"] not in DENSE_KINDS]
    none_can = {
        "cells": len(lost), "of": len(per_cell),
        "sparse_kinds": sorted({r["texture"] for r in sparse}),
        "sparse_coverage_best": max((_mean(r["coverage"] for r in g) for _, g in
                                     _by(sparse, "operator").items()), default=math.nan),
        "sparse_wrong_share": _pooled_wrong(sparse),
        "mean_coverage_claimed": _mean(r["coverage"] for r in lost_rows),
        "max_coverage_claimed": max((r["coverage"] for r in lost_rows), default=math.nan),
        "share_of_reconstructions_over_5pct": _mean(float(r["coverage"] > 0.05) for r in lost_rows),
        "wrong_share_of_claimed": _pooled_wrong(lost_rows),
        "wrong_share_elsewhere": _pooled_wrong(kept_rows),
        # where the confidence marks something at all (else every AUC is 0.5)
        "confidence_auc_median": _median(r["confidence_auc"] for r in fit_rows
                                         if r["coverage"] >= 0.05),
        "by_noise_contrast": [
            {"read_noise": n, "contrast": c, "share_lost": _mean(
                float(k in lost) for k in {r["key"] for r in dense
                                           if r["read_noise"] == n and r["contrast"] == c})}
            for n in cfg.read_noises for c in cfg.contrasts],
    }
    for n in cfg.read_noises:
        shares = [e["share_lost"] for e in none_can["by_noise_contrast"] if e["read_noise"] == n]
        recov = [1.0 - s for s in shares]
        none_can[f"contrast_recoverable_{n:g}"] = _crossing(list(cfg.contrasts), recov, 0.5)

    # the finding to check: SML under noise on low-frequency textures
    f_low = min(cfg.freqs_cyc_px)
    low = [r for r in fit_rows if r["freq_cyc_px"] == f_low and r["read_noise"] >= 0.01]
    sml_check = {"freq_cyc_px": f_low, "read_noise_at_least": 0.01, "cells": len({r["key"] for r in low})}
    if low:
        for op in dict.fromkeys([DEFAULT_OPERATOR, "glva", "glvn", "glvl", "gder", _best(low)[0]]):
            if op in cfg.operators:
                rs = [r for r in low if r["operator"] == op]
                sml_check[op] = {"good_share": _mean(r["good_share"] for r in rs),
                                 "recoverable_share": _mean(r["recoverable_share"] for r in rs),
                                 "coverage": _mean(r["coverage"] for r in rs)}
        sml_check["best"] = _best(low)[0]

    # peak fits
    fits = {}
    for f in cfg.fits:
        rs = [r for r in rows if r["fit"] == f]
        fits[f] = {"score": _mean(r["score"] for r in rs),
                   "rmse_steps_median": _median(r["rmse_steps"] for r in rs if r["coverage"] >= 0.2),
                   "bias_steps_median": _median(r["bias_steps"] for r in rs if r["coverage"] >= 0.2),
                   "coverage": _mean(r["coverage"] for r in rs)}

    return _clean({
        "cells": len(study.cells), "reconstructions": len(rows), "fit": fit,
        "seconds": study.seconds, "computed": study.computed, "reused": study.reused,
        "ranking": ranking, "family_best": fam_best, "winners": regimes, "by_kind": by_kind,
        "coverage_50pct_contrast": thresholds, "none_can": none_can, "sml_low_frequency": sml_check,
        "fits": fits, "auto": _auto_check(study, fit),
    })


def _auto_check(study: TextureStudy, fit: str) -> dict:
    """``--operator auto`` on the study's own cells, leave-one-texture-out: each cell is
    decided by a table without the cells sharing its texture (scene, kind, frequency)."""
    table = build_operator_table(study)
    texture_of = {d["key"]: (d["scene"], d["texture"], d["freq_cyc_px"]) for d in study.cells}
    picks: dict[str, int] = defaultdict(int)
    auto_s, sml_s, oracle_s, auto_g, sml_g, oracle_g = [], [], [], [], [], []
    ops = table.operators
    for i, doc in enumerate(study.cells):
        same = [k for k, t in texture_of.items() if t == texture_of[doc["key"]]]
        if len(same) == len(table.keys):
            return {}
        choice = choose_for_features(_features(doc), table, fit=fit, exclude=same)
        picks[choice.operator] += 1
        s, g = table.score[fit][i], table.good[fit][i]
        j = ops.index(choice.operator)
        auto_s.append(s[j])
        auto_g.append(g[j])
        if DEFAULT_OPERATOR in ops:
            sml_s.append(s[ops.index(DEFAULT_OPERATOR)])
            sml_g.append(g[ops.index(DEFAULT_OPERATOR)])
        oracle_s.append(s.max())
        oracle_g.append(g[int(np.argmax(s))])
    out = {"method": "leave one texture out", "picks": dict(sorted(picks.items(), key=lambda kv: -kv[1])),
           "auto_score": _mean(auto_s), "auto_good_share": _mean(auto_g),
           "oracle_score": _mean(oracle_s), "oracle_good_share": _mean(oracle_g)}
    if sml_s:
        out.update(sml_score=_mean(sml_s), sml_good_share=_mean(sml_g),
                   auto_better_cells=int(np.sum(np.array(auto_s) > np.array(sml_s) + 1e-9)),
                   auto_worse_cells=int(np.sum(np.array(auto_s) < np.array(sml_s) - 1e-9)))
    return out


# ------------------------------------------------------------------------------ writing


def _csv_text(rows: list[dict], columns: list[str]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None or (isinstance(v, float) and not math.isfinite(v))
                        else v) for k, v in r.items()})
    return buf.getvalue()


ROW_COLUMNS = ["scene", "texture", "contrast", "freq_cyc_px", "freq_rel_psf", "read_noise",
               "operator", "family", "fit", *METRICS, "feat_contrast", "feat_freq_cyc_px",
               "feat_noise", "feat_sparsity", "key"]
RANK_COLUMNS = ["rank", "operator", "family", "fit", "score", "good_share", "coverage",
                "wrong_share", "rmse_steps", "bias_steps", "confidence_auc", "wins",
                "ms_per_frame", "focus_ms_1mpx"]


def write_study(study: TextureStudy, out_dir: str | Path, analysis: dict | None = None
                ) -> dict[str, Path]:
    """Write the study's CSV, JSON, figures, summary and operator table into ``out_dir``
    (``analysis``: :func:`analyse_study` of the study, if already made)."""
    from .. import _atomic

    out = Path(out_dir)
    analysis = analysis or analyse_study(study)
    paths: dict[str, Path] = {}
    paths["csv"] = _atomic.write_text(out / "texture_study.csv",
                                      _csv_text(study.rows(), ROW_COLUMNS))
    ranking = [r for f in study.config.fits for r in analysis["ranking"][f]]
    paths["ranking_csv"] = _atomic.write_text(out / "texture_study_ranking.csv",
                                              _csv_text(ranking, RANK_COLUMNS))
    paths["json"] = _atomic.write_json(out / "texture_study.json", {
        "format": "smdinspect-texture-study", "version": 1,
        "settings": study.config.to_dict(), "fingerprint": study.config.fingerprint(),
        "metrics": {"errors": "in frame steps Δd = step_mm", "score":
                    f"good_share − {WRONG_WEIGHT:g} × coverage × wrong_share",
                    "recoverable_cutoff": RECOVERABLE, "dense_kinds": list(DENSE_KINDS)},
        "step_mm": study.config.step_mm, "analysis": analysis})
    paths["png"] = _figure(study, out / "texture_study.png", analysis)
    paths["ranking_png"] = _ranking_figure(study, out / "texture_study_ranking.png", analysis)
    paths["summary"] = _atomic.write_text(out / "texture_study.md", summary_text(study, analysis))
    paths["table"] = _atomic.write_text(out / "operator_table.json",
                                        build_operator_table(study).to_json())
    return paths


def _pct(v: Any, digits: int = 0) -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else \
        f"{100 * v:.{digits}f} %"


def _num(v: Any, fmt: str = ".2f") -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _op(name: str | None) -> str:
    return f"`{name}`" if name else f"none (< {100 * NOTHING:g} %)"


def _contrast(v: Any, lo: float) -> str:
    if v is None:
        return f"≤ {100 * lo:g} %"
    if v == "never":
        return "never (above every contrast studied)"
    return f"{100 * v:.2g} %"


def summary_text(study: TextureStudy, a: dict | None = None) -> str:
    """The written summary (Markdown) of a study."""
    a = a or analyse_study(study)
    cfg = study.config
    fit = a["fit"]
    lo = min(cfg.contrasts)
    L: list[str] = []
    add = L.append
    add("# Texture study: which focus operator, where\n")
    add(f"{a['cells']} stacks ({len(cfg.scenes)} scenes × {len(cfg.textures)} texture kinds × "
        f"{len(cfg.contrasts)} contrasts × {len(cfg.freqs_cyc_px)} frequencies × "
        f"{len(cfg.read_noises)} read-noise levels), each reconstructed with "
        f"{len(cfg.operators)} operators × {len(cfg.fits)} fits = {a['reconstructions']} "
        f"reconstructions; {cfg.size_px} px, {cfg.n_frames} frames, Δd = {cfg.step_mm:.3f} mm "
        f"(= {cfg.step_per_dof:g} depth of field), in-focus PSF σ0 = {cfg.sigma0_px:g} px, "
        f"shot noise at {cfg.photons_full_scale:g} e⁻ full scale, seed {cfg.seed}. "
        f"This run: {study.computed} cells computed in {study.seconds:.0f} s, "
        f"{study.reused} reused.\n")
    add(f"Score = share of pixels reliable and within 1 Δd − {WRONG_WEIGHT:g} × share reliable "
        "but wrong (a trusted wrong height costs more than a missing one). Errors in Δd; "
        "RMSE and bias over the reliable pixels (bias: median error). ms/frame: the whole "
        f"reconstruction per {cfg.size_px}² frame (mostly fixed overhead at this size); focus "
        "ms, 1024²: one focus measure of a 1024 × 1024 frame.\n")

    add(f"## Ranking (fit `{fit}`, mean over all cells)\n")
    add("| # | operator | family | score | right & reliable | coverage | wrong of reliable "
        "| RMSE Δd | bias Δd | conf. AUC | regimes won | ms/frame | focus ms, 1024² |")
    add("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in a["ranking"][fit]:
        add(f"| {r['rank']} | `{r['operator']}` | {r['family']} | {_num(r['score'])} | "
            f"{_pct(r['good_share'])} | {_pct(r['coverage'])} | {_pct(r['wrong_share'], 1)} | "
            f"{_num(r['rmse_steps'])} | {_num(r['bias_steps'], '+.2f')} | "
            f"{_num(r['confidence_auc'])} | {r['wins']} | {_num(r['ms_per_frame'], '.1f')} | "
            f"{_num(r['focus_ms_1mpx'], '.1f')} |")
    add("")

    add(f"## Which operator wins where (fit `{fit}`, mean over scenes and texture kinds)\n")
    add("| read noise | contrast | frequency (cyc/px) | best | its right & reliable | sml's "
        "| best pixel recovery of any operator |")
    add("|---|---|---|---|---|---|---|")
    for w in a["winners"]:
        add(f"| {_pct(w['read_noise'], 1)} | {_pct(w['contrast'], 1)} | {w['freq_cyc_px']:g} | "
            f"{_op(w['best'])} | {_pct(w['best_good_share'])} | {_pct(w['sml_good_share'])} | "
            f"{_pct(w['recoverable'])} |")
    add("")
    add("By texture kind:\n")
    add("| texture | read noise | best | its right & reliable | sml's |")
    add("|---|---|---|---|---|")
    for w in a["by_kind"]:
        add(f"| {w['texture']} | {_pct(w['read_noise'], 1)} | {_op(w['best'])} | "
            f"{_pct(w['best_good_share'])} | {_pct(w['sml_good_share'])} |")
    add("")

    add("## Contrast below which coverage falls under 50 % (dense textures: "
        f"{', '.join(DENSE_KINDS)})\n")
    add("| family (its best operator) | " + " | ".join(
        f"read noise {_pct(n, 1)}" for n in cfg.read_noises) + " |")
    add("|---|" + "---|" * len(cfg.read_noises))
    for fam, t in a["coverage_50pct_contrast"].items():
        add(f"| {fam} (`{t['operator']}`) | " + " | ".join(
            _contrast(t.get(f"{n:g}"), lo) for n in cfg.read_noises) + " |")
    add("")

    nc = a["none_can"]
    add("## Where no operator can, and what the confidence says\n")
    add(f"In {nc['cells']} of {nc['of']} stacks with dense texture ({', '.join(DENSE_KINDS)}) "
        f"no operator, with either fit, puts even {_pct(RECOVERABLE)} of the pixels within "
        "1 Δd (reliable or not): depth is not in those stacks. Contrast above which most "
        "of them are recoverable: " +
        ", ".join(f"{_contrast(nc.get(f'contrast_recoverable_{n:g}'), lo)} at read noise "
                  f"{_pct(n, 1)}" for n in cfg.read_noises) + ".\n")
    add(f"There the confidence marks on average {_pct(nc['mean_coverage_claimed'], 1)} of the "
        f"pixels reliable (the worst operator {_pct(nc['max_coverage_claimed'], 1)}; "
        f"{_pct(nc['share_of_reconstructions_over_5pct'], 1)} of those reconstructions claim "
        f"more than 5 %), and {_pct(nc['wrong_share_of_claimed'])} of what it claims is "
        f"wrong, against {_pct(nc['wrong_share_elsewhere'], 1)} in the recoverable cells. "
        f"Where it marks at least 5 % reliable, the confidence ranks right above wrong pixels "
        f"with a median ROC AUC of {_num(nc['confidence_auc_median'])}.\n")
    if nc["sparse_kinds"]:
        add(f"Sparse textures ({', '.join(nc['sparse_kinds'])}) leave most pixels blank: "
            f"the best operator marks {_pct(nc['sparse_coverage_best'])} of their pixels "
            f"reliable on average, {_pct(nc['sparse_wrong_share'], 1)} of all claims there "
            "wrong.\n")

    s = a["sml_low_frequency"]
    if DEFAULT_OPERATOR in s:
        add(f"## SML under sensor noise on low-frequency texture\n")
        add(f"At the lowest frequency ({s['freq_cyc_px']:g} cyc/px) with read noise ≥ 1 % "
            f"({s['cells']} cells), share of pixels right and reliable (raw share within 1 Δd):")
        add("")
        for op, v in s.items():
            if isinstance(v, dict):
                add(f"- `{op}`: {_pct(v['good_share'])} ({_pct(v['recoverable_share'])})")
        add("")

    add("## Peak fits\n")
    add("| fit | mean score | coverage | median RMSE Δd (cells ≥ 20 % covered) | median bias Δd |")
    add("|---|---|---|---|---|")
    for f, v in a["fits"].items():
        add(f"| `{f}` | {_num(v['score'])} | {_pct(v['coverage'])} | "
            f"{_num(v['rmse_steps_median'])} | {_num(v['bias_steps_median'], '+.3f')} |")
    add("")

    au = a["auto"]
    if au:
        add("## `--operator auto`, checked leave-one-texture-out\n")
        add(f"Each cell decided by the table without the cells of its texture: auto scores "
            f"{_num(au['auto_score'])} ({_pct(au['auto_good_share'])} right & reliable), "
            f"sml {_num(au.get('sml_score'))} ({_pct(au.get('sml_good_share'))}), the best "
            f"operator per cell (oracle) {_num(au['oracle_score'])} "
            f"({_pct(au['oracle_good_share'])}); auto beats sml in {au.get('auto_better_cells')}"
            f" cells, loses in {au.get('auto_worse_cells')}. Picks: " +
            ", ".join(f"`{k}` {v}" for k, v in au["picks"].items()) + ".\n")
    add("Files: texture_study.csv (one row per reconstruction), texture_study.json (settings "
        "and these numbers), texture_study.png, texture_study_ranking.csv/.png, "
        "operator_table.json (the table of --operator auto), cells/ (one file per finished "
        "cell; a rerun reuses them).\n")
    return "\n".join(L)


def _figure(study: TextureStudy, path: Path, a: dict) -> Path:
    """RMSE and coverage against contrast per family (best member), SML dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .. import _atomic

    cfg = study.config
    fit = a["fit"]
    rows = [r for r in study.rows() if r["fit"] == fit]
    noises = cfg.read_noises
    fig, axes = plt.subplots(2, len(noises), figsize=(4.2 * len(noises), 7.0), squeeze=False,
                             sharex=True)
    cs = list(cfg.contrasts)
    lines = [(fam, op, "-") for fam, op in a["family_best"].items()]
    if DEFAULT_OPERATOR in cfg.operators and DEFAULT_OPERATOR not in a["family_best"].values():
        lines.append(("laplacian", DEFAULT_OPERATOR, "--"))
    for col, n in enumerate(noises):
        for fam, op, style in lines:
            sel = [r for r in rows if r["operator"] == op and r["read_noise"] == n]
            cov = [_mean(r["coverage"] for r in sel if r["contrast"] == c) for c in cs]
            rmse = [_median(r["rmse_steps"] for r in sel if r["contrast"] == c
                            and r["coverage"] >= 0.05) for c in cs]
            label = f"{fam} ({op})" if style == "-" else f"{op} (default)"
            kw = dict(color=_COLOURS.get(fam, "k") if style == "-" else "k", ls=style,
                      marker="o", ms=3, lw=1.4, label=label)
            axes[0, col].plot(cs, rmse, **kw)
            axes[1, col].plot(cs, cov, **kw)
        axes[0, col].set_title(f"read noise {100 * n:g} % of full scale")
        axes[1, col].axhline(0.5, color="0.6", lw=0.8, ls=":")
        for row in (0, 1):
            axes[row, col].set_xscale("log")
            axes[row, col].grid(True, which="both", alpha=0.3)
        axes[0, col].set_ylim(0, 1.0)
        axes[1, col].set_ylim(0, 1.02)
        axes[1, col].set_xlabel("texture RMS contrast")
    axes[0, 0].set_ylabel("RMSE of reliable pixels (Δd), median")
    axes[1, 0].set_ylabel("coverage (reliable share), mean")
    axes[1, 0].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Texture study: {len(study.cells)} stacks, fit {fit}, mean over "
                 f"{len(cfg.scenes)} scenes, {len(cfg.textures)} kinds, "
                 f"{len(cfg.freqs_cyc_px)} frequencies", fontsize=10)
    fig.tight_layout()
    with _atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def _ranking_figure(study: TextureStudy, path: Path, a: dict) -> Path:
    """Heat map: operators (ranked) × (read noise, contrast), mean score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .. import _atomic

    cfg = study.config
    fit = a["fit"]
    ops = [r["operator"] for r in a["ranking"][fit]]
    cols = [(n, c) for n in cfg.read_noises for c in cfg.contrasts]
    groups = _by([r for r in study.rows() if r["fit"] == fit], "operator", "read_noise", "contrast")
    m = np.array([[_mean(r["score"] for r in groups.get((op, n, c), [])) for n, c in cols]
                  for op in ops])
    fig, ax = plt.subplots(figsize=(1.0 + 0.55 * len(cols), 1.2 + 0.3 * len(ops)))
    im = ax.imshow(m, cmap="RdYlGn", vmin=-0.5, vmax=1.0, aspect="auto")
    ax.set_yticks(range(len(ops)), [f"{i + 1}. {op}" for i, op in enumerate(ops)], fontsize=8)
    ax.set_xticks(range(len(cols)), [f"{100 * c:g}%" for _, c in cols], fontsize=7, rotation=90)
    for k in range(1, len(cfg.read_noises)):
        ax.axvline(k * len(cfg.contrasts) - 0.5, color="k", lw=1)
    for k, n in enumerate(cfg.read_noises):
        ax.text((k + 0.5) * len(cfg.contrasts) - 0.5, -1.0, f"read noise {100 * n:g} %",
                ha="center", va="bottom", fontsize=8)
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            if math.isfinite(m[i, j]):
                ax.text(j, i, str(int(round(100 * m[i, j]))), ha="center", va="center",
                        fontsize=5.5)
    ax.set_xlabel("texture contrast")
    fig.colorbar(im, ax=ax, fraction=0.03, label="score (right & reliable − 3 × wrong)")
    fig.suptitle(f"Operators ranked by mean score (fit {fit}); cells: score × 100 per read "
                 "noise and contrast", fontsize=9)
    fig.tight_layout()
    with _atomic.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
