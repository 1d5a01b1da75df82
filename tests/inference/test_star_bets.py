"""Target-recalculating (STaR) bets of the betting test: brute-force known answers,
monotonicity in m, p-value against the bounds, coverage by cell."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinfalsify.inference.betting import betting_bounds, betting_test, make_bets
from twinfalsify.inference.capital import OrderedSide, log_capital, star_bets
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.union import smallest_rejecting_alpha, union_reject

C = 0.9


def _brute_log_capital(x, m, sign, delta0, running_max=True, c=C):
    """One group, a plain loop: the formula of ``star_log_capital``'s docstring."""
    n = len(x)
    if sign < 0:
        x, m = [1.0 - v for v in x], 1.0 - m
    big_r = math.log(1 / delta0)
    ell, top, s, ss, sig2_prev = 0.0, 0.0, 0.0, 0.0, 0.25
    for i, xi in enumerate(x, start=1):
        var = min(sig2_prev, m * (1 - m))
        need = big_r - ell
        b = math.sqrt(2 * max(need, 0.5) / ((n - i + 1) * var)) * math.exp(min(need - 0.5, 0))
        b = min(b, c / m)
        ell += math.log(1 + b * (xi - m))
        top = max(top, ell)
        s += xi
        mu = (0.5 + s) / (i + 1)
        ss += (xi - mu) ** 2
        sig2_prev = (0.25 + ss) / (i + 1)
    return top if running_max else ell


def _side(groups, delta0):
    x = np.concatenate(groups)
    offs = np.concatenate([[0], np.cumsum([len(g) for g in groups])]).astype(np.int64)
    return OrderedSide(x, np.zeros(len(x)), offs, 1, star_bets(x, offs, delta0))


@pytest.mark.parametrize("running_max", [True, False])
@pytest.mark.parametrize("sign", [+1, -1])
def test_compiled_equals_brute_force_loop(sign, running_max):
    """Ragged groups (sizes 1..40, one empty; more groups than the kernel steps together), several
    m and targets: equal to 1e-12."""
    rng = np.random.default_rng(1)
    sizes = [1, 40, 0, 7, 25, 3, 40]
    groups = [rng.beta(0.7, 1.5, k) if j % 2 else (rng.random(k) < 0.3).astype(float)
              for j, k in enumerate(sizes)]
    delta0 = np.array([0.025, 1e-3, 0.1, 1e-5, 0.025, 0.3, 0.01])
    side = _side(groups, delta0)
    for m0 in (0.05, 0.2, 0.45, 0.8):
        m = np.clip(m0 + 0.05 * rng.standard_normal(len(sizes)), 0.01, 0.99)
        got = log_capital(side, m, sign, running_max, C)
        want = [_brute_log_capital(list(g), float(mi), sign, float(d), running_max)
                if len(g) else 0.0 for g, mi, d in zip(groups, m, delta0, strict=True)]
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_capital_monotone_in_m():
    """log max_t K+ non-increasing and log max_t K- non-decreasing on a fine grid of m, for
    skewed, binary and near-constant samples at small and large targets (module doc proof)."""
    rng = np.random.default_rng(2)
    groups = [(rng.random(60) < 0.1).astype(float), rng.beta(2, 5, 200), rng.random(30),
              np.full(50, 0.4) + 0.01 * rng.random(50), (rng.random(300) < 0.5).astype(float)]
    for d0 in (0.025, 1e-5):
        side = _side(groups, np.full(len(groups), d0))
        grid = np.linspace(1e-4, 1 - 1e-4, 241)
        for sign in (+1, -1):
            vals = np.array([log_capital(side, np.full(len(groups), m), sign, True, C)
                             for m in grid])
            steps = np.diff(vals, axis=0) * sign
            assert np.all(steps <= 1e-10), steps.max()


def _small_case(seed=3, h=10):
    rng = np.random.default_rng(seed)
    n = rng.integers(40, 250, h)
    nf = (n * rng.uniform(0.6, 1.0, h)).astype(int)
    nh = rng.integers(40, 250, h)
    shift = np.linspace(-0.1, 0.25, h)
    follow = Ragged.from_groups([rng.beta(2, 2, k) for k in nf])
    twin = Ragged.from_groups([np.clip(rng.beta(2, 2, k) - shift[i], 0, 1)
                               for i, k in enumerate(nh)])
    return HypothesisSamples(np.zeros(h), np.ones(h), n.astype(np.int64), follow, twin)


@pytest.mark.slow
def test_p_value_is_smallest_rejecting_alpha():
    """The crossing p equals the smallest alpha at which the union rule on the STaR bounds
    rejects (bisection on alpha), so p is never below the bound-based decision."""
    s = _small_case()
    p_lo, p_up = betting_test(s, tune_alpha=0.01, bets="star")

    def rule(side):
        def reject(alpha):
            b = betting_bounds(s, alpha, tune_alpha=0.01, bets="star")
            if side == "lo":
                return union_reject(b["upper_twin"], b["lower_lo"])
            return union_reject(b["upper_up"], b["lower_twin"])
        return reject

    ref_lo = smallest_rejecting_alpha(rule("lo"), len(s), rtol=1e-4)
    ref_up = smallest_rejecting_alpha(rule("up"), len(s), rtol=1e-4)
    assert (p_lo < 0.6).sum() + (p_up < 0.6).sum() >= 2
    np.testing.assert_allclose(p_lo, ref_lo, rtol=3e-3)
    np.testing.assert_allclose(p_up, ref_up, rtol=3e-3)
    assert np.all(p_lo >= ref_lo * (1 - 3e-3)) and np.all(p_up >= ref_up * (1 - 3e-3))


def test_star_tighter_than_plugin_on_skewed_data():
    """Bernoulli(0.1), n = 200: STaR's mean distance from the mean to the lower bound is below
    the plug-in bets' (measured 0.84x in docs/reference/benchmarks.md)."""
    rng = np.random.default_rng(4)
    x = (rng.random((400, 200)) < 0.1).astype(float)
    s = _one_sample(x)
    lo_s = betting_bounds(s, 0.05, tune_alpha=0.05, bets="star")["lower_twin"]
    lo_p = betting_bounds(s, 0.05, tune_alpha=0.05, bets="plugin")["lower_twin"]
    assert np.mean(0.1 - lo_s) < 0.95 * np.mean(0.1 - lo_p)


def _one_sample(x):
    r, n = x.shape
    g = Ragged(x.ravel().copy(), np.arange(0, r * n + 1, n, dtype=np.int64))
    return HypothesisSamples(np.zeros(r), np.ones(r), np.full(r, n), g, g)


CELLS = {
    "Bernoulli(0.1)": (lambda r, s: (r.random(s) < 0.1).astype(float), 0.1),
    "Bernoulli(0.5)": (lambda r, s: (r.random(s) < 0.5).astype(float), 0.5),
    "Beta(2,5)": (lambda r, s: r.beta(2, 5, s), 2 / 7),
    "Beta(0.2,2)": (lambda r, s: r.beta(0.2, 2, s), 0.2 / 2.2),
}


def _misses(draw, mu, n, reps, rng, alpha=0.05):
    """Misses of each one-sided (1 - alpha/2) STaR bound (the union rule's per-side level)."""
    s = _one_sample(draw(rng, (reps, n)))
    b = betting_bounds(s, alpha, tune_alpha=alpha, bets="star")
    return int(np.sum(b["lower_twin"] > mu)), int(np.sum(b["upper_twin"] < mu))


@pytest.mark.slow
def test_coverage_scan_then_confirm_worst_cell():
    """Scan: 4 distributions x n in {10, 50, 200}, 2,000 replicates each, each one-sided bound
    at level 0.025. Then 10,000 further replicates of the worst (cell, side): its miss rate's
    one-sided 99.9 % lower binomial limit stays below 0.025 (a violation of the nominal level
    by a third would show: 0.033 at 10,000 replicates is 5 SD away)."""
    rng = np.random.default_rng(7)
    worst, worst_rate = None, -1.0
    for name, (draw, mu) in CELLS.items():
        for n in (10, 50, 200):
            lo, up = _misses(draw, mu, n, 2000, rng)
            for side, k in (("lower", lo), ("upper", up)):
                assert k / 2000 <= 0.025 + 3 * math.sqrt(0.025 * 0.975 / 2000), (name, n, side)
                if k / 2000 > worst_rate:
                    worst, worst_rate = (name, n, side), k / 2000
    name, n, side = worst
    draw, mu = CELLS[name]
    k = sum(_misses(draw, mu, n, 2000, rng)[side == "upper"] for _ in range(5))
    rate, reps = k / 10000, 10000
    assert rate - 3.09 * math.sqrt(0.025 * 0.975 / reps) <= 0.025, (worst, rate)


def test_options():
    assert make_bets("star").kind == "star" and make_bets("star").running_max
    assert make_bets("star", running_max=False).running_max is False
    with pytest.raises(ValueError, match="one order"):
        make_bets("star", orders=4)
    with pytest.raises(ValueError, match="order must be"):
        make_bets("star", order="sorted")
