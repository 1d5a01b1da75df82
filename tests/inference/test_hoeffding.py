"""Hoeffding p-values: closed form = smallest rejecting alpha; refusal rules; correction."""

from __future__ import annotations

import gc

import numpy as np
import pytest
from scipy.optimize import brentq

from twinfalsify.inference.hoeffding import hoeffding_pvalue, hoeffding_radius, hoeffding_test
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged


def interval_rule_rejects(q_lo, q_twin, width, n, nhat, alpha):
    """Reject H_lo when the upper (1 - alpha/2) bound of Q_twin lies below the lower
    (1 - alpha/2) bound of Q_lo (docs/explanation/method.md)."""
    return q_twin + hoeffding_radius(width, nhat, alpha) < q_lo - hoeffding_radius(width, n, alpha)


@pytest.mark.parametrize(
    "q_lo,q_twin,width,n,nhat",
    [
        (0.6, 0.4, 1.0, 200, 300),
        (5.0, 4.0, 3.0, 1000, 50),
        (0.51, 0.5, 1.0, 10_000, 10_000),
        (10.0, 2.0, 20.0, 30, 30),
    ],
)
def test_pvalue_is_smallest_rejecting_alpha(q_lo, q_twin, width, n, nhat):
    p = float(hoeffding_pvalue(q_lo - q_twin, width, n, nhat))
    if p >= 1.0:
        assert not interval_rule_rejects(q_lo, q_twin, width, n, nhat, 0.999999)
        return

    def gap(alpha):
        return (q_lo - hoeffding_radius(width, n, alpha)) - (
            q_twin + hoeffding_radius(width, nhat, alpha)
        )

    alpha_star = brentq(gap, 1e-300, 2.0 - 1e-12, xtol=1e-15, rtol=1e-12)
    assert p == pytest.approx(alpha_star, rel=1e-8)
    assert interval_rule_rejects(q_lo, q_twin, width, n, nhat, p * 1.0001)
    assert not interval_rule_rejects(q_lo, q_twin, width, n, nhat, p * 0.9999)


def test_refusal_and_direction():
    p = hoeffding_pvalue(
        np.array([0.3, 0.3, 0.3, -0.3, 0.0]),
        1.0,
        np.array([0, 100, 100, 100, 100]),
        np.array([100, 0, 100, 100, 100]),
    )
    assert p[0] == 1.0 and p[1] == 1.0  # n = 0 or nhat = 0: refuse to reject
    assert p[2] < 1.0
    assert p[3] == 1.0 and p[4] == 1.0  # twin inside the bound


def test_factor_four_reproduces_authors_code_and_is_more_conservative():
    d, n, nhat = np.linspace(0.05, 0.3, 6), 400, 400
    p2 = hoeffding_pvalue(d, 1.0, n, nhat, factor=2.0)
    p4 = hoeffding_pvalue(d, 1.0, n, nhat, factor=4.0)
    np.testing.assert_allclose(np.minimum(1.0, 2 * p2), p4)


def test_monotone_in_gap_and_sample_size():
    d = np.linspace(0.0, 0.5, 50)
    p = hoeffding_pvalue(d, 1.0, 100, 100)
    assert np.all(np.diff(p) <= 0)
    ns = np.array([10, 100, 1000, 10000])
    assert np.all(np.diff(hoeffding_pvalue(0.1, 1.0, ns, ns)) <= 0)


def test_test_uses_both_sides_and_clipping():
    # follower values outside [0, 1] must be clipped before averaging
    s = HypothesisSamples(
        y_lo=np.array([0.0, 0.0]),
        y_up=np.array([1.0, 1.0]),
        n=np.array([1000, 1000]),
        follow=Ragged.from_groups([np.full(900, 5.0), np.full(900, -5.0)]),
        twin=Ragged.from_groups([np.full(500, 0.1), np.full(500, 0.9)]),
    )
    np.testing.assert_allclose(s.q_lo_hat, [0.9, 0.0])
    np.testing.assert_allclose(s.q_up_hat, [1.0, 0.1])
    p_lo, p_up = hoeffding_test(s)
    assert p_lo[0] < 1e-10 and p_up[0] == 1.0  # twin far below Q_lo
    assert p_up[1] < 1e-10 and p_lo[1] == 1.0  # twin far above Q_up


def test_type_one_error_of_hoeffding_below_alpha_by_simulation():
    """Twin mean exactly at Q_lo (boundary of H_lo): rejection rate <= alpha."""
    rng = np.random.default_rng(3)
    reps, n, nhat, alpha = 4000, 60, 40, 0.1
    obs = rng.random((reps, n)) < 0.3  # Y_lo in {0, 1}, mean 0.3
    twin = rng.random((reps, nhat)) < 0.3
    p = hoeffding_pvalue(obs.mean(1) - twin.mean(1), 1.0, n, nhat)
    assert (p <= alpha).mean() <= alpha


def test_holm_and_by_known_answers():
    p = np.array([0.001, 0.01, 0.02, 0.5])
    # Holm: 0.001 <= .05/4, 0.01 <= .05/3, 0.02 <= .05/2, 0.5 > .05
    np.testing.assert_array_equal(correct(p, 0.05, "holm"), [True, True, True, False])
    np.testing.assert_array_equal(correct(p, 0.05, "bonferroni"), [True, True, False, False])
    # BY: c_4 = 25/12; thresholds k 0.05 / (4 c_4) = 0.006, 0.012, 0.018, 0.024
    np.testing.assert_array_equal(correct(p, 0.05, "by"), [True, True, False, False])
    # step-down stops at the first failure: 0.03 > .05/2 keeps 0.04 <= .05 unrejected
    np.testing.assert_array_equal(correct([0.04, 0.03, 0.001], 0.05, "holm"),
                                  [False, False, True])
    with pytest.raises(ValueError, match="unknown correction"):
        correct(p, 0.05, "bh")
    with pytest.raises(ValueError, match="1 of 2 p-values are NaN"):
        correct([0.1, np.nan], 0.05)
    assert correct(np.array([]), 0.05).size == 0


@pytest.mark.parametrize("method,name", [("holm", "holm"), ("by", "fdr_by"),
                                         ("bonferroni", "bonferroni")])
def test_corrections_equal_statsmodels(method, name):
    """Decision for decision, on random families, families with ties (the lattice
    p-values of the bootstrap) and p-values at a threshold exactly."""
    from statsmodels.stats.multitest import multipletests

    rng = np.random.default_rng(11)
    families = [rng.random(m) ** rng.uniform(1, 8) for m in (1, 2, 5, 40, 500)]
    families += [rng.integers(0, 50, 300) / 100 for _ in range(5)]  # ties
    families += [0.05 / np.arange(8, 0, -1), np.full(7, 0.05 / 7), np.zeros(3), np.ones(3)]
    gc.freeze()  # multipletests collects garbage on every call: keep pytest's heap out of it
    try:
        for p in families:
            for alpha in (0.001, 0.05, 0.2):
                want = multipletests(p, alpha=alpha, method=name)[0]
                np.testing.assert_array_equal(correct(p, alpha, method), want)
    finally:
        gc.unfreeze()
