"""Betting bounds (Waudby-Smith & Ramdas 2024): coverage, monotonicity, p-value, reference."""

from __future__ import annotations

import numpy as np
import pytest

from twinfalsify.inference.betting import (
    MIX_GRID,
    MIX_RATIO,
    betting_bounds,
    betting_test,
    ordered_sides,
)
from twinfalsify.inference.hoeffding import hoeffding_radius, hoeffding_test
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.union import smallest_rejecting_alpha, union_reject

# a discrete raw outcome whose clipped mean is known exactly: clip to [10, 20]
SUPPORT = np.array([8.0, 12.0, 15.0, 19.0, 22.0])
PROBS = np.array([0.2, 0.3, 0.2, 0.2, 0.1])
CLIPPED_MEAN = float(np.clip(SUPPORT, 10, 20) @ PROBS)  # 14.8


def _replicates(rng, reps, n, p_follow, draw_obs, draw_twin, nhat=None, y=(0.0, 1.0)):
    """reps independent hypotheses = replicates of one design (vectorised Monte Carlo)."""
    nhat = n if nhat is None else nhat
    nf = rng.binomial(n, p_follow, reps)
    follow = Ragged.from_groups([draw_obs(k) for k in nf])
    twin = Ragged.from_groups([draw_twin(nhat) for _ in range(reps)])
    return HypothesisSamples(
        np.full(reps, y[0]), np.full(reps, y[1]), np.full(reps, n, np.int64), follow, twin
    )


CASES = {
    "bernoulli": (lambda r: lambda k: r.binomial(1, 0.3, k).astype(float), 0.3, (0.0, 1.0)),
    "beta": (lambda r: lambda k: r.beta(2, 5, k), 2 / 7, (0.0, 1.0)),
    "discrete_clipped": (lambda r: lambda k: r.choice(SUPPORT, k, p=PROBS), CLIPPED_MEAN,
                         (10.0, 20.0)),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("n", [20, 200])
def test_one_sided_bounds_cover(case, n):
    """Each one-sided (1 - alpha/2) bound covers its mean in >= 95 % of 2,000 replicates."""
    rng = np.random.default_rng(11 + n)
    make, mu, y = CASES[case]
    draw = make(rng)
    p_f, reps, alpha = 0.6, 2000, 0.1
    s = _replicates(rng, reps, n, p_f, draw, draw, y=y)
    b = betting_bounds(s, alpha, tune_alpha=alpha)
    q_lo, q_up = p_f * mu + (1 - p_f) * y[0], p_f * mu + (1 - p_f) * y[1]
    floor = 0.95 - 3 * np.sqrt(0.95 * 0.05 / reps)
    assert np.mean(b["lower_lo"] <= q_lo) >= floor
    assert np.mean(b["upper_up"] >= q_up) >= floor
    assert np.mean(b["lower_twin"] <= mu) >= floor
    assert np.mean(b["upper_twin"] >= mu) >= floor


def test_p_values_valid_at_the_null_boundary():
    """Q_twin = Q_lo exactly: P(p_lo <= a) <= a for a in {0.05, 0.2} (MC 2,000 reps)."""
    rng = np.random.default_rng(5)
    reps, n = 2000, 150
    # Y_lo: followers with prob 1, Beta(2, 2) values: Q_lo = 0.5 = Q_twin
    s = _replicates(rng, reps, n, 1.0, lambda k: rng.beta(2, 2, k), lambda k: rng.beta(2, 2, k))
    p_lo, p_up = betting_test(s, tune_alpha=0.05)
    for a in (0.05, 0.2):
        assert np.mean(p_lo <= a) <= a + 3 * np.sqrt(a * (1 - a) / reps)


def _small_case(seed=3, h=8):
    rng = np.random.default_rng(seed)
    n = rng.integers(60, 300, h)
    nf = (n * rng.uniform(0.6, 1.0, h)).astype(int)
    nh = rng.integers(40, 300, h)
    shift = np.linspace(-0.1, 0.25, h)
    follow = Ragged.from_groups([rng.beta(2, 2, k) for k in nf])
    twin = Ragged.from_groups([np.clip(rng.beta(2, 2, k) - shift[i], 0, 1)
                               for i, k in enumerate(nh)])
    return HypothesisSamples(np.zeros(h), np.ones(h), n.astype(np.int64), follow, twin)


def test_bounds_monotone_in_alpha():
    s = _small_case()
    prev = None
    for a in (1e-8, 1e-4, 0.01, 0.1, 0.5, 1.0):
        b = betting_bounds(s, a, tune_alpha=0.01)
        if prev is not None:  # larger alpha: bounds move inwards
            assert np.all(b["lower_lo"] >= prev["lower_lo"] - 1e-12)
            assert np.all(b["lower_twin"] >= prev["lower_twin"] - 1e-12)
            assert np.all(b["upper_twin"] <= prev["upper_twin"] + 1e-12)
            assert np.all(b["upper_up"] <= prev["upper_up"] + 1e-12)
        prev = b


@pytest.mark.parametrize("bets", [{"bets": "plugin", "orders": 1},
                                  {"bets": "plugin", "orders": 8}, {"bets": "mixture"}])
def test_p_value_is_smallest_rejecting_alpha(bets):
    """Closed-form crossing p == bisection on alpha of the interval rule on the bounds."""
    s = _small_case(h=12)
    p_lo, p_up = betting_test(s, tune_alpha=0.01, **bets)

    def rule(side):
        def reject(alpha):
            b = betting_bounds(s, alpha, tune_alpha=0.01, **bets)
            if side == "lo":
                return union_reject(b["upper_twin"], b["lower_lo"])
            return union_reject(b["upper_up"], b["lower_twin"])
        return reject

    ref_lo = smallest_rejecting_alpha(rule("lo"), len(s), rtol=1e-4)
    ref_up = smallest_rejecting_alpha(rule("up"), len(s), rtol=1e-4)
    assert (p_lo < 0.6).sum() + (p_up < 0.6).sum() >= 2  # the case exercises rejections
    np.testing.assert_allclose(p_lo, ref_lo, rtol=3e-3)
    np.testing.assert_allclose(p_up, ref_up, rtol=3e-3)


def _reference_p(x_large, x_small, delta0, c):
    """Per-hypothesis reference: explicit WSR recursion in Python, crossing by bisection."""

    def bets(x):
        n = len(x)
        lam, s, ss = np.empty(n), 0.0, 0.0
        sig2_prev = 0.25
        for i, xi in enumerate(x, start=1):
            lam[i - 1] = np.sqrt(2 * np.log(1 / delta0) / (n * sig2_prev))  # WSR Thm 3: no c cap
            s += xi
            mu = (0.5 + s) / (i + 1)
            ss += (xi - mu) ** 2
            sig2_prev = (0.25 + ss) / (i + 1)
        return lam

    la, ls = bets(x_large), bets(x_small)

    def logk(x, lam, m, sign):
        cap = c / m if sign > 0 else c / (1 - m)
        return max(0.0, np.max(np.cumsum(np.log(1 + sign * np.minimum(lam, cap) * (x - m)))))

    a, b = 0.0, 1.0
    for _ in range(100):
        m = 0.5 * (a + b)
        if logk(x_large, la, m, +1) >= logk(x_small, ls, m, -1):
            a = m
        else:
            b = m
    k = min(logk(x_large, la, b, +1), logk(x_small, ls, a, -1))
    k = max(k, min(logk(x_large, la, a, +1), logk(x_small, ls, a, -1)))
    return min(1.0, 2 * np.exp(-k))


def test_vectorised_matches_per_hypothesis_reference():
    s = _small_case(seed=9, h=10)
    alpha0, c = 0.01, 0.9
    p_lo, p_up = betting_test(s, tune_alpha=alpha0, c=c, tol=1e-6, bets="plugin", orders=1)
    lo, up, tw = ordered_sides(s, alpha0 / 2, seed=0, c=c, order="data")
    for h in range(len(s)):
        xl = lo.x[lo.offsets[h]: lo.offsets[h + 1]]
        xu = up.x[up.offsets[h]: up.offsets[h + 1]]
        xt = tw.x[tw.offsets[h]: tw.offsets[h + 1]]
        # the order is a permutation of the materialised samples
        np.testing.assert_allclose(np.sort(xl), np.sort(s.obs_side("lo").group(h)))
        np.testing.assert_allclose(np.sort(xu), np.sort(s.obs_side("up").group(h)))
        np.testing.assert_allclose(np.sort(xt), np.sort(s.twin_f.group(h)))
        assert p_lo[h] == pytest.approx(_reference_p(xl, xt, alpha0 / 2, c), rel=1e-4)
        assert p_up[h] == pytest.approx(_reference_p(xt, xu, alpha0 / 2, c), rel=1e-4)


def test_seeded_and_refusals():
    s = _small_case()
    a = betting_test(s, bets="plugin", seed=4)
    b = betting_test(s, bets="plugin", seed=4)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    # n = 0 and nhat = 0 refuse (p = 1) without disturbing the others
    rng = np.random.default_rng(0)
    groups_f = [rng.random(50), np.zeros(0), rng.random(50) * 0.2 + 0.8]
    groups_t = [rng.random(50), rng.random(40), np.zeros(0)]
    z = HypothesisSamples(np.zeros(3), np.ones(3), np.array([50, 0, 50]),
                          Ragged.from_groups(groups_f), Ragged.from_groups(groups_t))
    p_lo, p_up = betting_test(z)
    assert p_lo[1] == p_up[1] == p_lo[2] == p_up[2] == 1.0
    with pytest.raises(ValueError, match="tune_alpha"):
        betting_test(s, tune_alpha=0.0)


@pytest.mark.parametrize("n", [200, 1000])
def test_tighter_than_hoeffding_for_moderate_variance(n):
    """Beta(2, 2) (variance R^2/20), n >= 200, levels 1e-4 and 0.05: never wider than Hoeffding."""
    rng = np.random.default_rng(n)
    s = _replicates(rng, 200, n, 1.0, lambda k: rng.beta(2, 2, k), lambda k: rng.beta(2, 2, k))
    for alpha in (1e-4, 0.05):
        b = betting_bounds(s, alpha, tune_alpha=alpha)
        hoef = hoeffding_radius(1.0, n, alpha)
        assert np.all(s.q_twin_hat - b["lower_twin"] <= hoef)
        assert np.all(b["upper_twin"] - s.q_twin_hat <= hoef)


def test_rejects_more_than_hoeffding_on_shifted_twins():
    rng = np.random.default_rng(2)
    reps, n = 400, 500
    s = _replicates(rng, reps, n, 1.0, lambda k: rng.beta(2, 2, k),
                    lambda k: np.clip(rng.beta(2, 2, k) - 0.06, 0, 1))
    pb, _ = betting_test(s)
    ph, _ = hoeffding_test(s)
    level = 0.05 / reps
    assert (pb <= level).sum() > (ph <= level).sum()


def _avg_reference_p(sides_large, sides_small, delta0, c):
    """Per-hypothesis reference of the order-averaged p: terminal capitals, bisection on m."""
    def logk(xs, m, sign):
        vals = []
        for x in xs:
            n = len(x)
            lam, s_, ss, prev = np.empty(n), 0.0, 0.0, 0.25
            for i, xi in enumerate(x, start=1):
                lam[i - 1] = np.sqrt(2 * np.log(1 / delta0) / (n * prev))
                s_ += xi
                mu = (0.5 + s_) / (i + 1)
                ss += (xi - mu) ** 2
                prev = (0.25 + ss) / (i + 1)
            cap = c / m if sign > 0 else c / (1 - m)
            vals.append(np.sum(np.log1p(sign * np.minimum(lam, cap) * (x - m))))
        return np.log(np.mean(np.exp(vals)))

    return _bisected_p(lambda m: logk(sides_large, m, +1), lambda m: logk(sides_small, m, -1),
                       50)


def _bisected_p(g_dec, g_inc, n_iter):
    """p = min(1, 2 / K*), K* = the crossing of a non-increasing and a non-decreasing log
    capital in m, by plain bisection (a reference for the vectorised search)."""
    a, b = 0.0, 1.0
    for _ in range(n_iter):
        m = 0.5 * (a + b)
        if g_dec(m) >= g_inc(m):
            a = m
        else:
            b = m
    k = max(min(g_dec(b), g_inc(b)), 0.0)
    return min(1.0, 2 * np.exp(-k))


def test_order_average_matches_per_hypothesis_reference():
    """K orders: the p-value is 2 / crossing of the averaged terminal capitals (brute force)."""
    s = _small_case(seed=9, h=6)
    alpha0, c, k = 0.01, 0.9, 4
    p_lo, p_up = betting_test(s, tune_alpha=alpha0, c=c, tol=1e-6, bets="plugin", orders=k)
    lo, up, tw = ordered_sides(s, alpha0 / 2, seed=0, c=c, orders=k, order="data")
    g = len(s)

    def copies(side, h):
        return [side.x[side.offsets[j * g + h]: side.offsets[j * g + h + 1]] for j in range(k)]

    for h in range(g):
        for x in copies(tw, h):  # every copy is a permutation of the same sample
            np.testing.assert_allclose(np.sort(x), np.sort(s.twin_f.group(h)))
        assert not all(np.array_equal(copies(tw, h)[0], x) for x in copies(tw, h)[1:])
        ref_lo = _avg_reference_p(copies(lo, h), copies(tw, h), alpha0 / 2, c)
        ref_up = _avg_reference_p(copies(tw, h), copies(up, h), alpha0 / 2, c)
        assert p_lo[h] == pytest.approx(ref_lo, rel=1e-4)
        assert p_up[h] == pytest.approx(ref_up, rel=1e-4)


@pytest.mark.parametrize("orders", [4, 16])
def test_order_averaged_p_values_valid_at_the_null_boundary(orders):
    """Type-I error by simulation: Q_twin = Q_lo, P(p_lo <= a) <= a (Markov on the average)."""
    rng = np.random.default_rng(15)
    reps, n = 2000, 60
    s = _replicates(rng, reps, n, 1.0, lambda k: rng.beta(2, 5, k), lambda k: rng.beta(2, 5, k))
    p_lo, p_up = betting_test(s, tune_alpha=0.2, bets="plugin", orders=orders)
    for a in (0.05, 0.2, 0.5):
        se = 3 * np.sqrt(a * (1 - a) / reps)
        assert np.mean(p_lo <= a) <= a + se
        assert np.mean(p_up <= a) <= a + se


def test_order_depends_on_the_hypothesis_only():
    """A hypothesis keeps its p-value when tested alone, with others, or among failed-run
    completions (one order per hypothesis key)."""
    s = _small_case(seed=4, h=8)
    p_all = betting_test(s, tune_alpha=0.01, bets="plugin", orders=4)
    idx = np.array([1, 5, 6])
    p_sub = betting_test(s.take(idx), tune_alpha=0.01, bets="plugin", orders=4)
    np.testing.assert_allclose(p_sub[0], p_all[0][idx], rtol=2e-3)
    np.testing.assert_allclose(p_sub[1], p_all[1][idx], rtol=2e-3)
    # without keys the subset's hypotheses would be renumbered and get other orders
    bare = HypothesisSamples(s.y_lo[idx], s.y_up[idx], s.n[idx], s.follow.take(idx),
                             s.twin.take(idx))
    p_bare = betting_test(bare, tune_alpha=0.01, bets="plugin", orders=4)[0]
    assert not np.allclose(p_bare, p_sub[0])


def test_averaging_orders_shrinks_the_seed_spread():
    """Across 5 seeds, p varies much less with K = 16 orders than with one order."""
    rng = np.random.default_rng(21)
    h = 60
    s = _replicates(rng, h, 200, 0.8, lambda k: rng.beta(2, 2, k),
                    lambda k: np.clip(rng.beta(2, 2, k) - 0.2, 0, 1))
    p1, p16 = (np.array([betting_test(s, tune_alpha=1e-3, bets="plugin", orders=k, seed=sd,
                                      order="seed")[0]
                         for sd in range(5)]) for k in (1, 16))
    ok = (p1.max(axis=0) < 0.5) & (p16.max(axis=0) < 0.5)
    assert ok.sum() >= 20

    def spread(p):
        return np.median(np.log(p[:, ok].max(axis=0) / p[:, ok].min(axis=0)))

    one, many = spread(p1), spread(p16)
    assert many < 0.5 * one, (one, many)


# --- order-free grid mixture (bets: mixture) ------------------------------------------------


def _mixture_reference_p(x_large, x_small, delta0, c, grid=MIX_GRID, ratio=MIX_RATIO):
    """Per-hypothesis reference: explicit mixture of J constant bets, bisection on m."""

    def logk(x, m, sign):
        lam_min = np.sqrt(8 * np.log(1 / delta0) / len(x))
        cap = c / m if sign > 0 else c / (1 - m)
        caps = [np.sum(np.log1p(sign * min(lam_min * ratio**j, cap) * (x - m)))
                for j in range(grid)]
        return np.log(np.mean(np.exp(caps)))

    return _bisected_p(lambda m: logk(x_large, m, +1), lambda m: logk(x_small, m, -1), 60)


def test_mixture_matches_per_hypothesis_reference():
    s = _small_case(seed=9, h=10)
    alpha0, c = 0.01, 0.9
    p_lo, p_up = betting_test(s, tune_alpha=alpha0, c=c, tol=1e-6, bets="mixture")
    for h in range(len(s)):
        xl, xu = s.obs_side("lo").group(h), s.obs_side("up").group(h)
        xt = s.twin_f.group(h)
        assert p_lo[h] == pytest.approx(_mixture_reference_p(xl, xt, alpha0 / 2, c), rel=1e-4)
        assert p_up[h] == pytest.approx(_mixture_reference_p(xt, xu, alpha0 / 2, c), rel=1e-4)
    assert (p_lo < 0.5).sum() >= 2 and (p_up < 0.5).sum() >= 1  # rejections exercised


def test_mixture_p_values_are_order_free_and_seed_free():
    """The mixture's p is a symmetric function of each sample: any permutation of the
    followers or of the twin runs, and any seed, give the identical p-value (0 flips)."""
    s = _small_case(seed=12, h=12)
    base = betting_test(s, tune_alpha=1e-3, bets="mixture")
    rng = np.random.default_rng(0)
    perm = HypothesisSamples(
        s.y_lo, s.y_up, s.n,
        Ragged.from_groups([rng.permutation(s.follow.group(h)) for h in range(len(s))]),
        Ragged.from_groups([rng.permutation(s.twin.group(h)) for h in range(len(s))]))
    for sd in range(5):
        other = betting_test(perm, tune_alpha=1e-3, seed=sd, bets="mixture")
        np.testing.assert_allclose(other[0], base[0], rtol=1e-9)
        np.testing.assert_allclose(other[1], base[1], rtol=1e-9)
    # the plug-in bets, by contrast, do see the order
    p1 = [betting_test(s, tune_alpha=1e-3, bets="plugin", orders=1, seed=sd, order="seed")[0]
          for sd in range(3)]
    assert not np.allclose(p1[0], p1[1])


@pytest.mark.parametrize("n", [30, 300])
def test_mixture_p_values_valid_at_the_null_boundary(n):
    """Type-I error by simulation: Q_twin = Q_lo, P(p <= a) <= a (Markov on the mixture)."""
    rng = np.random.default_rng(16 + n)
    reps = 2000
    s = _replicates(rng, reps, n, 1.0, lambda k: rng.beta(2, 5, k), lambda k: rng.beta(2, 5, k))
    p_lo, p_up = betting_test(s, tune_alpha=0.2, bets="mixture")
    for a in (0.05, 0.2, 0.5):
        se = 3 * np.sqrt(a * (1 - a) / reps)
        assert np.mean(p_lo <= a) <= a + se
        assert np.mean(p_up <= a) <= a + se


@pytest.mark.parametrize("opts, match", [
    ({"bets": "kelly"}, "bets must be one of"),
    ({"bets": "mixture", "orders": 4}, "apply to bets: plugin"),
    ({"bets": "mixture", "running_max": True}, "apply to bets: plugin"),
    ({"bets": "mixture", "order": "data"}, "apply to bets: plugin"),
    ({"bets": "plugin", "order": "hash"}, "order must be one of"),
    ({"bets": "mixture", "grid": 0}, "grid must be >= 1"),
    ({"bets": "mixture", "grid_ratio": 1.0}, "grid_ratio > 1"),
    ({"bets": "plugin", "orders": 4, "running_max": True}, "running_max needs orders = 1"),
])
def test_bad_betting_options_are_config_errors(opts, match):
    from twinfalsify.inference.registry import make
    from twinfalsify.schema import ContractError

    with pytest.raises(ValueError, match=match):
        betting_test(_small_case(h=2), **opts)
    # a value's own type/range is named by its key (inference.options), a combination by
    # make_bets' message
    either = r"testing\.methods\.betting(: .*" + match + r"|\.\w+: .* is not allowed)"
    with pytest.raises(ContractError, match=either):
        make("betting", opts, seed=0)


# --- data order (the default: plug-in bets, no seed) -----------------------------------------


def _with_positions(s, rng):
    """``s`` with every follower at a random position among its hypothesis' n entering ones."""
    pos = Ragged.from_groups([rng.permutation(int(s.n[h]))[: s.n_follow[h]].astype(float)
                              for h in range(len(s))])
    return HypothesisSamples(s.y_lo, s.y_up, s.n, s.follow, s.twin, follow_pos=pos)


def test_data_order_is_seed_free():
    """The default p-values do not depend on the seed: 0 decisions can flip across seeds."""
    s = _with_positions(_small_case(seed=12, h=12), np.random.default_rng(1))
    base = betting_test(s, tune_alpha=1e-3)
    assert (base[0] < 0.5).sum() >= 2  # rejections exercised
    for sd in range(1, 5):
        other = betting_test(s, tune_alpha=1e-3, seed=sd)
        np.testing.assert_array_equal(other[0], base[0])
        np.testing.assert_array_equal(other[1], base[1])
    seeded = [betting_test(s, tune_alpha=1e-3, seed=sd, order="seed")[0] for sd in range(2)]
    assert not np.allclose(seeded[0], seeded[1])  # a seeded order does see the seed


def test_hashed_order_equals_a_lexsort_of_the_flat_hash_keys():
    """The compiled per-group sort gives the permutation of one stable lexsort of all hash
    keys (the reference), bit for bit: empty and one-element groups, copies, seeded and
    seedless, both salts, negative and large keys."""
    from helpers.reference import hashed_order_reference

    from twinfalsify.inference.betting import _hashed_order

    rng = np.random.default_rng(11)
    for case in range(12):
        g = int(rng.integers(1, 40))
        sizes = rng.integers(0, 300, g)
        sizes[rng.random(g) < 0.2] = rng.integers(0, 2)
        keys = rng.integers(-2**62, 2**62, g)
        copy = rng.integers(0, 4, g)
        for seed in (None, int(rng.integers(0, 2**31))):
            for salt in (1, 2):
                fast = _hashed_order(sizes, keys, copy, seed, salt)
                ref = hashed_order_reference(sizes, keys, copy, seed, salt)
                np.testing.assert_array_equal(fast, ref, err_msg=f"case {case}, seed {seed}")


def test_rescaled_moments_equal_clip_rescale_order_and_running_moments():
    """The one-pass kernel gives what clipping, rescaling, ordering by a permutation and
    ``running_moments`` give in numpy, bit for bit: empty groups, fill values, values
    outside [y_lo, y_up], ties and negative ranges."""
    from twinfalsify.inference.capital import running_moments
    from twinfalsify.inference.kernels import rescaled_moments

    rng = np.random.default_rng(4)
    for _ in range(10):
        sizes = rng.integers(0, 60, int(rng.integers(1, 12)))
        offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        g = len(sizes)
        y_lo = rng.normal(0, 5, g)
        y_up = y_lo + rng.uniform(0.5, 10, g)
        staged = np.round(rng.normal(0, 8, offs[-1]), 1)  # coarse: ties and clipped values
        real = rng.random(offs[-1]) < 0.7
        perm = np.concatenate([o + rng.permutation(k)
                               for o, k in zip(offs[:-1], sizes, strict=True)]).astype(np.int64)
        gid = np.repeat(np.arange(g), sizes)
        width = y_up - y_lo
        for fill in (0.0, 1.0):
            xs = np.where(real, (np.clip(staged, y_lo[gid], y_up[gid]) - y_lo[gid]) / width[gid],
                          fill)[perm]
            x, sig2 = np.empty(offs[-1]), np.empty(offs[-1])
            rescaled_moments(staged, real, perm, offs, y_lo, y_up, fill, x, sig2)
            assert x.tobytes() == xs.tobytes()
            assert sig2.tobytes() == running_moments(xs, offs)[1].tobytes()


def test_stable_argsort_keeps_tied_keys_in_index_order():
    """Ties in the 53-bit keys (astronomically rare for hashes, so forced here) keep the
    index order, as the stable sort of the reference does."""
    from twinfalsify.inference.kernels import stable_argsort

    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 7, 500):
        bits = rng.integers(0, 5, n).astype(np.uint64)  # many ties
        np.testing.assert_array_equal(stable_argsort(bits), np.argsort(bits, kind="stable"))


def test_numba_is_imported_when_a_test_first_bets_not_before():
    """The kernels' module is imported lazily: the modules every figure and summary job
    imports leave numba out; the first betting test brings it in (a fresh interpreter)."""
    import subprocess
    import sys

    from helpers.paths import SRC

    code = (
        "import sys\n"
        "import twinfalsify.summary, twinfalsify.figures, twinfalsify.twin_tests\n"
        "import twinfalsify.inference.betting as b, twinfalsify.inference.sequential\n"
        "from twinfalsify.inference.samples import HypothesisSamples, Ragged\n"
        "print('numba' in sys.modules)\n"
        "import numpy as np\n"
        "r = Ragged.from_groups([np.array([0.2, 0.5, 0.9])])\n"
        "s = HypothesisSamples(y_lo=np.zeros(1), y_up=np.ones(1), n=np.array([3]),\n"
        "                      follow=r, twin=r)\n"
        "b.betting_test(s, tune_alpha=0.05)\n"
        "print('numba' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={"PYTHONPATH": str(SRC), "MPLBACKEND": "Agg"}, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "True"]


def test_data_order_places_followers_at_their_positions():
    """Brute force: the observational sequence is the stay-order sequence (followers at
    follow_pos, fill values elsewhere) permuted by the seedless hash; the listing order of
    the followers (with their positions) does not matter."""
    from twinfalsify.inference.betting import _order_keys

    rng = np.random.default_rng(5)
    s = _with_positions(_small_case(seed=2, h=6), rng)
    lo, up, _ = ordered_sides(s, 0.01, order="data")
    for h in range(len(s)):
        n = int(s.n[h])
        seq_lo, seq_up = np.zeros(n), np.ones(n)
        p = s.follow_pos.group(h).astype(int)
        seq_lo[p] = seq_up[p] = s.follow_f.group(h)
        perm = _order_keys(np.array([n]), np.array([h]), np.zeros(1, np.int64), None, 1)
        np.testing.assert_array_equal(lo.x[lo.offsets[h]: lo.offsets[h + 1]], seq_lo[perm])
        np.testing.assert_array_equal(up.x[up.offsets[h]: up.offsets[h + 1]], seq_up[perm])
    # shuffle the listing of each hypothesis' followers together with their positions
    shuf = [rng.permutation(s.n_follow[h]) for h in range(len(s))]
    t = HypothesisSamples(
        s.y_lo, s.y_up, s.n,
        Ragged.from_groups([s.follow.group(h)[shuf[h]] for h in range(len(s))]), s.twin,
        follow_pos=Ragged.from_groups([s.follow_pos.group(h)[shuf[h]] for h in range(len(s))]))
    np.testing.assert_array_equal(betting_test(t, tune_alpha=1e-3)[0],
                                  betting_test(s, tune_alpha=1e-3)[0])


def test_follow_pos_checked():
    s = _small_case(h=2)
    bad = Ragged.from_groups([np.arange(s.n_follow[0], dtype=float) + s.n[0],
                              np.zeros(s.n_follow[1])])
    with pytest.raises(ValueError, match="follow_pos"):
        HypothesisSamples(s.y_lo, s.y_up, s.n, s.follow, s.twin, follow_pos=bad)
    dup = Ragged.from_groups([np.zeros(s.n_follow[0]), np.arange(s.n_follow[1], dtype=float)])
    with pytest.raises(ValueError, match="share a position"):
        betting_test(HypothesisSamples(s.y_lo, s.y_up, s.n, s.follow, s.twin, follow_pos=dup))


@pytest.mark.parametrize("p_follow", [0.3, 0.8])
def test_data_order_valid_at_the_null_boundary(p_follow):
    """Type-I error by simulation with followers at random stay positions (as in D):
    Q_twin = Q_lo, P(p_lo <= a) <= a. Y_lo's mean is p_follow E[x]."""
    rng = np.random.default_rng(40 + int(10 * p_follow))
    reps, n = 3000, 80
    mu = p_follow * 2 / 7
    s = _replicates(rng, reps, n, p_follow, lambda k: rng.beta(2, 5, k),
                    lambda k: (rng.random(k) < mu).astype(float))
    s = _with_positions(s, rng)
    p_lo, _ = betting_test(s, tune_alpha=0.2)
    for a in (0.05, 0.2, 0.5):
        assert np.mean(p_lo <= a) <= a + 3 * np.sqrt(a * (1 - a) / reps)


def _sorted_ids_case(rng, reps: int, n: int):
    """reps independent D samples of n stays listed by the outcome (ids ranked by it, as a
    sorted extract): X_0 ~ N(0, 1), outcome y = Phi(X_0 + e / 2) in (0, 1), every stay a
    follower; twin runs from the same law (Q_twin = Q_lo: H_lo and H_up at their boundary).
    Returns the samples without positions, the (reps, n, 2, 2) contents and the outcomes,
    both in id order."""
    from scipy.stats import norm

    x0 = rng.normal(size=(reps, n))
    y = norm.cdf(x0 + 0.5 * rng.normal(size=(reps, n)))
    by = np.argsort(y, axis=1, kind="stable")  # ids ranked by the outcome
    x0, y = np.take_along_axis(x0, by, 1), np.take_along_axis(y, by, 1)
    content = np.stack([np.stack([x0, np.zeros_like(x0)], -1), np.stack([x0, y], -1)], 2)
    twin = norm.cdf(rng.normal(size=(reps, n)) + 0.5 * rng.normal(size=(reps, n)))
    s = HypothesisSamples(np.zeros(reps), np.ones(reps), np.full(reps, n),
                          Ragged.from_groups(list(y)), Ragged.from_groups(list(twin)))
    return s, content, y


def test_ids_sorted_by_the_outcome_keep_the_level_in_the_content_order():
    """Stay ids ranked by the outcome: in the stay-id order (the earlier default) every
    follower's position is its outcome's rank; the keyed hash of each stay's content
    (X_0 and outcome, ``inference.order``) gives positions independent of the outcome, and
    one hypothesis tested in many such studies keeps its level on both sides, for each of
    several hypothesis keys (exact one-sided binomial checks at a = 0.05)."""
    from scipy.stats import binomtest, spearmanr

    from twinfalsify.inference.order import content_keys

    rng = np.random.default_rng(77)
    reps, n, a = 1000, 150, 0.05
    s, content, y = _sorted_ids_case(rng, reps, n)
    keys = content_keys(content.reshape(reps * n, 2, 2), np.zeros((reps * n, 1)), 2026)
    rank = np.argsort(np.argsort(keys[:, 1].reshape(reps, n), axis=1), axis=1)
    by_id = np.tile(np.arange(n), (reps, 1))
    assert spearmanr(by_id.ravel(), y.ravel() + 1e-12 * rng.random(y.size)).statistic > 0.99
    rho = [spearmanr(rank[r], y[r]).statistic for r in range(reps)]
    assert abs(np.mean(rho)) < 4 * np.std(rho) / np.sqrt(reps)  # no trend left
    pos = Ragged.from_groups(list(rank.astype(float)))
    for k in range(3):  # one hypothesis (one key) in reps studies
        t = HypothesisSamples(s.y_lo, s.y_up, s.n, s.follow, s.twin, follow_pos=pos,
                              keys=np.full(reps, k))
        for p in betting_test(t, tune_alpha=a):
            assert binomtest(int((p <= a).sum()), reps, a, alternative="greater").pvalue > 1e-3
