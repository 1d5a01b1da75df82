"""Union-rule p-value helper, checked against closed forms (Hoeffding, empirical Bernstein)."""

from __future__ import annotations

import numpy as np
import pytest

from twinfalsify.inference.bernstein import bernstein_radius, bernstein_test, sample_variances
from twinfalsify.inference.hoeffding import hoeffding_pvalue, hoeffding_radius
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.union import smallest_rejecting_alpha, union_reject


def test_union_reject_rule():
    assert union_reject(np.array([0.1, 0.5, np.nan, 0.2]), np.array([0.2, 0.5, 0.3, np.nan])
                        ).tolist() == [True, False, False, False]


def test_bisection_recovers_hoeffding_closed_form():
    """Hoeffding bounds into the rule; bisection == the paper's closed-form p (factor 2)."""
    rng = np.random.default_rng(0)
    h = 500
    d = rng.uniform(-0.05, 0.3, h)
    n, nhat = rng.integers(1, 3000, h), rng.integers(1, 3000, h)
    width = rng.uniform(0.5, 3, h)

    def reject(alpha):
        return union_reject(-d + hoeffding_radius(width, nhat, alpha),
                            0.0 - hoeffding_radius(width, n, alpha))

    p = smallest_rejecting_alpha(reject, h, rtol=1e-10)
    ref = hoeffding_pvalue(d, width, n, nhat)
    np.testing.assert_allclose(p, ref, rtol=1e-8)
    assert (ref < 1e-10).any() and (ref == 1).any() and ((ref > 0.01) & (ref < 1)).any()


def _case(seed=1, h=200):
    rng = np.random.default_rng(seed)
    n = rng.integers(0, 800, h)
    nf = (n * rng.uniform(0.3, 1, h)).astype(int)
    nh = rng.integers(0, 800, h)
    shift = rng.uniform(-0.1, 0.2, h)
    follow = Ragged.from_groups([5 + 10 * rng.beta(2, 3, k) for k in nf])
    twin = Ragged.from_groups([5 + 10 * (rng.beta(2, 3, k) - shift[i]) for i, k in enumerate(nh)])
    return HypothesisSamples(np.full(h, 6.0), np.full(h, 13.0), n.astype(np.int64), follow, twin)


def test_bernstein_closed_form_is_smallest_rejecting_alpha():
    s = _case()
    p_lo, p_up = bernstein_test(s)
    v_lo, v_up, v_tw = sample_variances(s)
    r = s.width

    def rule(side):
        def reject(alpha):
            a = np.asarray(alpha)
            rad_o = bernstein_radius(v_lo if side == "lo" else v_up, s.n, r, a)
            rad_t = bernstein_radius(v_tw, s.nhat, r, a)
            if side == "lo":
                return union_reject(s.q_twin_hat + rad_t, s.q_lo_hat - rad_o)
            return union_reject(s.q_up_hat + rad_o, s.q_twin_hat - rad_t)
        return reject

    np.testing.assert_allclose(p_lo, smallest_rejecting_alpha(rule("lo"), len(s)), rtol=1e-7)
    np.testing.assert_allclose(p_up, smallest_rejecting_alpha(rule("up"), len(s)), rtol=1e-7)
    assert ((p_lo < 0.05) | (p_up < 0.05)).sum() > 5
    small = (s.n < 2) | (s.nhat < 2)
    assert np.all(p_lo[small] == 1) and np.all(p_up[small] == 1)


def test_sample_variances_match_materialised():
    s = _case(seed=2, h=30)
    v_lo, v_up, v_tw = sample_variances(s)
    for h in range(len(s)):
        for v, y in ((v_lo, s.obs_side("lo").group(h)), (v_up, s.obs_side("up").group(h)),
                     (v_tw, s.twin_f.group(h))):
            if len(y) >= 2:
                assert v[h] == pytest.approx(np.var(y, ddof=1), rel=1e-9, abs=1e-12)
            else:
                assert np.isnan(v[h])


@pytest.mark.parametrize("n", [50, 400])
def test_bernstein_bound_coverage(n):
    """Each one-sided (1 - alpha/2) empirical-Bernstein bound covers in >= 95 % of 2,000 reps."""
    rng = np.random.default_rng(n)
    reps, alpha = 2000, 0.1
    x = rng.binomial(1, 0.2, (reps, n)).astype(float)
    rad = bernstein_radius(x.var(axis=1, ddof=1), np.full(reps, n), np.ones(reps), alpha)
    floor = 0.95 - 3 * np.sqrt(0.95 * 0.05 / reps)
    assert np.mean(x.mean(axis=1) - rad <= 0.2) >= floor
    assert np.mean(x.mean(axis=1) + rad >= 0.2) >= floor
