"""Failed twin runs in the statistics: conservative (worst case) vs drop (the paper)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from twinfalsify.falsify import make_methods, run_tests
from twinfalsify.inference.failures import (
    augment,
    conservative_pvalues,
    failure_pvalues,
    hoeffding_worst_k,
)
from twinfalsify.inference.hoeffding import hoeffding_test
from twinfalsify.inference.samples import HypothesisSamples, Ragged


def _samples(rng: np.random.Generator, h: int) -> tuple[HypothesisSamples, np.ndarray]:
    y_lo = rng.normal(0, 1, h)
    y_up = y_lo + rng.uniform(0.5, 3, h)
    n = rng.integers(0, 60, h)
    n_follow = np.array([rng.integers(0, k + 1) for k in n])
    follow = [rng.uniform(lo - 1, up + 1, k)
              for lo, up, k in zip(y_lo, y_up, n_follow, strict=True)]
    nhat = rng.integers(0, 60, h)
    # twin means shifted either way so that many p-values are small
    shift = rng.normal(0, 1.5, h)
    twin = [rng.uniform(lo, up, k) + s
            for lo, up, k, s in zip(y_lo, y_up, nhat, shift, strict=True)]
    samples = HypothesisSamples(y_lo, y_up, n, Ragged.from_groups(follow), Ragged.from_groups(twin))
    return samples, rng.integers(0, 40, h)


def _brute(method, samples, n_failed):
    """max over every k = 0..F, one hypothesis at a time (independent reference)."""
    p_lo = np.empty(len(samples))
    p_up = np.empty(len(samples))
    for h in range(len(samples)):
        one = samples.take([h])
        ks = range(int(n_failed[h]) + 1)
        p_lo[h] = max(method(augment(one, np.array([k]), one.y_up))[0][0] for k in ks)
        p_up[h] = max(method(augment(one, np.array([k]), one.y_lo))[1][0] for k in ks)
    return p_lo, p_up


def _generic_hoeffding(samples):
    """Hoeffding hidden behind a plain function: takes the generic (non closed-form) path."""
    return hoeffding_test(samples)


@pytest.mark.parametrize("seed", range(5))
def test_conservative_never_below_drop(seed):
    samples, f = _samples(np.random.default_rng(seed), 80)
    for method in (hoeffding_test, _generic_hoeffding):
        drop = failure_pvalues(method, samples, f, "drop")
        cons = failure_pvalues(method, samples, f, "conservative")
        for d, c in zip(drop, cons, strict=True):
            assert np.all(c >= d)
        # no failures: both modes agree exactly
        zero = failure_pvalues(method, samples, np.zeros_like(f), "conservative")
        assert all(np.array_equal(a, b) for a, b in zip(zero, drop, strict=True))
    assert (cons[0] > drop[0]).any()  # the failures matter somewhere


@pytest.mark.parametrize("seed", range(3))
def test_hoeffding_all_k_matches_brute_force(seed):
    samples, f = _samples(np.random.default_rng(100 + seed), 30)
    p_lo, p_up, k_lo, k_up = hoeffding_worst_k(samples, f)
    b_lo, b_up = _brute(hoeffding_test, samples, f)
    np.testing.assert_allclose(p_lo, b_lo, rtol=1e-12, atol=0)
    np.testing.assert_allclose(p_up, b_up, rtol=1e-12, atol=0)
    assert np.all((0 <= k_lo) & (k_lo <= f)) and np.all((0 <= k_up) & (k_up <= f))
    # the generic path (k in {0, F, Hoeffding argmax}) is exact for Hoeffding
    g_lo, g_up = conservative_pvalues(_generic_hoeffding, samples, f)
    np.testing.assert_allclose(g_lo, b_lo, rtol=1e-12, atol=0)
    np.testing.assert_allclose(g_up, b_up, rtol=1e-12, atol=0)


def test_hand_worked_example():
    # R = 1; 400 observational followers at 1 -> Qhat_lo = 1; 50 twin runs at 0.5; 150 failed.
    samples = HypothesisSamples(
        y_lo=np.array([0.0]), y_up=np.array([1.0]), n=np.array([400]),
        follow=Ragged.from_groups([np.ones(400)]), twin=Ragged.from_groups([np.full(50, 0.5)]),
    )  # fmt: skip
    f = np.array([150])
    # drop: d = 1 - 0.5, p = 2 exp(-2 d^2 / (400^-1/2 + 50^-1/2)^2)
    p_drop = 2 * math.exp(-2 * 0.5**2 / (1 / 20 + 50**-0.5) ** 2)
    # k failed runs at y_up = 1: d_k = 1 - (25 + k)/(50 + k) = 25/(50 + k) and the
    # Hoeffding z_k = d_k / (400^-1/2 + (50 + k)^-1/2) decreases in k: worst case k = F = 150
    p_cons = 2 * math.exp(-2 * (25 / 200) ** 2 / (1 / 20 + 200**-0.5) ** 2)
    assert p_drop == pytest.approx(2.36e-6, rel=1e-2)  # 2 exp(-13.65)
    assert p_cons == pytest.approx(0.234, rel=1e-2)  # 2 exp(-2.145)
    drop = failure_pvalues(hoeffding_test, samples, f, "drop")
    cons = failure_pvalues(hoeffding_test, samples, f, "conservative")
    assert drop[0][0] == pytest.approx(p_drop, rel=1e-12)
    assert cons[0][0] == pytest.approx(p_cons, rel=1e-12)
    assert hoeffding_worst_k(samples, f)[2][0] == 150
    # H_up side: the twin is below Q_up anyway, failures at y_lo cannot make it reject
    assert drop[1][0] == 1.0 and cons[1][0] == 1.0


def test_no_successful_runs_but_failures_is_untestable():
    samples = HypothesisSamples(
        y_lo=np.array([0.0]), y_up=np.array([1.0]), n=np.array([100]),
        follow=Ragged.from_groups([np.ones(100)]), twin=Ragged.from_groups([np.zeros(0)]),
    )  # fmt: skip
    p_lo, p_up = failure_pvalues(hoeffding_test, samples, np.array([30]), "conservative")
    assert p_lo[0] == 1.0 and p_up[0] == 1.0


def test_unknown_mode_names_the_key():
    samples, f = _samples(np.random.default_rng(0), 3)
    with pytest.raises(ValueError, match="testing.failed_runs"):
        failure_pvalues(hoeffding_test, samples, f, "ignore")


def test_study_rejection_under_drop_disappears_under_conservative():
    """A biased twin that fails most of its runs: drop rejects, conservative does not."""
    hyps = pd.DataFrame({
        "hyp_id": [0, 1], "kind": ["causal", "causal"], "outcome": ["HR", "HR"], "t": [1, 1],
        "y_lo": [60.0, 60.0], "y_up": [120.0, 120.0],
    })  # fmt: skip
    rng = np.random.default_rng(3)
    follow = Ragged.from_groups([rng.uniform(95, 120, 300), rng.uniform(95, 120, 300)])
    # hypothesis 0: 200 ok runs near 70 (far too low) and 300 failed runs;
    # hypothesis 1: the same runs, no failures
    twin = Ragged.from_groups([rng.normal(70, 3, 200), rng.normal(70, 3, 200)])
    samples = HypothesisSamples(hyps.y_lo.to_numpy(), hyps.y_up.to_numpy(),
                                np.array([300, 300]), follow, twin)
    n_failed = np.array([300, 0])
    methods = make_methods({"hoeffding": {}}, 0)
    drop = run_tests(hyps, samples, n_failed, methods, failed_runs="drop")
    cons = run_tests(hyps, samples, n_failed, methods, failed_runs="conservative")
    lo = lambda r: r[r.side == "lo"].set_index("hyp_id")  # noqa: E731
    assert lo(drop).loc[0, "rejected"] and lo(drop).loc[1, "rejected"]
    assert not lo(cons).loc[0, "rejected"] and lo(cons).loc[1, "rejected"]
    assert (cons["p_value"].to_numpy() >= drop["p_value"].to_numpy()).all()
    assert set(cons["failed_runs"]) == {"conservative"} and set(drop["failed_runs"]) == {"drop"}
    assert lo(cons).loc[0, "n_failed"] == 300


def test_failed_run_counted_only_if_it_could_have_entered():
    """n_failed: a run failing at hour 2 counts unless its hour 1 already left B_1."""
    from helpers.studies import OneCellBins

    from twinfalsify.bounds import TwinNodes, twin_runs
    from twinfalsify.design import WHOLE_SPACE
    from twinfalsify.schema import FEATURES

    k = FEATURES.index("HR")
    index = {(1,): 0, (1, 2): 1}
    values = np.zeros((2, 3, len(FEATURES)))
    values[0, :, k] = [1.0, -1.0, 1.0]  # hour 1: runs 0, 2 in B_1 (code 1), run 1 not
    values[1, :, k] = [np.nan, np.nan, 5.0]  # runs 0 and 1 fail in hour 2
    nodes = TwinNodes(index=index, values=values, x0=np.zeros((3, len(FEATURES))))
    hyps = pd.DataFrame({"outcome": ["HR", "HR"], "t": [2, 2], "actions": [(1, 2), (1, 2)],
                         "bins": [(WHOLE_SPACE, 1, WHOLE_SPACE), (WHOLE_SPACE,) * 3]})
    side = twin_runs(hyps, nodes, OneCellBins())
    twin, n_failed = side.values, side.n_failed
    assert list(n_failed) == [1, 2]  # run 1 left B_1 in hour 1: cannot enter hypothesis 0
    assert list(twin.group(0)) == [5.0] and list(twin.group(1)) == [5.0]


@pytest.mark.parametrize("bets", [{"bets": "plugin", "seed": 3, "orders": 4, "order": "seed"},
                                  {}, {"bets": "mixture"}])
def test_betting_worst_case_uses_one_order_and_the_family_tuning(bets):
    """Every completion k is evaluated with the hypothesis' own orders (plug-in bets; the
    mixture has none) and the tuning of the whole family: equal to evaluating the
    completions on the full set of hypotheses."""
    from functools import partial

    from twinfalsify.inference.betting import betting_test, default_tune_alpha
    from twinfalsify.inference.failures import hoeffding_worst_k

    rng = np.random.default_rng(12)
    h = 40
    s, _ = _samples(rng, h)
    s = s.take(np.flatnonzero((s.n > 0) & (s.nhat > 0)))
    h = len(s)
    f = np.where(np.arange(h) % 2 == 0, 0, rng.integers(1, 8, h))
    method = partial(betting_test, **bets)
    got_lo, got_up = conservative_pvalues(method, s, f)
    full = partial(betting_test, **bets, tune_alpha=default_tune_alpha(h))
    ref_lo, ref_up = full(s)
    _, _, k_lo, k_up = hoeffding_worst_k(s, f)
    for k in (f, k_lo):
        ref_lo = np.maximum(ref_lo, full(augment(s, k, s.y_up))[0])
    for k in (f, k_up):
        ref_up = np.maximum(ref_up, full(augment(s, k, s.y_lo))[1])
    np.testing.assert_allclose(got_lo, ref_lo, rtol=2e-3)
    np.testing.assert_allclose(got_up, ref_up, rtol=2e-3)
    assert (np.minimum(got_lo, got_up)[f > 0] < 1).sum() >= 2  # completions exercised


def test_betting_is_tuned_per_family_in_run_tests():
    """run_tests tunes the betting test at alpha / (2H) with H the parameter sets of each
    hypothesis' own family (kind), with and without failed runs: each family's p-values equal
    a separate call on that family alone at its own tuning, and differ from tuning over all."""
    from functools import partial

    from twinfalsify.inference.betting import betting_test, default_tune_alpha

    rng = np.random.default_rng(21)
    s, f = _samples(rng, 60)
    keep = np.flatnonzero((s.n > 0) & (s.nhat > 0))
    s, f = s.take(keep), f[keep]
    h = len(s)
    kind = np.where(np.arange(h) % 3 == 0, "manski", "causal")
    hyps = pd.DataFrame({"hyp_id": np.arange(h), "kind": kind, "outcome": "HR", "t": 1})
    for n_failed in (np.zeros(h, np.int64), np.where(np.arange(h) % 2 == 0, f, 0)):
        res = run_tests(hyps, s, n_failed, make_methods({"betting": {}}, 0, alpha=0.1),
                        alpha=0.1)
        for k in ("causal", "manski"):
            idx = np.flatnonzero(kind == k)
            alone = partial(betting_test, alpha=0.1,
                            tune_alpha=default_tune_alpha(len(idx), 0.1))
            ref = failure_pvalues(alone, s.take(idx), n_failed[idx], "conservative")
            for side, p in zip(("lo", "up"), ref, strict=True):
                got = res[(res["side"] == side)].set_index("hyp_id").loc[idx, "p_value"]
                np.testing.assert_array_equal(got.to_numpy(), p)
    pooled, _ = betting_test(s, alpha=0.1, tune_alpha=default_tune_alpha(h, 0.1))
    got = res[res["side"] == "lo"].set_index("hyp_id").loc[np.arange(h), "p_value"].to_numpy()
    assert not np.array_equal(got[got < 1], pooled[got < 1])
