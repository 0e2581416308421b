"""Statistical process control across boards: capability, control charts, run rules.

Pure functions on arrays (no files; the reader and writers are in :mod:`._spc_report`).

* **Capability** against a band ``[lsl, usl]``: ``Cp = (usl − lsl) / 6σ_within`` and
  ``Cpk = min(usl − μ, μ − lsl) / 3σ_within`` with the short-term σ of the chart
  (individuals: ``MR̄ / d2(2)``; X̄–R: ``R̄ / d2(n)``), and the long-term ``Pp``, ``Ppk``
  with the overall sample σ (``ddof=1``).
* **Control charts.** Individuals (I-MR) for one joint (one value per board), X̄–R for a
  package/joint type (the subgroup is that type's joints on one board). Limits come
  from a baseline (the first boards, Phase I) and are applied to every board.
* **Run rules** (Western Electric / Nelson), each reported at the point that completes
  the run: see :data:`RULES`.

Examples
--------
>>> import numpy as np
>>> cap = capability(np.array([0.20, 0.22, 0.21, 0.23, 0.19]), lsl=0.10, usl=0.30)
>>> round(cap.cpk, 3)
1.504
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import InputError

__all__ = [
    "RULES",
    "Capability",
    "ControlChart",
    "RuleHit",
    "capability",
    "individuals_chart",
    "run_rules",
    "xbar_r_chart",
]

#: Rule number → what it detects (Nelson's numbering; 1, 5, 6 are Western Electric's
#: zone rules A, B, C, 2 its run rule with nine points).
RULES = {
    1: "one point beyond 3σ",
    2: "nine points in a row on one side of the centre line",
    3: "six points in a row steadily increasing or decreasing",
    4: "fourteen points in a row alternating up and down",
    5: "two of three points in a row beyond 2σ on the same side",
    6: "four of five points in a row beyond 1σ on the same side",
    7: "fifteen points in a row within 1σ (limits too wide / stratified data)",
    8: "eight points in a row beyond 1σ on both sides (mixture)",
}

#: Control-chart constants for subgroups of n = 2..10 (ASTM / Montgomery tables).
_D2 = {2: 1.128, 3: 1.693, 4: 2.059, 5: 2.326, 6: 2.534, 7: 2.704, 8: 2.847, 9: 2.970,
       10: 3.078}
_A2 = {2: 1.880, 3: 1.023, 4: 0.729, 5: 0.577, 6: 0.483, 7: 0.419, 8: 0.373, 9: 0.337,
       10: 0.308}
_D3 = {2: 0.0, 3: 0.0, 4: 0.0, 5: 0.0, 6: 0.0, 7: 0.076, 8: 0.136, 9: 0.184, 10: 0.223}
_D4 = {2: 3.267, 3: 2.574, 4: 2.282, 5: 2.114, 6: 2.004, 7: 1.924, 8: 1.864, 9: 1.816,
       10: 1.777}
#: Largest subgroup for which an X̄–R chart is drawn (the R chart's constants).
MAX_SUBGROUP = 10


@dataclass(frozen=True)
class Capability:
    """Mean, spread and capability of one series against its band.

    Values that cannot be computed (no band, fewer than 2 values, zero spread) are NaN.
    """

    n: int
    mean: float
    sigma: float
    sigma_within: float
    lsl: float
    usl: float
    cp: float
    cpk: float
    pp: float
    ppk: float


@dataclass(frozen=True)
class RuleHit:
    """A run rule that fired: ``rule`` (see :data:`RULES`) completed at point ``index``."""

    index: int
    rule: int

    @property
    def text(self) -> str:
        return RULES[self.rule]


@dataclass(frozen=True)
class ControlChart:
    """Limits of a control chart and the run rules that fired.

    Attributes
    ----------
    kind : str
        ``"individuals"`` or ``"xbar-r"``.
    values : (n,) float64
        The plotted statistic per board (the value, or the subgroup mean); NaN when the
        board has none.
    cl, ucl, lcl : float
        Centre line and 3σ limits of ``values`` (NaN when the baseline is too short).
    sigma : float
        Short-term σ of one value (``MR̄/d2`` or ``R̄/d2``).
    sigma_stat : float
        σ of the plotted statistic (``sigma`` for individuals, ``sigma/√n`` for X̄).
    spread : (n,) float64
        Moving ranges (individuals; the first is NaN) or subgroup ranges (X̄–R).
    spread_cl, spread_ucl, spread_lcl : float
        Centre line and limits of the spread chart.
    baseline : int
        Number of boards the limits were computed from (the first ones).
    subgroup : int
        Values per subgroup (1 for individuals).
    hits : tuple of RuleHit
        Run rules that fired on ``values`` (plus rule 1 on the spread chart is not
        reported: a range beyond its limit shows as a point beyond 3σ on the values).
    """

    kind: str
    values: np.ndarray
    cl: float
    ucl: float
    lcl: float
    sigma: float
    sigma_stat: float
    spread: np.ndarray
    spread_cl: float
    spread_ucl: float
    spread_lcl: float
    baseline: int
    subgroup: int
    hits: tuple[RuleHit, ...] = field(default=())

    @property
    def first_hit(self) -> int | None:
        """Index of the first point where any rule fired, or ``None``."""
        return min((h.index for h in self.hits), default=None)


def _as_series(values, name: str = "values") -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1:
        raise InputError(f"{name} must be one-dimensional (one value per board); got shape "
                         f"{x.shape}")
    return x


def _nan(x) -> float:
    return float(x) if x is not None and math.isfinite(float(x)) else math.nan


def capability(values, *, lsl: float | None = None, usl: float | None = None,
               sigma_within: float | None = None) -> Capability:
    """Mean, σ, Cp/Cpk and Pp/Ppk of ``values`` against the band ``[lsl, usl]``.

    Parameters
    ----------
    values : (n,) array_like
        One value per board; NaN values are left out.
    lsl, usl : float, optional
        Lower and upper specification limits. With one of them only, Cp and Pp are NaN
        and Cpk/Ppk are one-sided.
    sigma_within : float, optional
        Short-term σ (from a control chart). Default: ``MR̄ / 1.128`` of ``values`` in
        their order (the individuals chart's estimate).

    Returns
    -------
    Capability
    """
    x = _as_series(values)
    x = x[np.isfinite(x)]
    lsl, usl = _nan(lsl), _nan(usl)
    if math.isfinite(lsl) and math.isfinite(usl) and usl < lsl:
        raise InputError(f"usl must be >= lsl; got lsl={lsl}, usl={usl}")
    n = int(x.size)
    mean = float(x.mean()) if n else math.nan
    sigma = float(x.std(ddof=1)) if n >= 2 else math.nan
    if sigma_within is None:
        sigma_within = float(np.mean(np.abs(np.diff(x)))) / _D2[2] if n >= 2 else math.nan
    sw = _nan(sigma_within)

    def cp_of(s: float) -> float:
        if not (math.isfinite(lsl) and math.isfinite(usl)) or not s > 0:
            return math.nan
        return (usl - lsl) / (6.0 * s)

    def cpk_of(s: float) -> float:
        if not s > 0 or not math.isfinite(mean):
            return math.nan
        sides = [d for d in ((usl - mean) if math.isfinite(usl) else math.nan,
                             (mean - lsl) if math.isfinite(lsl) else math.nan)
                 if math.isfinite(d)]
        return min(sides) / (3.0 * s) if sides else math.nan

    return Capability(n=n, mean=mean, sigma=sigma, sigma_within=sw, lsl=lsl, usl=usl,
                      cp=cp_of(sw), cpk=cpk_of(sw), pp=cp_of(sigma), ppk=cpk_of(sigma))


def _baseline_count(n: int, baseline: int | None) -> int:
    if baseline is None:
        return n
    if isinstance(baseline, bool) or not isinstance(baseline, (int, np.integer)) or baseline < 2:
        raise InputError(f"baseline must be an integer >= 2 (boards); got {baseline!r}")
    return min(int(baseline), n)


def individuals_chart(values, *, baseline: int | None = None, rules: Sequence[int] | None = None
                      ) -> ControlChart:
    """Individuals (I-MR) chart of one value per board.

    Parameters
    ----------
    values : (n,) array_like
        In production order; NaN for a board without a value (skipped by the moving
        ranges and the rules, which run over the remaining points in order).
    baseline : int, optional
        Limits from the first ``baseline`` boards (default: all).
    rules : sequence of int, optional
        Rules to check (default: all of :data:`RULES`).

    Returns
    -------
    ControlChart
        ``cl`` the baseline mean, ``ucl``/``lcl`` = ``cl ± 3·MR̄/1.128``.
    """
    x = _as_series(values)
    b = _baseline_count(len(x), baseline)
    base = x[:b][np.isfinite(x[:b])]
    mr_all = np.full(len(x), np.nan)
    ok = np.flatnonzero(np.isfinite(x))
    if ok.size >= 2:
        mr_all[ok[1:]] = np.abs(np.diff(x[ok]))
    mr_base = np.abs(np.diff(base))
    if base.size >= 2:
        cl = float(base.mean())
        mr_bar = float(mr_base.mean())
        sigma = mr_bar / _D2[2]
    else:
        cl = mr_bar = sigma = math.nan
    chart = ControlChart(kind="individuals", values=x, cl=cl, ucl=cl + 3 * sigma,
                         lcl=cl - 3 * sigma, sigma=sigma, sigma_stat=sigma, spread=mr_all,
                         spread_cl=mr_bar, spread_ucl=_D4[2] * mr_bar, spread_lcl=0.0,
                         baseline=b, subgroup=1)
    return _with_hits(chart, rules)


def xbar_r_chart(subgroups, *, baseline: int | None = None,
                 rules: Sequence[int] | None = None) -> ControlChart:
    """X̄–R chart: one subgroup of ``k`` values per board (2 <= k <= 10).

    Parameters
    ----------
    subgroups : (n, k) array_like
        Row i holds board i's values (e.g. the max heights of every joint of one
        package type). A row with a NaN is left out of the limits and of the rules.
    baseline : int, optional
        Limits from the first ``baseline`` boards (default: all).
    rules : sequence of int, optional
        Rules checked on the subgroup means (default: all).

    Returns
    -------
    ControlChart
        ``cl`` = grand mean X̿, limits ``X̿ ± A2·R̄``; ``sigma`` = ``R̄/d2``.
    """
    g = np.asarray(subgroups, dtype=np.float64)
    if g.ndim != 2 or not 2 <= g.shape[1] <= MAX_SUBGROUP:
        raise InputError(f"subgroups must be (boards, k) with 2 <= k <= {MAX_SUBGROUP}; got "
                         f"shape {g.shape}")
    k = g.shape[1]
    complete = np.all(np.isfinite(g), axis=1)
    means = np.where(complete, np.nanmean(np.where(complete[:, None], g, 0.0), axis=1), np.nan)
    ranges = np.where(complete, np.ptp(np.where(complete[:, None], g, 0.0), axis=1), np.nan)
    b = _baseline_count(len(g), baseline)
    ok = complete[:b]
    if ok.sum() >= 2:
        xbb = float(means[:b][ok].mean())
        r_bar = float(ranges[:b][ok].mean())
        sigma = r_bar / _D2[k]
    else:
        xbb = r_bar = sigma = math.nan
    chart = ControlChart(kind="xbar-r", values=means, cl=xbb, ucl=xbb + _A2[k] * r_bar,
                         lcl=xbb - _A2[k] * r_bar, sigma=sigma,
                         sigma_stat=sigma / math.sqrt(k), spread=ranges, spread_cl=r_bar,
                         spread_ucl=_D4[k] * r_bar, spread_lcl=_D3[k] * r_bar, baseline=b,
                         subgroup=k)
    return _with_hits(chart, rules)


def _with_hits(chart: ControlChart, rules: Sequence[int] | None) -> ControlChart:
    from dataclasses import replace

    hits = run_rules(chart.values, cl=chart.cl, sigma=chart.sigma_stat, rules=rules)
    return replace(chart, hits=tuple(hits))


def run_rules(values, *, cl: float, sigma: float, rules: Sequence[int] | None = None
              ) -> list[RuleHit]:
    """Western Electric / Nelson run rules on a series (see :data:`RULES`).

    Parameters
    ----------
    values : (n,) array_like
        The plotted points in order; NaN points are skipped (the runs go over the
        remaining points).
    cl : float
        Centre line.
    sigma : float
        σ of one plotted point (zones at 1, 2, 3 σ).
    rules : sequence of int, optional
        Which rules (default all, 1–8).

    Returns
    -------
    list of RuleHit
        Every point that completes a run of a rule (a long run fires at each of its
        points past the minimum length), sorted by index then rule. Empty when ``cl``
        or ``sigma`` is not finite or ``sigma`` is 0.
    """
    x = _as_series(values)
    wanted = sorted(RULES) if rules is None else sorted(set(int(r) for r in rules))
    bad = [r for r in wanted if r not in RULES]
    if bad:
        raise InputError(f"unknown run rule {bad[0]}; the rules are {sorted(RULES)}")
    if not (math.isfinite(cl) and math.isfinite(sigma) and sigma > 0):
        return []
    idx = np.flatnonzero(np.isfinite(x))
    z = (x[idx] - cl) / sigma
    n = len(z)
    hits: set[tuple[int, int]] = set()

    def window_rule(rule: int, length: int, test) -> None:
        for end in range(length - 1, n):
            if test(z[end - length + 1:end + 1]):
                hits.add((int(idx[end]), rule))

    if 1 in wanted:
        for i in np.flatnonzero(np.abs(z) > 3):
            hits.add((int(idx[i]), 1))
    if 2 in wanted:
        window_rule(2, 9, lambda w: bool(np.all(w > 0) or np.all(w < 0)))
    if 3 in wanted:
        window_rule(3, 6, lambda w: bool(np.all(np.diff(w) > 0) or np.all(np.diff(w) < 0)))
    if 4 in wanted:
        def alternating(w):
            d = np.sign(np.diff(w))
            return bool(np.all(d != 0) and np.all(d[1:] == -d[:-1]))
        window_rule(4, 14, alternating)

    def k_of_m(rule: int, k: int, m: int, level: float) -> None:
        for end in range(m - 1, n):
            w = z[end - m + 1:end + 1]
            # the point completing the run must itself be one of the k
            if z[end] > level and np.sum(w > level) >= k:
                hits.add((int(idx[end]), rule))
            if z[end] < -level and np.sum(w < -level) >= k:
                hits.add((int(idx[end]), rule))

    if 5 in wanted:
        k_of_m(5, 2, 3, 2.0)
    if 6 in wanted:
        k_of_m(6, 4, 5, 1.0)
    if 7 in wanted:
        window_rule(7, 15, lambda w: bool(np.all(np.abs(w) < 1)))
    if 8 in wanted:
        window_rule(8, 8, lambda w: bool(np.all(np.abs(w) > 1) and np.any(w > 1)
                                         and np.any(w < -1)))
    return [RuleHit(index=i, rule=r) for i, r in sorted(hits)]
