"""Bootstrap test: compact resampling law, exact smallest-alpha p-value, refusals, seeding."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.reference import resample_sums_reference

from twinfalsify.inference.bootstrap import (
    bootstrap_distributions,
    bootstrap_test,
    union_pvalue_sorted,
)
from twinfalsify.inference.samples import HypothesisSamples, Ragged


def _samples(rng, h, n, nf, nhat, shift=0.0):
    follow = Ragged.from_groups([rng.beta(2, 5, k) for k in np.broadcast_to(nf, (h,))])
    twin = Ragged.from_groups([np.clip(rng.beta(2, 5, k) + shift, 0, 1)
                               for k in np.broadcast_to(nhat, (h,))])
    return HypothesisSamples(np.zeros(h), np.ones(h), np.broadcast_to(np.asarray(n), (h,)).copy(),
                             follow, twin)


def test_compact_resampling_has_the_bootstrap_law():
    """Mean and variance of the resampled means equal those of resampling the full sample.

    For a resample of size n of the materialised sample y: E[theta*] = ybar and
    Var[theta*] = (1/n) * (1/n) sum (y - ybar)^2 (plug-in variance / n).
    """
    rng = np.random.default_rng(0)
    s = _samples(rng, 1, 300, 120, 150)
    s = s.with_bounds(np.array([0.15]), np.array([0.5]))  # clipped masses at both ends
    b = 20000
    d = bootstrap_distributions(s, n_resamples=b, min_n=1, seed=1)
    for side, dist in (("lo", d.lo), ("up", d.up), (None, d.twin)):
        y = s.obs_side(side).group(0) if side else s.twin_f.group(0)
        var = y.var() / len(y)
        assert abs(dist.mean() - y.mean()) < 4 * np.sqrt(var / b)
        assert dist.var() == pytest.approx(var, rel=0.05)  # sd of the ratio ~ sqrt(2/b) = 1 %


def _rule(small_hat, small, large_hat, large, delta, kind):
    """Independent reference: np.quantile's inverted-CDF quantiles at level delta per side."""
    if kind == "reverse_percentile":
        upper = 2 * small_hat - np.quantile(small, delta, method="inverted_cdf")
        lower = 2 * large_hat - np.quantile(large, 1 - delta, method="inverted_cdf")
    else:
        upper = np.quantile(small, 1 - delta, method="inverted_cdf")
        lower = np.quantile(large, delta, method="inverted_cdf")
    return upper < lower


@pytest.mark.parametrize("kind", ["reverse_percentile", "percentile"])
@pytest.mark.parametrize("b", [100, 99])
def test_p_value_is_smallest_rejecting_alpha(kind, b):
    rng = np.random.default_rng(7)
    h = 300
    small = np.sort(rng.normal(0, 1, (h, b)), axis=1)
    large = np.sort(rng.normal(rng.uniform(-1, 5, (h, 1)), 1, (h, b)), axis=1)
    sh, lh = small.mean(axis=1), large.mean(axis=1)
    p = union_pvalue_sorted(sh, small, lh, large, kind)
    assert 0 < (p < 1).sum() < h and (p == 0).sum() > 0  # exercises all regimes
    for i in range(h):
        if p[i] < 1:  # rejects just above p/2 per side ...
            assert _rule(sh[i], small[i], lh[i], large[i], p[i] / 2 + 1e-9, kind)
        if p[i] > 0:  # ... and not just below
            assert not _rule(sh[i], small[i], lh[i], large[i], p[i] / 2 - 1e-9, kind)
        # and on a fine grid of alpha the rule rejects exactly when alpha > p (at alpha = p
        # itself, a step of the quantile functions, the infimum may or may not be attained)
        for a in np.linspace(0.001, 0.999, 37):
            if abs(a - p[i]) < 1e-12:
                continue
            assert _rule(sh[i], small[i], lh[i], large[i], a / 2, kind) == (a > p[i])


def test_refusals_and_seeding():
    rng = np.random.default_rng(3)
    s = _samples(rng, 4, np.array([99, 100, 400, 400]), np.array([99, 100, 300, 300]),
                 np.array([200, 200, 99, 100]), shift=-0.3)
    p_lo, p_up = bootstrap_test(s, seed=5)
    assert p_lo[0] == p_up[0] == 1.0  # n < 100
    assert p_lo[2] == p_up[2] == 1.0  # nhat < 100
    assert p_lo[1] < 1 and p_lo[3] < 1  # strongly shifted twin is rejected
    again = bootstrap_test(s, seed=5)
    np.testing.assert_array_equal(again[0], p_lo)
    np.testing.assert_array_equal(again[1], p_up)
    d1 = bootstrap_distributions(s, seed=5)
    d2 = bootstrap_distributions(s, seed=6)
    assert not np.array_equal(d1.twin[1], d2.twin[1])
    assert np.all(np.isnan(d1.lo[0])) and d1.eligible.tolist() == [False, True, False, True]
    with pytest.raises(ValueError, match="kind"):
        bootstrap_test(s, kind="bca")
    with pytest.raises(ValueError, match="alpha_grid"):
        bootstrap_test(s, alpha_grid=np.linspace(0, 1, 5))


def test_p_values_take_values_on_the_2_over_b_lattice():
    rng = np.random.default_rng(4)
    s = _samples(rng, 50, 300, 250, 200, shift=rng.uniform(-0.1, 0.1))
    p_lo, p_up = bootstrap_test(s, n_resamples=100, seed=0)
    for p in (p_lo, p_up):
        k = p * 50
        assert np.allclose(k, np.round(k))


def test_authors_grid_variant():
    """Smallest grid alpha at which the level-alpha-per-side rule (linear quantiles) rejects."""
    rng = np.random.default_rng(8)
    s = _samples(rng, 40, 300, 280, 200, shift=-0.02)
    grid = np.linspace(0, 1, 101)
    p_lo, _ = bootstrap_test(s, variant="authors_grid", alpha_grid=grid, seed=2)
    d = bootstrap_distributions(s, seed=2)
    for i in range(len(s)):
        def rej(a, i=i):
            upper = 2 * d.twin_hat[i] - np.quantile(d.twin[i], a)
            lower = 2 * d.lo_hat[i] - np.quantile(d.lo[i], 1 - a)
            return upper < lower
        first = next((a for a in grid if rej(a)), 1.0)
        assert p_lo[i] == pytest.approx(first)
    exact, _ = bootstrap_test(s, seed=2)
    assert np.mean(p_lo <= exact + 1e-12) > 0.9  # alpha (not alpha/2) per side: less conservative


def test_reverse_percentile_coverage_is_close_to_nominal():
    """Asymptotic method: one-sided 95 % bound covers ~95 % (Beta(2,5), n = 200, B = 200)."""
    rng = np.random.default_rng(12)
    reps, b = 1000, 200
    s = _samples(rng, reps, 200, 200, 200)
    d = bootstrap_distributions(s, n_resamples=b, min_n=1, seed=3)
    j = int(np.ceil(0.95 * b)) - 1
    lower = 2 * d.twin_hat - d.twin[:, j]
    cover = np.mean(lower <= 2 / 7)
    assert 0.92 <= cover <= 0.98


def test_all_resamples_separated_is_reported_at_the_floor_and_flagged():
    """p = 0 (every resample separates) becomes the floor: > 0 for Holm, flagged in results."""
    import pandas as pd

    from twinfalsify.falsify import make_methods, run_tests
    from twinfalsify.inference.bootstrap import P_FLOOR, at_floor

    rng = np.random.default_rng(3)
    h = 40
    s = _samples(rng, h, 400, 400, 300)
    # half the twins far below Q_lo: every resample separates; half at the truth
    twin = Ragged.from_groups([np.clip(rng.beta(2, 5, 300) - (0.25 if i < h // 2 else 0), 0, 1)
                               for i in range(h)])
    s = HypothesisSamples(s.y_lo, s.y_up, s.n, s.follow, twin)
    p_lo, _ = bootstrap_test(s, seed=1)
    assert np.all(p_lo > 0)
    assert np.all(p_lo[: h // 2] == P_FLOOR) and np.all(at_floor(p_lo[: h // 2]))
    assert not at_floor(p_lo[h // 2:]).any()
    assert np.all(bootstrap_test(s, seed=1, p_floor=1e-9)[0][: h // 2] == 1e-9)
    with pytest.raises(ValueError, match="p_floor"):
        bootstrap_test(s, seed=1, p_floor=0.05)  # not below the resolution 2/B
    hyps = pd.DataFrame({"hyp_id": np.arange(h), "kind": "causal", "outcome": "HR", "t": 1})
    res = run_tests(hyps, s, np.zeros(h, np.int64),
                    make_methods({"bootstrap": {}, "hoeffding": {}}, 1))
    boot = res[(res["method"] == "bootstrap") & (res["side"] == "lo")]
    assert boot["p_floor"].to_numpy()[: h // 2].all()
    assert boot["rejected"].to_numpy()[: h // 2].all()
    assert not res.loc[res["method"] == "hoeffding", "p_floor"].any()


@pytest.mark.parametrize("seed", range(4))
def test_resample_sums_are_the_reference_draws_bit_for_bit(seed):
    """Same sums and the same generator state after (the draws that follow are the same):
    groups from empty to 30,000 values, rows drawn 0 times, blocks over the draw budget,
    an odd number of 32-bit draws before (a half-used 64-bit output)."""
    from twinfalsify.inference.bootstrap import _resample_sums

    rng = np.random.default_rng(seed)
    sizes = rng.choice([0, 1, 2, 7, 130, 2_000, 30_000], size=40)
    values = Ragged.from_groups([rng.normal(50, 20, k) for k in sizes])
    rows = rng.permutation(np.flatnonzero(sizes > 0))[:25]
    rows = np.concatenate([rows, np.flatnonzero(sizes == 0)[:3]])
    b = 37
    counts = (rng.random((rows.size, b)) * values.sizes[rows][:, None] * 1.5).astype(np.int64)
    counts[rng.random(rows.size) < 0.2] = 0
    g1, g2 = np.random.default_rng(seed + 10), np.random.default_rng(seed + 10)
    g1.integers(0, 1 << 32, 3, dtype=np.int64), g2.integers(0, 1 << 32, 3, dtype=np.int64)
    want = resample_sums_reference(values, rows, counts, g1)
    got = _resample_sums(values, rows, counts, g2)
    assert np.array_equal(got, want) and np.any(want != 0)
    assert g1.bit_generator.state == g2.bit_generator.state
    np.testing.assert_array_equal(g1.integers(0, 1 << 32, 5), g2.integers(0, 1 << 32, 5))
    empty = np.zeros((0, b), np.int64)
    assert _resample_sums(values, rows[:0], empty, g2).shape == (0, b)


def test_bootstrap_p_values_are_the_reference_draws_bit_for_bit(monkeypatch):
    """Whole bootstrap distributions, clipped masses at both ends, refused hypotheses
    (n or nhat below min_n, n = 0, nhat = 0) included: exactly the reference's."""
    from twinfalsify.inference import bootstrap

    rng = np.random.default_rng(11)
    h = 30
    n = rng.integers(0, 600, h)
    n[:2] = 0
    nf = (n * rng.uniform(0.3, 1, h)).astype(np.int64)
    nhat = rng.integers(0, 500, h)
    nhat[2:4] = 0
    follow = Ragged.from_groups([rng.uniform(-0.2, 1.2, k) for k in nf])
    twin = Ragged.from_groups([rng.uniform(-0.3, 1.1, k) for k in nhat])
    s = HypothesisSamples(np.full(h, 0.1), np.full(h, 0.9), n, follow, twin)
    got = bootstrap_distributions(s, n_resamples=64, min_n=20, seed=3)
    p_got = bootstrap_test(s, n_resamples=64, min_n=20, seed=3)
    monkeypatch.setattr(bootstrap, "_resample_sums", resample_sums_reference)
    want = bootstrap_distributions(s, n_resamples=64, min_n=20, seed=3)
    p_want = bootstrap_test(s, n_resamples=64, min_n=20, seed=3)
    for name in ("lo", "up", "twin"):
        assert np.array_equal(getattr(got, name), getattr(want, name), equal_nan=True)
    assert np.array_equal(p_got, p_want) and not np.all(got.eligible)
