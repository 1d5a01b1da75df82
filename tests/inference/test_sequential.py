"""Sequential (anytime-valid) testing: confidence-sequence coverage, exact futility,
early rejection consistent with the p-value, prefix-reuse accounting."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.paths import ROOT

from twinfalsify.inference.betting import OrderedSide, log_capital
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import ObservationalSide, Ragged, TwinRuns
from twinfalsify.inference.sequential import (
    CURTAILED,
    FUTILE,
    REJECTED,
    UNDECIDED,
    SequentialState,
    future_bet_bound,
    horizon_bets,
    node_runs,
    run_to_stop,
)


def ref_bet(succ: list[float], seen_b0: int, left_b0: int, delta0: float) -> float:
    """The twin bet at a run with X_0 in B_0, from scratch: sigma2 from the successful entering
    values before it (WSR's running plug-in), n = max(i, E + rho R) with
    rho = (E + 1/2) / (S + 1) (module doc)."""
    total = dev = 0.0
    for t, x in enumerate(succ, 1):
        total += x
        dev += (x - (0.5 + total) / (t + 1)) ** 2
    e = len(succ)
    sig2 = (0.25 + dev) / (e + 1)
    n = max(e + 1.0, e + (e + 0.5) / (seen_b0 + 1.0) * left_b0)
    return float(np.sqrt(2.0 * np.log(1.0 / delta0) / (sig2 * n)))


def ref_bets(x_runs: np.ndarray, enter: np.ndarray, in_b0: np.ndarray, delta0: float
             ) -> np.ndarray:
    """Plain loop over runs in X_0 order: the bet placed at every entering run."""
    out, succ = [], []
    for j in range(len(in_b0)):
        if enter[j]:
            out.append(ref_bet(succ, int(in_b0[:j].sum()), int(in_b0[j:].sum()), delta0))
            succ.append(float(x_runs[j]))
    return np.array(out)


def twin_side(x: np.ndarray, enter: np.ndarray, in_b0: np.ndarray, delta0: float
              ) -> OrderedSide:
    """(G, n) runs in X_0 order -> the twin side of G groups (entering runs only)."""
    g = x.shape[0]
    cb = np.concatenate([np.zeros((g, 1), np.int64), np.cumsum(in_b0, axis=1)], axis=1)
    gi, j = np.nonzero(enter)
    offs = np.concatenate([[0], np.cumsum(enter.sum(axis=1))]).astype(np.int64)
    seen, left = cb[gi, j], cb[gi, -1] - cb[gi, j]
    return OrderedSide(x[gi, j], horizon_bets(x[gi, j], offs, np.full(g, delta0), seen, left),
                       offs)


def test_horizon_bets_match_a_plain_loop_and_are_predictable():
    """The vectorised bets equal a run-by-run loop; a bet reads only the values before it and
    the plan (X_0 in B_0), never a later value nor the final number of entering runs."""
    rng = np.random.default_rng(0)
    g, n = 5, 300
    in_b0 = rng.random((g, n)) < [[0.2], [0.5], [0.8], [1.0], [0.05]]
    enter = in_b0 & (rng.random((g, n)) < [[0.9], [0.3], [0.7], [1.0], [0.5]])
    x = rng.beta(2, 5, (g, n))
    side = twin_side(x, enter, in_b0, 0.01)
    for k in range(g):
        np.testing.assert_allclose(side.lam[side.offsets[k]:side.offsets[k + 1]],
                                   ref_bets(x[k], enter[k], in_b0[k], 0.01), rtol=1e-12)
    # a later value, or whether later runs enter, changes no earlier bet
    y, late = x.copy(), enter.copy()
    y[:, 150:] = 1 - y[:, 150:]
    late[:, 150:] = in_b0[:, 150:]
    for other, ent in ((twin_side(y, enter, in_b0, 0.01), enter),
                       (twin_side(x, late, in_b0, 0.01), late)):
        for k in range(g):
            e = int(enter[k, :151].sum())  # entering runs up to run 150 included
            a, b = side.offsets[k], other.offsets[k]
            # (to rounding: the flat cumulative sums restart per group by subtraction)
            np.testing.assert_allclose(other.lam[b:b + e], side.lam[a:a + e], rtol=1e-12)
            np.testing.assert_allclose(other.lam[b:other.offsets[k + 1]],
                                       ref_bets(y[k] if ent is enter else x[k], ent[k],
                                                in_b0[k], 0.01), rtol=1e-12)
        assert not np.allclose(other.lam[-20:], side.lam[-20:])  # later bets do change


def test_future_bet_bound_dominates_every_continuation():
    """Brute force over continuations: whatever the future values and entering pattern, the
    bet at the s-th remaining run with X_0 in B_0 never exceeds the bound lambdabar_s."""
    rng = np.random.default_rng(6)
    budget, d0 = 120, 1e-4
    for frac in (1.0, 0.4):
        in_b0 = rng.random(budget) < frac
        for j in (0, 1, 10, 60, 110):  # runs revealed
            for rate in (1.0, 0.6, 0.1):
                enter_past = in_b0[:j] & (rng.random(j) < rate)
                x_past = rng.beta(2, 5, j)
                succ = x_past[enter_past]
                side = OrderedSide(succ, None, np.array([0, len(succ)]))
                seen, r = int(in_b0[:j].sum()), int(in_b0[j:].sum())
                fb = future_bet_bound(side, np.array([len(succ)]), np.array([seen]),
                                      np.array([r]), np.array([d0]))
                bound = fb.bets()
                assert len(bound) == r
                futures = [(np.zeros(budget), np.ones(budget, bool)),
                           (np.ones(budget), np.ones(budget, bool)),
                           (np.tile([0.0, 1.0], budget // 2), np.ones(budget, bool)),
                           (rng.random(budget), rng.random(budget) < 0.5),
                           (np.zeros(budget), np.arange(budget) >= budget - 5),  # late entries
                           (np.zeros(budget), np.arange(budget) % 7 == 0)]
                futures += [(rng.random(budget) ** 3, rng.random(budget) < p)
                            for p in (0.05, 0.3, 0.9)]
                for fut_x, fut_enter in futures:
                    xs = np.concatenate([x_past, fut_x[j:]])
                    ent = np.concatenate([enter_past, in_b0[j:] & fut_enter[j:]])
                    # bet at every remaining run with X_0 in B_0 (entering or not)
                    s_pos = np.flatnonzero(in_b0[j:]) + j
                    lam = [ref_bet(list(xs[:q][ent[:q]]), int(in_b0[:q].sum()),
                                   int(in_b0[q:].sum()), d0) for q in s_pos]
                    assert np.all(np.array(lam) <= bound * (1 + 1e-12)), (frac, j, rate)


@pytest.mark.parametrize("dist", ["bernoulli", "beta"])
def test_confidence_sequence_is_time_uniform(dist):
    """P(exists t <= n: K_t(true mean) >= 1/delta) <= delta, for K+ and K- (Ville), with the
    horizon bets on runs that enter at random among those with X_0 in B_0."""
    rng = np.random.default_rng(1)
    g, n, delta = 4000, 400, 0.1
    if dist == "bernoulli":
        x, mu = (rng.random((g, n)) < 0.3).astype(float), 0.3
    else:
        x, mu = rng.beta(2, 2, (g, n)), 0.5
    in_b0 = rng.random((g, n)) < 0.6
    enter = in_b0 & (rng.random((g, n)) < 0.7)
    side = twin_side(x, enter, in_b0, delta)  # bets tuned at the level tested: least favourable
    m = np.full(g, mu)
    se = np.sqrt(delta * (1 - delta) / g)
    for sign in (+1, -1):
        hit = log_capital(side, m, sign, running_max=True) >= np.log(1 / delta)
        assert hit.mean() <= delta + 3 * se, (sign, hit.mean())
        assert hit.mean() > 0.005  # the test has teeth: the sequence does get near the level


def concat_worlds(parts: list) -> tuple:
    """One study from several ``_world`` outputs (hypotheses stacked in order)."""
    hyps = pd.concat([p[0] for p in parts], ignore_index=True)
    obs = ObservationalSide(np.concatenate([p[1].n for p in parts]), Ragged.from_groups(
        [g for p in parts for g in (p[1].follow.group(i) for i in range(len(p[1].follow)))]))
    runs = TwinRuns(
        Ragged.from_groups([p[2].values.group(i) for p in parts for i in range(len(p[2].values))]),
        np.concatenate([p[2].run for p in parts]),
        np.concatenate([p[2].in_b0 for p in parts]), np.concatenate([p[2].failed for p in parts]))
    return hyps, obs, runs


def _world(h: int, n_obs: int, m: int, q_lo: float, twin_mean: float, propensity: float,
           rng: np.random.Generator, b0_frac: float = 1.0):
    """h hypotheses in [0, 1]: obs followers Beta-ish around q/propensity, twin Bernoulli-ish."""
    hyps = pd.DataFrame({"y_lo": 0.0, "y_up": 1.0, "kind": "causal"}, index=range(h))
    nf = rng.binomial(n_obs, propensity, h)
    # follower mean f_mean so that Q_lo = propensity * f_mean = q_lo
    f_mean = min(q_lo / propensity, 1.0)
    follow = Ragged.from_groups([rng.beta(4 * f_mean, 4 * (1 - f_mean), k) for k in nf])
    obs = ObservationalSide(n=np.full(h, n_obs), follow=follow)
    in_b0 = rng.random((h, m)) < b0_frac
    enter = in_b0 & (rng.random((h, m)) < 0.8)
    hh, ii = np.nonzero(enter)
    vals = rng.beta(4 * twin_mean, 4 * (1 - twin_mean), len(hh))
    sizes = np.bincount(hh, minlength=h)
    runs = TwinRuns(Ragged(vals, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)),
                    ii.astype(np.int64), in_b0, np.zeros((h, m), bool))
    return hyps, obs, runs


@pytest.mark.parametrize(("curtail", "combine"), [(0.0, "union"), (0.2, "union")])
def test_p_values_at_the_stopping_time_are_valid_at_the_null_boundary(curtail, combine):
    """Twin mean = Q_lo (H_lo true, at its boundary): P(p_lo <= a) <= a at data-dependent stops
    (Holm-aware futility and, opt-in, curtailment only choose the stops), for both rules."""
    rng = np.random.default_rng(2)
    h = 2000
    hyps, obs, runs = _world(h, 300, 400, q_lo=0.4, twin_mean=0.4, propensity=1.0, rng=rng)
    st = SequentialState(hyps, obs, None, budget=400, batch_size=25, alpha=0.05,
                         n_family=np.full(h, 20),  # lenient a* = 0.0025: more early stops
                         curtail=curtail, combine=combine)
    run_to_stop(st, runs)
    p_lo, _, _ = st.p_values(runs)
    for a in (0.05, 0.2, 0.5):
        assert (p_lo <= a).mean() <= a + 3 * np.sqrt(a * (1 - a) / h), a


def test_p_values_stay_valid_for_both_sides_when_few_runs_can_enter():
    """Null boundary for H_lo and H_up at once (twin mean = Q_lo = Q_up), a quarter of the X_0
    in B_0: the horizon n_i is then estimated from few runs early on, and P(p <= a) <= a per
    side at the data-dependent stops."""
    rng = np.random.default_rng(13)
    h = 2000
    hyps, obs, runs = _world(h, 300, 400, q_lo=0.4, twin_mean=0.4, propensity=1.0, rng=rng,
                             b0_frac=0.25)
    st = SequentialState(hyps, obs, None, budget=400, batch_size=25, n_family=np.full(h, 20))
    run_to_stop(st, runs)
    p_lo, p_up, nhat = st.p_values(runs)
    assert 50 < nhat.mean() < 90  # about 400 x 0.25 x 0.8 entering runs at the budget
    for p in (p_lo, p_up):
        for a in (0.05, 0.2, 0.5):
            assert (p <= a).mean() <= a + 3 * np.sqrt(a * (1 - a) / h), a
    assert (p_lo <= 0.5).mean() > 0.1  # the test has teeth: p-values are not all 1


def _state(hyps, obs, runs, budget, batch, **kw) -> SequentialState:
    st = SequentialState(hyps, obs, None, budget=budget, batch_size=batch, **kw)
    run_to_stop(st, runs)
    return st


def test_futility_never_loses_a_rejection_and_early_rejection_matches_p():
    """Brute force: the same data run to the budget without stopping (one batch)."""
    rng = np.random.default_rng(3)
    h, m = 600, 600
    parts = [_world(h // 4, 400, m, 0.4, tm, 0.7, rng, b0_frac=0.3) for tm in (0.05, 0.15, 0.3)]
    # L > 1/2: the K- bet at L is truncated at c/(1-L) > 2c, so the future factor exceeds 1 + c
    parts.append(_world(h // 4, 400, m, 0.8, 0.7, 0.95, rng, b0_frac=0.3))
    hyps, obs, runs = concat_worlds(parts)
    nf = np.full(h, 2 * h)
    seq = _state(hyps, obs, runs, m, 20, n_family=nf)
    full = _state(hyps, obs, runs, m, m, n_family=nf, holm_aware=False)  # batch 0, then all
    p_full_lo, p_full_up, _ = full.p_values(runs)
    p_lo, p_up, _ = seq.p_values(runs)
    dec = seq.side
    assert (dec == REJECTED).sum() > 20 and (dec == FUTILE).sum() > 20  # both rules act
    # futile at level a (alpha, or Holm-aware alpha/2^q): not reachable with the whole budget
    lvl = seq.fut_level
    assert np.all(p_full_lo[dec[:, 0] == FUTILE] > lvl[dec[:, 0] == FUTILE, 0])
    assert np.all(p_full_up[dec[:, 1] == FUTILE] > lvl[dec[:, 1] == FUTILE, 1])
    assert (lvl[dec == FUTILE] < 0.05).sum() > 10  # Holm-aware futility acts
    # ... and Holm on the full-budget p-values rejects none of the futile sides
    holm_full = correct(np.concatenate([p_full_lo, p_full_up]), 0.05, "holm").reshape(2, -1).T
    assert not holm_full[dec == FUTILE].any()
    # early rejection verified exactly at a*: the crossing p agrees (to its tolerance)
    a_star = 0.05 / nf
    assert np.all(p_lo[dec[:, 0] == REJECTED] <= a_star[0])
    assert np.all(p_full_lo[dec[:, 0] == REJECTED] <= a_star[0] * 1.003)
    # sides still undecided at the budget agree with the fixed computation at the budget
    both = (seq.stop_batch == seq.n_batches) & (dec[:, 0] == UNDECIDED)
    # (to the crossing's tolerance: tol = 1e-3 on log K*, and chunked cumulative sums round
    # differently when the other hypotheses differ)
    np.testing.assert_allclose(p_lo[both], p_full_lo[both], rtol=1.1e-3)
    # stopping saved runs, Holm-aware futility more
    plain = _state(hyps, obs, runs, m, 20, n_family=nf, holm_aware=False)
    assert seq.runs_used().mean() < plain.runs_used().mean() < 0.8 * m
    # opt-in curtailment acts and saves runs in total (a curtailed side is not counted as
    # primary-futile, so an individual other side may then run longer)
    cur = _state(hyps, obs, runs, m, 20, n_family=nf, curtail=0.2)
    assert (cur.side == CURTAILED).any() and cur.runs_used().sum() < seq.runs_used().sum()
    assert not (cur.fut_level[cur.side == CURTAILED] > 0).any()


def test_no_twin_run_when_the_observational_bound_is_uninformative():
    """Obs lower bound at alpha is 0 (no followers): H_lo futile before any run is simulated."""
    rng = np.random.default_rng(4)
    hyps, obs, runs = _world(50, 200, 300, 0.4, 0.1, 1.0, rng)
    obs = ObservationalSide(obs.n, Ragged.from_groups([np.zeros(0)] * 50))  # Y_lo = y_lo only
    st = _state(hyps, obs, runs, 300, 50, n_family=np.full(50, 100))
    assert np.all(st.side[:, 0] == FUTILE)
    assert np.all(st.side[:, 1] == FUTILE)  # Y_up = y_up only: upper bound 1, never rejectable
    assert np.all(st.stop_batch == 0) and np.all(st.runs_used() == 0)


def test_node_runs_count_prefix_reuse():
    """Node hours = max over hypotheses whose path uses the node (worked by hand)."""
    paths = np.array([[0, -1], [0, 1], [0, 2], [3, -1]])  # a, a-b, a-c, d
    per_hyp = np.array([10, 40, 25, 0])
    np.testing.assert_array_equal(node_runs(paths, per_hyp, 4), [40, 40, 25, 0])


def test_bad_input_raises():
    rng = np.random.default_rng(5)
    hyps, obs, _ = _world(3, 20, 10, 0.4, 0.4, 1.0, rng)
    with pytest.raises(ValueError, match="batch_size"):
        SequentialState(hyps, obs, None, budget=10, batch_size=0)
    bad = hyps.assign(y_up=0.0)
    with pytest.raises(ValueError, match="y_up must exceed y_lo"):
        SequentialState(bad, obs, None, budget=10, batch_size=5)


@pytest.mark.parametrize(("eps", "most_lost"), [(0.05, 0.10), (0.2, 0.30)])
def test_curtailment_forgoes_few_rejections_the_full_budget_makes(eps, most_lost):
    """Curtailment's estimated probability is a *predictive* one (the mean increment is
    itself estimated): of the sides the full budget rejects at a*, the share curtailed stays
    near epsilon even with small batches. Conditional power at the plug-in mean (variance
    r v only) curtailed 32 % of them here at epsilon 0.05 (batch 10)."""
    rng = np.random.default_rng(7)
    h, m = 600, 800
    hyps, obs, runs = concat_worlds(
        [_world(h // 3, 400, m, 0.4, tm, 1.0, rng, b0_frac=0.5) for tm in (0.22, 0.26, 0.30)])
    nf = np.full(h, 2 * h)
    full = _state(hyps, obs, runs, m, m, n_family=nf, holm_aware=False)
    win = full.p_values(runs)[0] <= 0.05 / nf  # rejected at a* with the whole budget
    cur = _state(hyps, obs, runs, m, 10, n_family=nf, curtail=eps)
    lost = win & (cur.side[:, 0] == CURTAILED)
    assert win.sum() > 300 and (cur.side[:, 0] == CURTAILED).sum() > 100  # both act
    assert lost.sum() <= most_lost * win.sum(), (lost.sum(), win.sum())
    assert cur.runs_used().mean() < 0.5 * m  # and it does save runs


def _failing_world(h: int, m: int, q_lo: float, rng: np.random.Generator, fail_above: float,
                   fail_prob: float):
    """``_world`` at the null boundary (twin mean = Q_lo over *all* entering runs), where a run
    whose outcome would exceed ``fail_above`` fails with probability ``fail_prob``: failures
    that depend on the outcome, so the successful runs alone understate the twin mean."""
    hyps, obs, _ = _world(h, 300, m, q_lo, q_lo, 1.0, rng)
    enter = rng.random((h, m)) < 0.8
    hh, ii = np.nonzero(enter)
    vals = rng.beta(4 * q_lo, 4 * (1 - q_lo), len(hh))
    fail = (vals > fail_above) & (rng.random(len(hh)) < fail_prob)
    failed = np.zeros((h, m), bool)
    failed[hh[fail], ii[fail]] = True
    ok = ~fail
    sizes = np.bincount(hh[ok], minlength=h)
    runs = TwinRuns(Ragged(vals[ok], np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)),
                    ii[ok].astype(np.int64), np.ones((h, m), bool), failed)
    return hyps, obs, runs


def test_conservative_capital_bets_the_next_runs_bet_on_each_failed_run_at_the_worst_value():
    """Brute force, run by run: a failed run multiplies K- by 1 - min(lambda, c/(1-m)) (1 - m)
    (K+ by 1 - min(lambda, c/m) m), lambda being the bet of its own place (read from the
    successful runs before it and the plan); a successful run as in the drop capital."""
    rng = np.random.default_rng(11)
    hyps, obs, runs = _failing_world(6, 120, 0.4, rng, fail_above=0.5, fail_prob=0.5)
    runs.failed[0] = False  # a hypothesis without failures: its capital is the drop one
    # some runs that neither enter nor fail have X_0 outside B_0 (the plan's S and R vary)
    entered = np.zeros_like(runs.in_b0)
    entered[np.repeat(np.arange(6), runs.values.sizes), runs.run] = True
    runs.in_b0[~entered & ~runs.failed & (rng.random(runs.in_b0.shape) < 0.7)] = False
    st = SequentialState(hyps, obs, None, budget=120, batch_size=10, n_family=np.full(6, 20))
    groups, upto = np.arange(6), np.full(6, 90)  # failures after the last revealed run too
    sides, nhat = st._twin_prefix(runs, upto, groups)
    drop = SequentialState(hyps, obs, None, budget=120, batch_size=10, n_family=np.full(6, 20),
                           failed_runs="drop")._twin_prefix(runs, upto, groups)[0]
    c, d0 = 0.9, st.delta0[0]
    for m in (0.2, 0.45, 0.7):
        mm = np.full(6, m)
        got_lo = log_capital(sides.lo, mm, -1, False)
        got_up = log_capital(sides.up, mm, +1, False)
        for g in groups:
            succ, lo, up = [], 0.0, 0.0
            pos = runs.run[runs.values.offsets[g]:runs.values.offsets[g + 1]]
            vals = runs.values.group(g)
            for j in range(90):
                b0 = runs.in_b0[g]
                lam = ref_bet(succ, int(b0[:j].sum()), int(b0[j:120].sum()), d0)
                b_lo, b_up = min(lam, c / (1 - m)), min(lam, c / m)
                if runs.failed[g, j]:
                    lo += np.log1p(-b_lo * (1 - m))
                    up += np.log1p(-b_up * m)
                elif j in pos:
                    x = vals[np.flatnonzero(pos == j)[0]]
                    lo += np.log1p(-b_lo * (x - m))
                    up += np.log1p(b_up * (x - m))
                    succ.append(x)
            assert got_lo[g] == pytest.approx(lo, abs=1e-10)
            assert got_up[g] == pytest.approx(up, abs=1e-10)
        # worst case never helps rejection; without failures it is the drop capital exactly
        assert np.all(got_lo <= log_capital(drop.lo, mm, -1, False) + 1e-12)
        assert got_lo[0] == log_capital(drop.lo, mm, -1, False)[0]
    assert runs.failed[1:, :90].any() and np.array_equal(nhat, drop.succ.sizes)


@pytest.mark.parametrize(("combine", "curtail"), [("union", 0.0), ("union", 0.2)])
def test_conservative_failures_keep_p_values_valid_when_failures_depend_on_the_outcome(combine,
                                                                                       curtail):
    """Twin mean = Q_lo over all entering runs, but high outcomes tend to fail: dropping the
    failures rejects the true H_lo far too often; the conservative capital stays valid, at
    data-dependent stops, and on the same data its p-value is never below the drop one."""
    rng = np.random.default_rng(12)
    h = 2000
    hyps, obs, runs = _failing_world(h, 400, 0.4, rng, fail_above=0.5, fail_prob=0.5)
    p, p_at_budget = {}, {}
    for mode in ("drop", "conservative"):
        st = SequentialState(hyps, obs, None, budget=400, batch_size=25, n_family=np.full(h, 20),
                             combine=combine, failed_runs=mode, curtail=curtail)
        run_to_stop(st, runs)
        p[mode] = st.p_values(runs)[0]
        if curtail == 0.0:  # (once is enough: this part does not depend on the stops)
            # the same data for both (the stops above differ): one batch of the whole budget
            st = _state(hyps, obs, runs, 400, 400, n_family=np.full(h, 20), failed_runs=mode,
                        holm_aware=False)
            p_at_budget[mode] = st.p_values(runs)[0]
    if p_at_budget:  # (to the union crossing's tolerance, 1e-3 on log K*)
        assert np.all(p_at_budget["conservative"] >= p_at_budget["drop"] * (1 - 1.1e-3))
        assert (p_at_budget["conservative"] > 1.5 * p_at_budget["drop"]).mean() > 0.5
    for a in (0.05, 0.2, 0.5):
        se = 3 * np.sqrt(a * (1 - a) / h)
        assert (p["conservative"] <= a).mean() <= a + se, a
    assert (p["drop"] <= 0.05).mean() > 0.05 + 3 * np.sqrt(0.05 * 0.95 / h)  # teeth


def test_product_rule_is_refused_with_its_reason():
    """combine: product was withdrawn: with the twin's X_0 drawn from the observational
    sample it exceeded its level, so the library refuses it (no silent fallback)."""
    rng = np.random.default_rng(0)
    hyps, obs, _ = _world(5, 50, 60, q_lo=0.4, twin_mean=0.4, propensity=1.0, rng=rng)
    with pytest.raises(ValueError, match="combine: product was removed: it can exceed its level"):
        SequentialState(hyps, obs, None, budget=10, batch_size=5, combine="product")
    with pytest.raises(ValueError, match="combine must be one of union, got 'sum'"):
        SequentialState(hyps, obs, None, budget=10, batch_size=5, combine="sum")


def test_a_config_naming_the_product_rule_gets_one_line_saying_why():
    """The study config is refused at parse time with the reason, not a bare "not one of"."""

    import yaml

    from twinfalsify.studyconfig import study_config_error

    root = ROOT
    cfg = yaml.safe_load((root / "config" / "config.yaml").read_text())
    cfg.setdefault("twin_runs", {})["combine"] = "product"
    msg = study_config_error(cfg, root / "workflow" / "schemas" / "config.schema.yaml")
    assert msg is not None and "\n" not in msg
    assert msg.startswith("config key twin_runs.combine: product was removed")
    assert "exceed its level" in msg
    cfg["twin_runs"]["combine"] = "union"
    assert "combine" not in (study_config_error(cfg, root / "workflow" / "schemas"
                                                / "config.schema.yaml") or "")
