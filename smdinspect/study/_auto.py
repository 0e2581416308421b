"""``--operator auto``: pick the focus operator from the texture study's table.

The table (``operator_table.json``, shipped in this package and rewritten by every
``smdinspect study texture`` run into its ``--out``) holds, for every study cell, the
texture features measured on its stack (:mod:`smdinspect.study._features`) and every
operator's **score** there: the share of pixels marked reliable and within 1 Δd of the
truth, minus 3 × the share marked reliable but wrong. For a new stack the same features
are measured; the ``k`` study cells nearest in feature space (log contrast, log frequency,
log noise, sparsity; each scaled by its spread over the table) vote, weighted by
``1 / (0.25 + distance)``; the operator with the best expected score wins. Operators
within ``margin`` (0.02) of the best count as equal: SML, the default, if it is among
them, else the one with the cheapest focus measure (timed by the study).

Regenerate the shipped table after changing the focus measures, the confidence or the
renderer::

    smdinspect study texture --out study/
    cp study/operator_table.json smdinspect/study/operator_table.json
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import InputError
from ._features import TextureFeatures, stack_features

__all__ = ["OperatorChoice", "OperatorTable", "TABLE_PATH", "choose_operator",
           "load_operator_table"]

log = logging.getLogger(__name__)

#: The table shipped with smdinspect (package data).
TABLE_PATH = Path(__file__).with_name("operator_table.json")
TABLE_FORMAT = "smdinspect-operator-table"
TABLE_VERSION = 1
FEATURE_NAMES = ("log10_contrast", "log10_freq_cyc_px", "log10_noise", "sparsity")
#: Operator kept when nothing beats it by the margin.
DEFAULT_OPERATOR = "sml"
#: Feature-space distance beyond which a stack is outside the study's range.
FAR = 1.5


@dataclass(frozen=True, eq=False)
class OperatorTable:
    """The study's per-cell features and operator scores (see :func:`load_operator_table`).

    Attributes
    ----------
    operators : tuple of str
    keys : tuple of str
        One per study cell.
    features : (n_cells, 4) float64
        :meth:`TextureFeatures.vector` of every cell's stack.
    scale : (4,) float64
        Spread of each feature over the cells (distances are measured in it).
    score, good : dict fit → (n_cells, n_operators) float64
        Score and good share (reliable and within 1 Δd) of every operator in every cell.
    meta : dict
        How the table was made (settings, seed, date).
    """

    operators: tuple[str, ...]
    keys: tuple[str, ...]
    features: np.ndarray
    scale: np.ndarray
    score: dict[str, np.ndarray]
    good: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def fits(self) -> tuple[str, ...]:
        return tuple(self.score)

    def to_json(self) -> str:
        """:meth:`to_doc` as compact JSON text, one study cell a line."""
        doc = self.to_doc()
        cells = doc.pop("cells")
        head = json.dumps(doc, ensure_ascii=False, separators=(",", ":"))
        body = ",\n".join(json.dumps(c, separators=(",", ":")) for c in cells)
        return head[:-1] + ',"cells":[\n' + body + "\n]}\n"

    def to_doc(self) -> dict:
        """The JSON document of the table (scores in thousandths)."""

        def milli(a: np.ndarray) -> list[int]:
            return [int(v) for v in np.rint(1000 * np.nan_to_num(a, nan=0.0))]

        return {
            "format": TABLE_FORMAT, "version": TABLE_VERSION, "meta": self.meta,
            "feature_names": list(FEATURE_NAMES), "scale": [round(float(v), 5) for v in self.scale],
            "operators": list(self.operators), "fits": list(self.fits),
            "cells": [{"key": k, "features": [round(float(v), 4) for v in self.features[i]],
                       **{f"score_{fit}": milli(self.score[fit][i]) for fit in self.fits},
                       **{f"good_{fit}": milli(self.good[fit][i]) for fit in self.fits}}
                      for i, k in enumerate(self.keys)],
        }

    @classmethod
    def from_doc(cls, doc: Any, source: str = "") -> "OperatorTable":
        where = source or "operator table"
        if not isinstance(doc, dict) or doc.get("format") != TABLE_FORMAT:
            raise InputError(f"{where} is not an smdinspect operator table")
        if doc.get("version") != TABLE_VERSION:
            raise InputError(f"{where}: unsupported version {doc.get('version')!r}; "
                             f"this smdinspect reads version {TABLE_VERSION}")
        try:
            ops = tuple(str(o) for o in doc["operators"])
            fits = tuple(str(f) for f in doc["fits"])
            cells = doc["cells"]
            keys = tuple(str(c["key"]) for c in cells)
            feats = np.array([c["features"] for c in cells], np.float64).reshape(len(cells), -1)
            score = {f: np.array([c[f"score_{f}"] for c in cells], np.float64) / 1000.0
                     for f in fits}
            good = {f: np.array([c[f"good_{f}"] for c in cells], np.float64) / 1000.0
                    for f in fits}
            scale = np.array(doc["scale"], np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{where} is damaged ({type(exc).__name__}: {exc})") from None
        if not keys or feats.shape[1] != len(FEATURE_NAMES) or scale.shape != (len(FEATURE_NAMES),) \
                or any(a.shape != (len(keys), len(ops)) for a in (*score.values(), *good.values())):
            raise InputError(f"{where} is damaged (inconsistent array sizes)")
        return cls(ops, keys, feats, np.maximum(scale, 1e-3), score, good,
                   meta=dict(doc.get("meta") or {}), source=source)


def load_operator_table(path: str | Path | None = None) -> OperatorTable:
    """Read an operator table (default: the one shipped with smdinspect)."""
    p = TABLE_PATH if path is None else Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        hint = (" (regenerate it: smdinspect study texture --out study/ && cp "
                "study/operator_table.json " f"{TABLE_PATH})") if path is None else ""
        raise InputError(f"operator table not found: {p}{hint}") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the operator table {p}: {exc}") from None
    return OperatorTable.from_doc(doc, source=str(p))


@dataclass(frozen=True)
class OperatorChoice:
    """The outcome of :func:`choose_operator`.

    ``expected_*`` are the neighbouring study cells' weighted means: ``good`` the share of
    pixels reliable and within 1 Δd, ``score`` good − 3 × reliable-but-wrong.
    """

    operator: str
    fit: str
    features: TextureFeatures
    expected_good: float
    expected_score: float
    default_good: float
    default_score: float
    neighbours: tuple[tuple[str, float], ...]
    runner_up: tuple[tuple[str, float], ...]
    table: str

    def explain(self) -> str:
        """One paragraph: what was measured, what the study says, what was picked."""
        near = ", ".join(f"{k} (d={d:.2f})" for k, d in self.neighbours[:3])
        alt = ", ".join(f"{op} {s:+.2f}" for op, s in self.runner_up[:3])
        text = (f"--operator auto: measured {self.features.describe()}; nearest texture-study "
                f"cells {near}. There the study expects {self.operator} to mark "
                f"{100 * self.expected_good:.0f} % of pixels reliable and right (score "
                f"{self.expected_score:+.2f}) against {100 * self.default_good:.0f} % "
                f"({self.default_score:+.2f}) for {DEFAULT_OPERATOR}, the default "
                f"[scores: {alt}] -> {self.operator}")
        if self.neighbours and self.neighbours[0][1] > FAR:
            text += (f". The stack lies outside the study's range (nearest cell at distance "
                     f"{self.neighbours[0][1]:.1f} > {FAR:g}): the pick is an extrapolation")
        if self.expected_good < 0.2:
            text += (". The nearest study textures are hard for every operator: expect low "
                     "coverage (the confidence masks what cannot be measured)")
        return text

    def to_dict(self) -> dict:
        return {"operator": self.operator, "fit": self.fit, "features": self.features.to_dict(),
                "expected_good_share": round(self.expected_good, 4),
                "expected_score": round(self.expected_score, 4),
                f"{DEFAULT_OPERATOR}_expected_good_share": round(self.default_good, 4),
                f"{DEFAULT_OPERATOR}_expected_score": round(self.default_score, 4),
                "nearest_cells": [{"key": k, "distance": round(d, 4)} for k, d in self.neighbours],
                "best_scores": {op: round(s, 4) for op, s in self.runner_up},
                "table": self.table, "explanation": self.explain()}


def choose_for_features(features: TextureFeatures, table: OperatorTable, *, fit: str = "power",
                        k: int = 6, margin: float = 0.02,
                        exclude: Sequence[str] = ()) -> OperatorChoice:
    """The operator the ``k`` study cells nearest to ``features`` score best
    (``exclude``: cell keys left out, for leave-one-out checks)."""
    if not isinstance(table, OperatorTable):
        raise InputError(f"table must be an OperatorTable; got {type(table).__name__}")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise InputError(f"k must be an integer >= 1; got {k!r}")
    use_fit = fit if fit in table.score else table.fits[0]
    keep = np.array([key not in set(exclude) for key in table.keys])
    if not keep.any():
        raise InputError("the operator table has no cells left to choose from")
    idx = np.flatnonzero(keep)
    d = np.sqrt((((table.features[idx] - features.vector()) / table.scale) ** 2).sum(axis=1))
    order = np.argsort(d, kind="stable")[: min(k, idx.size)]
    near, dist = idx[order], d[order]
    w = 1.0 / (0.25 + dist)
    w /= w.sum()
    score = w @ table.score[use_fit][near]
    good = w @ table.good[use_fit][near]
    best = int(np.argmax(score))
    ops = table.operators
    j = ops.index(DEFAULT_OPERATOR) if DEFAULT_OPERATOR in ops else best
    close = [i for i in range(len(ops)) if score[best] - score[i] <= margin]
    cost = table.meta.get("focus_ms_1mpx") or {}
    # within the margin: the default if it is there, else the cheapest focus measure
    pick = j if j in close else min(close, key=lambda i: (cost.get(ops[i], math.inf), -score[i]))
    ranked = np.argsort(-score, kind="stable")
    return OperatorChoice(
        operator=ops[pick], fit=use_fit, features=features,
        expected_good=float(good[pick]), expected_score=float(score[pick]),
        default_good=float(good[j]), default_score=float(score[j]),
        neighbours=tuple((table.keys[i], float(di)) for i, di in zip(near, dist)),
        runner_up=tuple((ops[i], float(score[i])) for i in ranked[:5]),
        table=table.source or "in memory")


def choose_operator(stack, *, fit: str = "power", table: OperatorTable | str | Path | None = None,
                    k: int = 6) -> OperatorChoice:
    """Pick the focus operator for ``stack`` from a quick texture analysis.

    Parameters
    ----------
    stack : FocalStack or sequence of (H, W) / (H, W, 3) frames
        Up to :data:`~smdinspect.study._features.MAX_FRAMES` frames are decoded.
    fit : str
        The peak fit the reconstruction will use (the table's ``power`` scores stand in
        for fits the study did not run).
    table : OperatorTable or path, optional
        Default the table shipped with smdinspect.
    k : int
        Study cells that vote.

    Returns
    -------
    OperatorChoice
        ``.operator`` to pass to :class:`smdinspect.sff.FocusConfig`; ``.explain()`` says why.
    """
    if not isinstance(table, OperatorTable):
        table = load_operator_table(table)
    features = stack_features(stack)
    choice = choose_for_features(features, table, fit=fit, k=k)
    log.info("%s", choice.explain())
    return choice

