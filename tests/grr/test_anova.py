"""Gauge R&R statistics against known variance components (AIAG ANOVA method)."""

import math

import numpy as np
import pytest
from scipy import stats

from smdinspect.errors import InputError
from smdinspect.grr import gauge_rr, rating


def crossed(p, o, r, *, sd_part, sd_op, sd_int, sd_e, seed):
    """Long-format data of a crossed design with known effects; also the realised effects."""
    rng = np.random.default_rng(seed)
    P = rng.normal(0, sd_part, p)
    O = rng.normal(0, sd_op, o)
    PO = rng.normal(0, sd_int, (p, o))
    E = rng.normal(0, sd_e, (p, o, r))
    y = 5.0 + P[:, None, None] + O[None, :, None] + PO[:, :, None] + E
    pi, oi, _ = np.meshgrid(np.arange(p), np.arange(o), np.arange(r), indexing="ij")
    return y.ravel(), pi.ravel(), oi.ravel(), (P, O, PO, E)


def test_crossed_design_recovers_the_variance_components():
    y, parts, ops, (P, O, PO, E) = crossed(30, 40, 6, sd_part=1.0, sd_op=0.2, sd_int=0.1,
                                           sd_e=0.15, seed=1)
    g = gauge_rr(y, parts=parts, operators=ops, interaction_alpha=0.05)
    assert g.method == "crossed" and (g.n_parts, g.n_operators, g.n_trials) == (30, 40, 6)
    assert not g.interaction_pooled
    # against the realised effects (the estimators' targets for this sample)
    assert g.sigma_repeatability == pytest.approx(E.std(ddof=1), rel=0.02)
    assert math.sqrt(g.var_interaction) == pytest.approx(PO.std(ddof=1), rel=0.08)
    assert math.sqrt(g.var_operator) == pytest.approx(O.std(ddof=1), rel=0.08)
    assert g.sigma_part == pytest.approx(P.std(ddof=1), rel=0.03)
    # and against the true σ, within sampling error
    assert g.sigma_repeatability == pytest.approx(0.15, rel=0.03)
    assert math.sqrt(g.var_operator) == pytest.approx(0.2, rel=0.25)
    grr = math.sqrt(0.15 ** 2 + 0.2 ** 2 + 0.1 ** 2)
    assert g.sigma_grr == pytest.approx(grr, rel=0.15)
    assert g.sigma_reproducibility == pytest.approx(math.sqrt(g.var_operator + g.var_interaction))
    assert [t.source for t in g.anova] == ["part", "operator", "part x operator",
                                           "repeatability"]
    assert sum(t.df for t in g.anova) == y.size - 1
    assert sum(t.ss for t in g.anova) == pytest.approx(np.sum((y - y.mean()) ** 2))


def test_variance_estimates_are_unbiased_on_small_aiag_studies():
    """10 parts x 3 operators x 3 trials (the AIAG layout), 400 studies: mean estimates."""
    est = []
    for seed in range(400):
        y, parts, ops, _ = crossed(10, 3, 3, sd_part=0.5, sd_op=0.1, sd_int=0.0, sd_e=0.05,
                                   seed=100 + seed)
        g = gauge_rr(y, parts=parts, operators=ops, interaction_alpha=0.0)  # never pool
        est.append((g.var_repeatability, g.var_part))
    var_e, var_p = np.mean(est, axis=0)
    assert var_e == pytest.approx(0.05 ** 2, rel=0.03)
    assert var_p == pytest.approx(0.5 ** 2, rel=0.1)


def test_no_interaction_is_pooled():
    y, parts, ops, (_, O, _, E) = crossed(10, 3, 5, sd_part=1.0, sd_op=0.3, sd_int=0.0,
                                          sd_e=0.1, seed=3)
    g = gauge_rr(y, parts=parts, operators=ops)
    assert g.interaction_pooled and g.var_interaction == 0.0
    assert [t.source for t in g.anova] == ["part", "operator", "repeatability"]
    assert g.anova[-1].df == 10 * 3 * 5 - 10 - 3 + 1
    assert g.sigma_repeatability == pytest.approx(0.1, rel=0.15)


def test_one_trial_per_cell_uses_the_additive_model():
    y, parts, ops, _ = crossed(8, 4, 1, sd_part=1.0, sd_op=0.2, sd_int=0.0, sd_e=0.05, seed=4)
    g = gauge_rr(y, parts=parts, operators=ops)
    assert g.method == "crossed" and g.interaction_pooled and g.anova[-1].df == 7 * 3


def test_one_part_several_operators_is_a_one_way_anova():
    rng = np.random.default_rng(5)
    groups = [rng.normal(mu, 0.02, n) for mu, n in ((1.0, 5), (1.05, 4), (0.98, 6))]
    y = np.concatenate(groups)
    ops = np.repeat(["A", "B", "C"], [5, 4, 6])
    g = gauge_rr(y, operators=ops)
    f, p = stats.f_oneway(*groups)
    assert g.method == "one-way" and g.n_parts == 1 and g.n_operators == 3
    assert g.anova[0].f == pytest.approx(f) and g.anova[0].p == pytest.approx(p)
    ms_w = sum(np.sum((s - s.mean()) ** 2) for s in groups) / (15 - 3)
    assert g.var_repeatability == pytest.approx(ms_w)
    n0 = (15 - (25 + 16 + 36) / 15) / 2
    assert g.var_operator == pytest.approx((g.anova[0].ms - ms_w) / n0)
    assert math.isnan(g.var_part) and math.isnan(g.ndc) and math.isnan(g.pct_study)


def test_repeats_only_give_the_sample_sigma_and_pct_of_tolerance():
    y = np.array([0.300, 0.310, 0.290, 0.305, 0.295, np.nan])
    g = gauge_rr(y, tolerance=0.4)
    assert g.n == 5 and g.sigma_repeatability == pytest.approx(np.std(y[:5], ddof=1))
    assert math.isnan(g.var_operator) and g.sigma_grr == g.sigma_repeatability
    assert g.pct_tolerance == pytest.approx(600 * g.sigma_grr / 0.4)
    assert gauge_rr(y, tolerance=0.4, k_sigma=5.15).pct_tolerance == pytest.approx(
        515 * g.sigma_grr / 0.4)


def test_parts_only_give_ndc_and_study_variation():
    rng = np.random.default_rng(6)
    truth = rng.normal(0, 1.0, 20)
    y = np.repeat(truth, 4) + rng.normal(0, 0.1, 80)
    g = gauge_rr(y, parts=np.repeat(np.arange(20), 4))
    assert g.method == "one-way" and math.isnan(g.var_operator)
    assert g.sigma_repeatability == pytest.approx(0.1, rel=0.2)
    assert g.pct_study == pytest.approx(100 * g.sigma_grr / math.hypot(g.sigma_grr, g.sigma_part))
    assert g.ndc == math.floor(1.41 * g.sigma_part / g.sigma_grr) and g.ndc >= 10


def test_too_few_values():
    assert gauge_rr([1.0]).method == "none"
    assert math.isnan(gauge_rr([1.0, np.nan], tolerance=1.0).pct_tolerance)
    assert gauge_rr([1.0, 2.0], operators=["A", "B"]).method == "none"  # no replicate


def test_errors():
    with pytest.raises(InputError, match="balanced"):
        gauge_rr([1, 2, 3, 4, 5], parts=[0, 0, 1, 1, 1], operators=[0, 1, 0, 1, 1])
    with pytest.raises(InputError, match="one label per value"):
        gauge_rr([1, 2, 3], operators=["A", "B"])
    with pytest.raises(InputError, match="tolerance must be > 0"):
        gauge_rr([1, 2, 3], tolerance=0)
    with pytest.raises(InputError, match="one-dimensional"):
        gauge_rr(np.ones((2, 2)))


def test_rating_follows_aiag():
    assert [rating(v) for v in (5, 10, 10.1, 30, 31, math.nan)] == [
        "acceptable", "acceptable", "marginal", "marginal", "unacceptable", "n/a"]


def test_docstring_example():
    import doctest

    import smdinspect.grr._anova as module

    assert doctest.testmod(module).failed == 0
