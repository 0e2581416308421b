"""Gauge R&R by the ANOVA method (AIAG MSA, 4th edition): variance components.

Pure functions on arrays. A measurement ``y`` of part ``i`` by operator ``j`` in trial
``k`` is modelled as ``y = μ + P_i + O_j + (PO)_ij + ε_ijk`` with independent random
effects; the mean squares of the ANOVA table give the variance components

=====================  ====================================================================
repeatability (EV)     ``σ²_e = MS_e``
operator (AV)          ``σ²_o = (MS_o − MS_po) / (p·r)``
interaction            ``σ²_po = (MS_po − MS_e) / r``
part (PV)              ``σ²_p = (MS_p − MS_po) / (o·r)``
=====================  ====================================================================

(negative estimates are set to 0). Reproducibility is ``σ²_o + σ²_po``, the gauge
``σ²_GRR = σ²_e + σ²_o + σ²_po`` and the total ``σ²_TV = σ²_GRR + σ²_p``. When the
interaction's F test is not significant (``p > interaction_alpha``, Minitab's rule) the
interaction is pooled into the error and the reduced model is used. With one part (a
single joint) or one operator the design is a one-way layout (the other factor's terms
vanish), which may be unbalanced.

Figures of merit:

* ``%GR&R`` against the tolerance ``T = USL − LSL``: ``k·σ_GRR / T × 100`` with
  ``k = 6`` (AIAG 4th edition; older editions used 5.15);
* ``%GR&R`` of the study variation: ``σ_GRR / σ_TV × 100``;
* number of distinct categories ``ndc = ⌊1.41 · σ_p / σ_GRR⌋`` (AIAG: 5 or more).

AIAG's acceptance: ``≤ 10 %`` acceptable, ``10–30 %`` marginal, ``> 30 %``
unacceptable (:func:`rating`).

Examples
--------
>>> import numpy as np
>>> y = np.array([1.00, 1.02, 0.98, 1.01, 0.99])
>>> g = gauge_rr(y, tolerance=0.5)
>>> round(g.sigma_repeatability, 4), round(g.pct_tolerance, 2)
(0.0158, 18.97)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..errors import InputError

__all__ = [
    "ACCEPTABLE_PCT",
    "MARGINAL_PCT",
    "AnovaTerm",
    "GaugeRR",
    "gauge_rr",
    "rating",
]

#: AIAG MSA limits of %GR&R: up to 10 % acceptable, up to 30 % marginal.
ACCEPTABLE_PCT = 10.0
MARGINAL_PCT = 30.0


def rating(pct: float) -> str:
    """AIAG rating of a %GR&R: ``"acceptable"`` (≤ 10 %), ``"marginal"`` (≤ 30 %),
    ``"unacceptable"``; ``"n/a"`` for NaN."""
    if not math.isfinite(pct):
        return "n/a"
    if pct <= ACCEPTABLE_PCT:
        return "acceptable"
    return "marginal" if pct <= MARGINAL_PCT else "unacceptable"


@dataclass(frozen=True)
class AnovaTerm:
    """One row of the ANOVA table (``f`` and ``p`` NaN for the error row)."""

    source: str
    df: int
    ss: float
    ms: float
    f: float = math.nan
    p: float = math.nan

    def to_dict(self) -> dict:
        return {"source": self.source, "df": self.df, "ss": _j(self.ss), "ms": _j(self.ms),
                "f": _j(self.f), "p": _j(self.p)}


@dataclass(frozen=True)
class GaugeRR:
    """Variance components and figures of merit of one gauge study.

    Variances are in the squared unit of the measurements, σ in their unit. A component
    the design cannot estimate is NaN (the operator terms with one operator, the part
    term with one part) and counts as 0 in the sums.

    Attributes
    ----------
    method : str
        ``"crossed"`` (parts × operators, two-way ANOVA), ``"one-way"`` or ``"none"``
        (fewer than 2 values).
    n, n_parts, n_operators : int
        Values used, distinct parts and operators among them.
    n_trials : int
        Trials per part and operator (crossed), else the largest group's size.
    mean : float
    var_repeatability, var_operator, var_interaction, var_part : float
    interaction_pooled : bool
        The interaction was not significant and was pooled into the error.
    tolerance : float
        ``USL − LSL`` (NaN: none).
    k_sigma : float
        Spread of the gauge in σ (6).
    anova : tuple of AnovaTerm
    """

    method: str
    n: int
    n_parts: int
    n_operators: int
    n_trials: int
    mean: float
    var_repeatability: float
    var_operator: float = math.nan
    var_interaction: float = math.nan
    var_part: float = math.nan
    interaction_pooled: bool = False
    tolerance: float = math.nan
    k_sigma: float = 6.0
    anova: tuple[AnovaTerm, ...] = field(default=())

    @property
    def var_reproducibility(self) -> float:
        """``σ²_o + σ²_po`` (NaN with one operator)."""
        if not math.isfinite(self.var_operator):
            return math.nan
        return self.var_operator + _z(self.var_interaction)

    @property
    def var_grr(self) -> float:
        return self.var_repeatability + _z(self.var_reproducibility)

    @property
    def sigma_repeatability(self) -> float:
        """EV: the repeatability σ."""
        return _sqrt(self.var_repeatability)

    @property
    def sigma_reproducibility(self) -> float:
        """AV (with the interaction): the reproducibility σ."""
        return _sqrt(self.var_reproducibility)

    @property
    def sigma_grr(self) -> float:
        return _sqrt(self.var_grr)

    @property
    def sigma_part(self) -> float:
        """PV: the part-to-part σ."""
        return _sqrt(self.var_part)

    @property
    def sigma_total(self) -> float:
        """TV: ``√(σ²_GRR + σ²_p)``."""
        return _sqrt(self.var_grr + _z(self.var_part))

    @property
    def pct_tolerance(self) -> float:
        """``k·σ_GRR / tolerance × 100`` (NaN without a tolerance)."""
        t = self.tolerance
        if not (math.isfinite(t) and t > 0):
            return math.nan
        return 100.0 * self.k_sigma * self.sigma_grr / t

    @property
    def pct_study(self) -> float:
        """``σ_GRR / σ_TV × 100`` (NaN with one part)."""
        if not math.isfinite(self.var_part) or not self.sigma_total > 0:
            return math.nan
        return 100.0 * self.sigma_grr / self.sigma_total

    @property
    def ndc(self) -> float:
        """``⌊1.41·σ_p/σ_GRR⌋`` (NaN with one part or a perfect gauge)."""
        if not math.isfinite(self.var_part) or not self.sigma_grr > 0:
            return math.nan
        return float(math.floor(1.41 * self.sigma_part / self.sigma_grr))

    def to_dict(self) -> dict:
        return {
            "method": self.method, "n": self.n, "n_parts": self.n_parts,
            "n_operators": self.n_operators, "n_trials": self.n_trials, "mean": _j(self.mean),
            "sigma_repeatability": _j(self.sigma_repeatability),
            "sigma_reproducibility": _j(self.sigma_reproducibility),
            "sigma_operator": _j(_sqrt(self.var_operator)),
            "sigma_interaction": _j(_sqrt(self.var_interaction)),
            "sigma_grr": _j(self.sigma_grr), "sigma_part": _j(self.sigma_part),
            "sigma_total": _j(self.sigma_total), "tolerance": _j(self.tolerance),
            "k_sigma": self.k_sigma, "pct_tolerance": _j(self.pct_tolerance),
            "pct_study": _j(self.pct_study), "ndc": _j(self.ndc),
            "interaction_pooled": self.interaction_pooled,
            "anova": [t.to_dict() for t in self.anova],
        }


def _z(v: float) -> float:
    return v if math.isfinite(v) else 0.0


def _sqrt(v: float) -> float:
    return math.sqrt(v) if math.isfinite(v) and v >= 0 else math.nan


def _j(v: float):
    return float(v) if v is not None and math.isfinite(v) else None


def _labels(x, n: int, name: str) -> np.ndarray:
    if x is None:
        return np.zeros(n, dtype=np.int64)
    a = np.asarray(x)
    if a.shape != (n,):
        raise InputError(f"{name} must give one label per value ({n}); got shape {a.shape}")
    return np.unique(a, return_inverse=True)[1].reshape(n)


def gauge_rr(values, *, parts=None, operators=None, tolerance: float | None = None,
             k_sigma: float = 6.0, interaction_alpha: float = 0.05) -> GaugeRR:
    """Variance components of a gauge study (AIAG ANOVA method).

    Parameters
    ----------
    values : (n,) array_like
        The measurements; NaN values are left out.
    parts, operators : (n,) array_like, optional
        The part and the operator (or fixturing) of each value. Default: one part, one
        operator (every value repeats the same measurement).
    tolerance : float, optional
        ``USL − LSL`` of the characteristic, for :attr:`GaugeRR.pct_tolerance`.
    k_sigma : float
        Gauge spread in σ for %GR&R (6: AIAG 4th edition; 5.15: 3rd).
    interaction_alpha : float
        The part × operator interaction is pooled into the error when its F test's
        p-value is above this (0 never pools, 1 always).

    Returns
    -------
    GaugeRR

    Raises
    ------
    InputError
        Bad shapes or options, or several parts and several operators that are not a
        balanced crossed design (every part measured the same number of times by every
        operator).
    """
    y = np.asarray(values, dtype=np.float64)
    if y.ndim != 1:
        raise InputError(f"values must be one-dimensional; got shape {y.shape}")
    n_all = y.size
    pi, oi = _labels(parts, n_all, "parts"), _labels(operators, n_all, "operators")
    if not (math.isfinite(k_sigma) and k_sigma > 0):
        raise InputError(f"k_sigma must be > 0; got {k_sigma}")
    if not 0.0 <= interaction_alpha <= 1.0:
        raise InputError(f"interaction_alpha must be in [0, 1]; got {interaction_alpha}")
    tol = math.nan if tolerance is None else float(tolerance)
    if math.isfinite(tol) and tol <= 0:
        raise InputError(f"tolerance must be > 0; got {tolerance}")
    ok = np.isfinite(y)
    y, pi, oi = y[ok], pi[ok], oi[ok]
    pi = np.unique(pi, return_inverse=True)[1].reshape(-1)
    oi = np.unique(oi, return_inverse=True)[1].reshape(-1)
    n = y.size
    p = int(pi.max()) + 1 if n else 0
    o = int(oi.max()) + 1 if n else 0
    common = dict(n=n, n_parts=p, n_operators=o, tolerance=tol, k_sigma=float(k_sigma))
    none = GaugeRR(method="none", n_trials=int(n > 0), mean=float(y.mean()) if n else math.nan,
                   var_repeatability=math.nan, **common)
    if n < 2:
        return none
    if p > 1 and o > 1:
        return _crossed(y, pi, oi, p, o, interaction_alpha, common)
    groups = pi if p > 1 else oi
    if n - (int(groups.max()) + 1) < 1:
        return none  # no replicate: nothing to estimate the error from
    var_e, var_g, terms, size = _one_way(y, groups, "part" if p > 1 else "operator")
    return GaugeRR(method="one-way", n_trials=size, mean=float(y.mean()),
                   var_repeatability=var_e, var_operator=var_g if o > 1 else math.nan,
                   var_part=var_g if p > 1 else math.nan, anova=terms, **common)


def _one_way(y: np.ndarray, groups: np.ndarray, name: str):
    """Random-effects one-way ANOVA (unbalanced allowed): (σ²_e, σ²_group, terms, max n_i)."""
    a = int(groups.max()) + 1
    n = y.size
    counts = np.bincount(groups, minlength=a)
    if a == 1:
        var_e = float(np.var(y, ddof=1))
        return var_e, math.nan, (AnovaTerm("repeatability", n - 1, var_e * (n - 1), var_e),), n
    samples = [y[groups == i] for i in range(a)]
    means = np.array([s.mean() for s in samples])
    ss_b = float(np.sum(counts * (means - y.mean()) ** 2))
    ss_w = float(sum(np.sum((s - s.mean()) ** 2) for s in samples))
    df_b, df_w = a - 1, n - a
    ms_b, ms_w = ss_b / df_b, ss_w / df_w
    f, pval = (stats.f_oneway(*samples) if ms_w > 0 and all(c >= 1 for c in counts)
               else (math.nan, math.nan))
    n0 = (n - float(np.sum(counts ** 2)) / n) / df_b  # mean group size (unbalanced)
    var_g = max(0.0, (ms_b - ms_w) / n0)
    terms = (AnovaTerm(name, df_b, ss_b, ms_b, float(f), float(pval)),
             AnovaTerm("repeatability", df_w, ss_w, ms_w))
    return ms_w, var_g, terms, int(counts.max())


def _crossed(y, pi, oi, p: int, o: int, alpha: float, common: dict) -> GaugeRR:
    cells = np.zeros((p, o), dtype=np.int64)
    np.add.at(cells, (pi, oi), 1)
    r = int(cells.flat[0])
    if not np.all(cells == r):
        raise InputError("a study of several parts by several operators must be balanced "
                         f"(every part measured equally often by every operator); got "
                         f"{int(cells.min())} to {int(cells.max())} values per part and "
                         "operator")
    x = np.empty((p, o, r))
    order = np.lexsort((oi, pi))
    x[:] = y[order].reshape(p, o, r)
    grand = x.mean()
    mp, mo, mpo = x.mean(axis=(1, 2)), x.mean(axis=(0, 2)), x.mean(axis=2)
    ss_p = o * r * float(np.sum((mp - grand) ** 2))
    ss_o = p * r * float(np.sum((mo - grand) ** 2))
    ss_po = r * float(np.sum((mpo - mp[:, None] - mo[None, :] + grand) ** 2))
    ss_e = float(np.sum((x - mpo[:, :, None]) ** 2))
    df_p, df_o, df_po, df_e = p - 1, o - 1, (p - 1) * (o - 1), p * o * (r - 1)
    ms_p, ms_o, ms_po = ss_p / df_p, ss_o / df_o, ss_po / df_po
    ms_e = ss_e / df_e if df_e else math.nan

    def test(ms, ms_den, df_num, df_den):
        if not (math.isfinite(ms_den) and ms_den > 0):
            return math.nan, math.nan
        f = ms / ms_den
        return f, float(stats.f.sf(f, df_num, df_den))

    f_po, p_po = test(ms_po, ms_e, df_po, df_e)
    pooled = df_e == 0 or not (math.isfinite(p_po) and p_po <= alpha)
    if pooled:  # reduced model: part + operator + error (the interaction in the error)
        df_err = df_po + df_e
        ms_err = (ss_po + ss_e) / df_err
        f_p, p_p = test(ms_p, ms_err, df_p, df_err)
        f_o, p_o = test(ms_o, ms_err, df_o, df_err)
        terms = (AnovaTerm("part", df_p, ss_p, ms_p, f_p, p_p),
                 AnovaTerm("operator", df_o, ss_o, ms_o, f_o, p_o),
                 AnovaTerm("repeatability", df_err, ss_po + ss_e, ms_err))
        var_e, var_po = ms_err, 0.0
        var_o = max(0.0, (ms_o - ms_err) / (p * r))
        var_p = max(0.0, (ms_p - ms_err) / (o * r))
    else:  # full model: parts and operators tested against the interaction
        f_p, p_p = test(ms_p, ms_po, df_p, df_po)
        f_o, p_o = test(ms_o, ms_po, df_o, df_po)
        terms = (AnovaTerm("part", df_p, ss_p, ms_p, f_p, p_p),
                 AnovaTerm("operator", df_o, ss_o, ms_o, f_o, p_o),
                 AnovaTerm("part x operator", df_po, ss_po, ms_po, f_po, p_po),
                 AnovaTerm("repeatability", df_e, ss_e, ms_e))
        var_e = ms_e
        var_po = max(0.0, (ms_po - ms_e) / r)
        var_o = max(0.0, (ms_o - ms_po) / (p * r))
        var_p = max(0.0, (ms_p - ms_po) / (o * r))
    return GaugeRR(method="crossed", n_trials=r, mean=float(grand), var_repeatability=var_e,
                   var_operator=var_o, var_interaction=var_po, var_part=var_p,
                   interaction_pooled=pooled, anova=terms, **common)
