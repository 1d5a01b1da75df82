"""Failed twin runs at their own places in the betting test's data order (conservative mode)."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pandas as pd
import pytest
from helpers.studies import OneCellBins
from scipy.stats import beta as beta_dist

from twinfalsify.bounds import TwinNodes, twin_runs
from twinfalsify.design import WHOLE_SPACE
from twinfalsify.inference.betting import (
    _order_keys,
    betting_test,
    default_tune_alpha,
    log_capital,
    twin_candidates,
    worst_twin_sides,
)
from twinfalsify.inference.failures import failure_pvalues
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.schema import FEATURES


def _placed(x_runs: list[np.ndarray], failed: list[np.ndarray], n_obs: int = 80,
            seed: int = 0) -> HypothesisSamples:
    """Hypotheses on [0, 1] whose twin runs 0..len(x)-1 gave ``x`` (NaN: failed at that run);
    the observational side is ``n_obs`` uniform followers."""
    rng = np.random.default_rng(seed)
    h = len(x_runs)
    ok = [np.flatnonzero(~f) for f in failed]
    return HypothesisSamples(
        y_lo=np.zeros(h), y_up=np.ones(h), n=np.full(h, n_obs),
        follow=Ragged.from_groups([rng.uniform(0, 1, n_obs) for _ in range(h)]),
        twin=Ragged.from_groups([x[o] for x, o in zip(x_runs, ok, strict=True)]),
        twin_run=Ragged.from_groups(ok),
        failed_run=Ragged.from_groups([np.flatnonzero(f) for f in failed]),
    )  # fmt: skip


def test_twin_runs_give_each_failed_run_its_plan_index():
    """bounds.twin_runs: the failed run in the middle of the plan keeps its index."""
    k = FEATURES.index("HR")
    values = np.zeros((1, 5, len(FEATURES)))
    values[0, :, k] = [1.0, 2.0, np.nan, 3.0, -1.0]  # run 2 fails; run 4 leaves B_1
    nodes = TwinNodes(index={(1,): 0}, values=values, x0=np.zeros((5, len(FEATURES))))
    hyps = pd.DataFrame({"outcome": ["HR"], "t": [1], "actions": [(1,)],
                         "bins": [(WHOLE_SPACE, 1)]})
    side = twin_runs(hyps, nodes, OneCellBins())
    assert side.values.group(0).tolist() == [1.0, 2.0, 3.0]
    assert side.run.group(0).tolist() == [0, 1, 3]
    assert side.failed_run.group(0).tolist() == [2] and side.n_failed.tolist() == [1]


def test_failed_run_sits_at_its_place_in_the_order():
    """The candidate sequence is the plan order with the failed run in the middle; after the
    data order's permutation it sits where the hash puts plan position 3 of 7, whatever the
    values (and the successful runs keep the order they have without failures)."""
    x = np.array([0.1, 0.2, 0.3, np.nan, 0.5, 0.6, 0.7])
    s = _placed([x], [np.isnan(x)])
    cand, failed = twin_candidates(s)
    assert failed.tolist() == [False, False, False, True, False, False, False]
    np.testing.assert_array_equal(cand.values[~failed], x[~np.isnan(x)])
    perm = _order_keys(np.array([7]), s.hyp_keys, np.zeros(1, np.int64), None, 2)
    tw_lo, tw_up = worst_twin_sides(s, 0.01, order="data")
    where = int(np.flatnonzero(perm == 3)[0])
    assert tw_lo.x[where] == 1.0 and tw_up.x[where] == 0.0
    np.testing.assert_array_equal(np.delete(tw_lo.x, where), np.delete(x[perm], where))
    # another failed run: the successful values do not move, only their bets may
    x2 = x.copy()
    x2[3], x2[0] = 0.4, np.nan
    lo2, _ = worst_twin_sides(_placed([x2], [np.isnan(x2)]), 0.01, order="data")
    assert lo2.x[int(np.flatnonzero(perm == 0)[0])] == 1.0


def _plugin_bet(lam_n):
    """WSR's fixed-n plug-in bet tuned for lam_n values (before the truncation)."""
    def bet(s2, need, left, mm, delta0):
        return math.sqrt(2 * math.log(1 / delta0) / (lam_n * s2))
    return bet


def _star_bet(s2, need, left, mm, delta0, r0=0.5):
    """``capital.star_log_capital``'s bet: sized for the need left over the places left,
    decaying exponentially below r0 (before the truncation)."""
    b = math.sqrt(2 * max(need, r0) / (left * min(s2, mm * (1 - mm))))
    return b * math.exp(min(need - r0, 0.0))


def _brute_capital(x_plan, failed, perm, delta0, m, sign, worst, bet):
    """log max_t K(m) by a loop: runs in plan order permuted by ``perm``; each bet is
    ``bet(sigma2 of the successful values before it, need left, places left, m, delta0)``,
    truncated at c/m (K- as K+ of 1 - x at 1 - m); a failed run contributes x = ``worst``
    (None: the value in ``x_plan``)."""
    c = 0.9
    xs, fs = x_plan[perm], failed[perm]
    mm = m if sign > 0 else 1 - m
    seen: list[float] = []
    mus: list[float] = []
    logk, best = 0.0, 0.0
    for i, (x, f) in enumerate(zip(xs, fs, strict=True)):
        k = len(seen)
        s2 = (0.25 + sum((v - mu) ** 2 for v, mu in zip(seen, mus, strict=True))) / (k + 1)
        b = min(bet(s2, math.log(1 / delta0) - logk, len(xs) - i, mm, delta0), c / mm)
        v = worst if (f and worst is not None) else x
        if not (f and worst is None and np.isnan(x)):  # a failed run that does not enter
            logk += math.log1p(b * ((v if sign > 0 else 1 - v) - mm))
        best = max(best, logk)
        if not f:
            seen.append(x)
            mus.append((0.5 + sum(seen)) / (len(seen) + 1))
    return best


def test_running_max_in_place_matches_a_brute_force_loop_and_dominates():
    """The code's capital with failed runs in place equals a plain loop over the sequence;
    and it is at most the capital of any completion of the failed runs (not entering, or
    any value in [0, 1]) with the same bets: the dominance the validity rests on."""
    rng = np.random.default_rng(4)
    x = rng.beta(2, 5, 60)
    failed = np.zeros(60, bool)
    failed[[3, 17, 18, 40, 59]] = True
    x_obs = np.where(failed, np.nan, x)
    s = _placed([x_obs], [failed])
    delta0 = 0.005
    tw_lo, tw_up = worst_twin_sides(s, delta0, order="data")
    perm = _order_keys(np.array([60]), s.hyp_keys, np.zeros(1, np.int64), None, 2)
    plug = _plugin_bet(60)
    for m in (0.15, 0.3, 0.45, 0.7):
        got_lo = log_capital(tw_lo, np.array([m]), -1)[0]
        got_up = log_capital(tw_up, np.array([m]), +1)[0]
        assert got_lo == pytest.approx(_brute_capital(x_obs, failed, perm, delta0, m, -1, 1.0,
                                                      plug), rel=1e-10, abs=1e-12)
        assert got_up == pytest.approx(_brute_capital(x_obs, failed, perm, delta0, m, +1, 0.0,
                                                      plug), rel=1e-10, abs=1e-12)
        for _ in range(20):  # completions: each failed run absent (NaN) or some value
            comp = np.where(failed, np.where(rng.random(60) < 0.5, np.nan, rng.random(60)), x)
            true_lo = _brute_capital(comp, failed, perm, delta0, m, -1, None, plug)
            true_up = _brute_capital(comp, failed, perm, delta0, m, +1, None, plug)
            assert got_lo <= true_lo + 1e-12 and got_up <= true_up + 1e-12


def test_star_bets_in_place_match_a_brute_force_loop_and_dominate():
    """STaR bets with failed runs in place: equal to a plain loop, and at most the capital of
    any completion (not entering, or any value in [0, 1]) scored with the same variances.
    The bets also read the capital so far; the dominance holds because the next capital is
    non-decreasing in the capital so far (``betting`` module doc, "STaR bets", (a))."""
    rng = np.random.default_rng(14)
    x = rng.beta(2, 5, 60)
    failed = np.zeros(60, bool)
    failed[[0, 3, 17, 18, 40, 59]] = True
    x_obs = np.where(failed, np.nan, x)
    s = _placed([x_obs], [failed])
    perm = _order_keys(np.array([60]), s.hyp_keys, np.zeros(1, np.int64), None, 2)
    for delta0 in (0.005, 0.2):  # 0.2: the capital passes its target (the exponential part)
        tw_lo, tw_up = worst_twin_sides(s, delta0, order="data", star=True)
        for m in (0.05, 0.15, 0.3, 0.45, 0.7):
            got_lo = log_capital(tw_lo, np.array([m]), -1)[0]
            got_up = log_capital(tw_up, np.array([m]), +1)[0]
            assert got_lo == pytest.approx(_brute_capital(
                x_obs, failed, perm, delta0, m, -1, 1.0, _star_bet), rel=1e-10, abs=1e-12)
            assert got_up == pytest.approx(_brute_capital(
                x_obs, failed, perm, delta0, m, +1, 0.0, _star_bet), rel=1e-10, abs=1e-12)
            for _ in range(20):
                comp = np.where(failed, np.where(rng.random(60) < 0.5, np.nan,
                                                 rng.random(60)), x)
                assert got_lo <= _brute_capital(comp, failed, perm, delta0, m, -1, None,
                                                _star_bet) + 1e-12
                assert got_up <= _brute_capital(comp, failed, perm, delta0, m, +1, None,
                                                _star_bet) + 1e-12


def test_without_failed_runs_the_order_and_p_values_do_not_change():
    """No failed run: the same p-values with or without the places (bit for bit)."""
    rng = np.random.default_rng(5)
    xs = [rng.beta(2, 3, k) for k in (30, 50, 70)]
    s = _placed(xs, [np.zeros(len(v), bool) for v in xs])
    bare = s.without_failed()
    for mode in ("conservative", "drop"):
        a = failure_pvalues(betting_test, s, np.zeros(3, np.int64), mode)
        b = failure_pvalues(betting_test, bare, np.zeros(3, np.int64), mode)
        assert all(u.tobytes() == v.tobytes() for u, v in zip(a, b, strict=True))


def test_naming_the_bets_does_not_change_how_failed_runs_are_handled():
    """``bets: star`` written out (as a config does) places the failed runs exactly as the
    default does, bit for bit; plug-in bets place them too (their own p-values), and the
    mixture, which has no order, takes the completions instead (other p-values)."""
    from twinfalsify.inference.failures import _places_failed_runs

    rng = np.random.default_rng(8)
    xs = [rng.beta(2, 3, k) for k in (30, 50, 70)]
    s = _placed(xs, [rng.random(len(v)) < 0.15 for v in xs])
    f = s.failed_run.sizes
    assert f.sum() > 0
    tuned = partial(betting_test, tune_alpha=1e-3)
    named = partial(betting_test, tune_alpha=1e-3, bets="star")
    a = failure_pvalues(tuned, s, f, "conservative")
    b = failure_pvalues(named, s, f, "conservative")
    assert all(u.tobytes() == v.tobytes() for u, v in zip(a, b, strict=True))
    assert _places_failed_runs(named) and _places_failed_runs(partial(betting_test, bets="plugin"))
    assert not _places_failed_runs(partial(betting_test, bets="mixture"))


def _clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1 - level
    lo = 0.0 if k == 0 else float(beta_dist.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta_dist.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def _null_replicates(rng, reps: int, n: int, fail, draw) -> tuple[HypothesisSamples,
                                                                    np.ndarray]:
    """``reps`` replicates at the null boundary Q_twin = Q_lo = Q_up (every trajectory follows;
    twin and D outcomes drawn by ``draw(rng, n)``); run i fails with probability fail(x_i)."""
    obs = [draw(rng, n) for _ in range(reps)]
    runs = [draw(rng, n) for _ in range(reps)]
    failed = [rng.random(n) < fail(x) for x in runs]
    ok = [np.flatnonzero(~f) for f in failed]
    s = HypothesisSamples(
        y_lo=np.zeros(reps), y_up=np.ones(reps), n=np.full(reps, n),
        follow=Ragged.from_groups(obs),
        twin=Ragged.from_groups([x[o] for x, o in zip(runs, ok, strict=True)]),
        twin_run=Ragged.from_groups(ok),
        failed_run=Ragged.from_groups([np.flatnonzero(f) for f in failed]),
    )  # fmt: skip
    return s, np.array([f.sum() for f in failed])


def _bernoulli(rng, n):
    return (rng.random(n) < 0.3).astype(float)


def _beta(rng, n):
    return rng.beta(2, 2, n)


@pytest.mark.parametrize("name, fail, draw", [
    ("fails iff x > Q, Bernoulli", lambda x: (x > 0.5).astype(float), _bernoulli),
    ("P(fail) = x / 2, Bernoulli", lambda x: 0.5 * x, _bernoulli),
    ("fails iff x > Q, Beta(2, 2)", lambda x: (x > 0.6).astype(float), _beta),
])
def test_level_under_outcome_dependent_failures(name, fail, draw):
    """At the null boundary, with failures driven by the outcome, H_lo (the side the failures
    push towards rejection: they remove high twin outcomes) keeps its level at alpha = 0.05:
    the Clopper-Pearson interval of the rejection rate does not lie above alpha (and the rate
    itself does not exceed it). With Bernoulli outcomes failing at x = 1 the worst case is the
    truth, so the check is not vacuous; dropping the failed runs loses the level in every
    setting (so the setting can detect a violation). Larger run:
    benchmarks/bench_failed_places.py."""
    alpha, reps = 0.05, 1000
    s, f = _null_replicates(np.random.default_rng(11), reps, 200, fail, draw)
    method = partial(betting_test, tune_alpha=default_tune_alpha(1))  # each replicate alone
    p_cons, _ = failure_pvalues(method, s, f, "conservative")
    p_drop, _ = failure_pvalues(method, s, f, "drop")
    k = int((p_cons <= alpha).sum())
    lo, hi = _clopper_pearson(k, reps)
    assert lo <= alpha and k / reps <= alpha, (name, k, reps, lo, hi)
    assert _clopper_pearson(int((p_drop <= alpha).sum()), reps)[0] > alpha, name


def test_study_failures_are_placed_counted_and_never_below_drop():
    """On a synthetic study whose twin loses 10 % of its node-runs: twin_runs' failed runs
    are exactly the n_failed that twin_side counts, each entering or failed run appears
    once, and the conservative betting p-values are >= the drop ones, strictly above for
    some hypothesis, and equal wherever nothing failed."""
    import io

    from helpers.studies import build_study

    from twinfalsify import bounds
    from twinfalsify.runs import plan as tp
    from twinfalsify.runs.registry import make_twin

    st = build_study(1500, 3, runs=300)
    twin = make_twin("oracle", {"kind": "oracle"},
                     {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}}})
    runs = pd.concat([tp.run_shard(twin, st.plan, k, st.x0, st.actions, log=io.StringIO())
                      for k in range(len(st.plan.shards))], ignore_index=True)
    nodes = tp.load_nodes(runs, st.plan, st.x0)
    rng = np.random.default_rng(0)
    lost = rng.random(nodes.values.shape[:2]) < 0.1
    nodes.values[lost] = np.nan
    side = bounds.twin_runs(st.hyps, nodes, st.states)
    nf = side.n_failed
    np.testing.assert_array_equal(side.failed_run.sizes, nf)
    for h in range(len(st.hyps)):
        both = np.concatenate([side.run.group(h), side.failed_run.group(h)])
        assert len(np.unique(both)) == len(both)
    s = bounds.hypothesis_samples(st.hyps, st.obs, side)
    cons = failure_pvalues(betting_test, s, nf, "conservative")
    drop = failure_pvalues(betting_test, s, nf, "drop")
    for c, d in zip(cons, drop, strict=True):
        assert np.all(c >= d)
        assert np.array_equal(c[nf == 0], d[nf == 0])
        assert np.any(c[nf > 0] > d[nf > 0])
