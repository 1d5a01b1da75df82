"""The data order on tied and coarse data: records of identical content keyed by their copy
index, so the betting test holds its level per hypothesis and per key (seed) when many
records tie, the twin's X_0 draw mixes tied X_0, and numbering still changes nothing."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.studies import OneCellBins
from scipy import stats

from twinfalsify import bounds
from twinfalsify.design import WHOLE_SPACE
from twinfalsify.inference.betting import betting_test
from twinfalsify.inference.order import break_ties, content_keys, tied_share, x0_keys
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.runs import plan as tp
from twinfalsify.schema import FEATURES

ALPHA = 0.05
K = FEATURES.index("HR")


def test_break_ties_keeps_distinct_keys_and_separates_copies():
    rng = np.random.default_rng(0)
    distinct = rng.integers(0, 2**63, 50, dtype=np.int64).astype(np.uint64)
    np.testing.assert_array_equal(break_ties(distinct, 3), distinct)  # no tie: unchanged
    tied = np.repeat(distinct[:5], 40)
    out = break_ties(tied, 3)
    assert len(np.unique(out)) == len(out)
    assert tied_share(tied) == 1.0 and tied_share(distinct) == 0.0
    # the first copy keeps its key; the set of keys per content does not depend on row order
    perm = rng.permutation(len(tied))
    again = break_ties(tied[perm], 3)
    for k in distinct[:5]:
        assert set(out[tied == k]) == set(again[tied[perm] == k])
        assert k in set(out[tied == k])


def _study(n: int, p: float, rng: np.random.Generator, seed: int, m: int,
           follow: float = 1.0):
    """One hypothesis (hour 1, whole space, action 1, outcome in [0, 1]) as the workflow builds
    it: every trajectory of D has the same covariates and a binary outcome; a share
    ``follow`` took action 1 (the others action 0); the twin's m outcomes are i.i.d. with
    the followers' mean."""
    x = np.full((n, 2, len(FEATURES)), 50.0)
    x[:, 1, K] = rng.random(n) < p
    actions = (rng.random((n, 1)) < follow).astype(np.int64)
    hyps = pd.DataFrame({"hyp_id": [0], "kind": ["causal"], "outcome": ["HR"], "t": [1],
                         "actions": [(1,)], "bins": [(WHOLE_SPACE, WHOLE_SPACE)],
                         "y_lo": [0.0], "y_up": [1.0]})
    obs = bounds.observational_side(hyps, x, actions, OneCellBins(), t_max=1, order_seed=seed)
    twin = (rng.random(m) < p).astype(float)
    return obs, twin


def _rejection_rates(keys, reps: int, n: int, p: float, m: int, rng,
                     seed: int = 7, follow: float = 1.0) -> np.ndarray:
    """(len(keys), 2): rejection rate of H_lo and H_up per hypothesis key, one hypothesis per
    replicate (the key fixed, as one hypothesis of a study is; a new D each replicate), tuned
    as a one-hypothesis study."""
    groups = {"follow": [], "pos": [], "twin": [], "n": [], "key": []}
    for key in keys:
        for _ in range(reps):
            obs, twin = _study(n, p, rng, seed, m, follow)
            groups["follow"].append(obs.follow.group(0))
            groups["pos"].append(obs.follow_pos.group(0))
            groups["twin"].append(twin)
            groups["n"].append(int(obs.n[0]))
            groups["key"].append(int(key))
    h = len(groups["n"])
    s = HypothesisSamples(np.zeros(h), np.ones(h), np.array(groups["n"], np.int64),
                          Ragged.from_groups(groups["follow"]),
                          Ragged.from_groups(groups["twin"]),
                          keys=np.array(groups["key"], np.int64),
                          follow_pos=Ragged.from_groups(groups["pos"]))
    p_lo, p_up = betting_test(s, tune_alpha=ALPHA / 2)
    rej = np.stack([p_lo <= ALPHA, p_up <= ALPHA], axis=1).reshape(len(keys), reps, 2)
    return rej.mean(axis=1)


@pytest.mark.slow
def test_binary_outcome_identical_covariates_holds_level_per_key():
    """Scan 200 hypothesis keys, then a confirmatory run of 2,000 studies on the worst key and
    side: its rejection rate is not significantly above alpha (one-sided 99 % Clopper-Pearson
    lower bound below alpha). Identical contents sat together and gave 0.24 for the worst key
    (lower bound far above alpha). The default (STaR) bets are nearly exact at the null
    boundary: 10,000 studies on this scan's worst key (101, H_lo) gave 0.0344 [0.030, 0.039],
    so a bound on the other side (upper bound below alpha) would need far more studies."""
    rng = np.random.default_rng(1)
    keys = np.arange(200)
    rates = _rejection_rates(keys, 20, 20, 0.5, 20, rng)
    worst_key, worst_side = np.unravel_index(np.argmax(rates), rates.shape)
    reps = 2000
    confirm = _rejection_rates([keys[worst_key]], reps, 20, 0.5, 20, rng)[0, worst_side]
    hits = int(round(confirm * reps))
    lower = stats.beta.ppf(0.01, hits, reps - hits + 1)  # Clopper-Pearson, one side
    assert lower < ALPHA and confirm <= 1.2 * ALPHA, (keys[worst_key], worst_side, confirm)


def test_tied_contents_are_interleaved_not_blocked():
    """With two contents (outcome 0 or 1, nothing else differs) the followers' positions are
    a random interleaving: the 1s are not one block at either end of the order."""
    rng = np.random.default_rng(2)
    obs, _ = _study(400, 0.5, rng, 7, 10)
    vals = obs.follow.group(0)[np.argsort(obs.follow_pos.group(0))]
    runs = 1 + int(np.sum(vals[1:] != vals[:-1]))
    assert runs > 150  # a random order of 200 + 200 has about 200 runs; blocks have 2


def test_tied_x0_draw_takes_a_random_share_of_each_value():
    """Two X_0 values, each half of D, m = N / 2: the share of one value in the plan varies
    like a hypergeometric draw over seeds (whole blocks gave 0 or 1 only)."""
    n, m = 200, 100
    x0 = np.repeat(np.array([[60.0] * len(FEATURES), [90.0] * len(FEATURES)]), n // 2, axis=0)
    ids = np.arange(1000, 1000 + n)
    hyps = pd.DataFrame({"actions": [(1,)]})
    shares = []
    for seed in range(40):
        plan = tp.plan_twin_runs(hyps, ids, m, 1, seed, x0=x0)
        chosen = np.isin(np.asarray(plan.x0_stay_ids), ids[: n // 2])
        shares.append(chosen.mean())
    shares = np.array(shares)
    assert ((shares > 0.3) & (shares < 0.7)).mean() > 0.9
    assert abs(shares.mean() - 0.5) < 0.05


def test_renumbering_tied_stays_changes_no_x0_sequence():
    """Tied X_0 rows get their copy index by row order, but identical rows are identical: any
    renumbering or reordering of the stays gives the plan the same X_0 sequence."""
    rng = np.random.default_rng(3)
    base = np.round(rng.normal(80, 5, (30, len(FEATURES))))
    x0 = base[rng.integers(0, 30, 300)]  # many exact duplicates
    ids = np.arange(300)
    hyps = pd.DataFrame({"actions": [(1,)]})
    ref = tp.plan_twin_runs(hyps, ids, 120, 1, 5, x0=x0)
    want = x0[np.asarray(ref.x0_stay_ids)]
    for trial in range(3):
        perm = rng.permutation(300)
        new_ids = rng.permutation(10_000)[:300]
        plan = tp.plan_twin_runs(hyps, new_ids, 120, 1, 5, x0=x0[perm])
        pos = {int(s): i for i, s in enumerate(new_ids)}
        got = x0[perm][[pos[int(s)] for s in plan.x0_stay_ids]]
        np.testing.assert_array_equal(got, want, err_msg=f"trial {trial}")


def test_content_keys_equal_x0_keys_and_break_ties_per_hour():
    rng = np.random.default_rng(4)
    x = np.round(rng.normal(0, 1, (50, 3, len(FEATURES))))
    x[10:20] = x[0]  # ten exact copies of row 0
    a = np.ones((50, 2), dtype=np.int64)
    keys = content_keys(x, a, 9)
    np.testing.assert_array_equal(keys[:, 0], x0_keys(x[:, 0], 9))
    for t in range(3):
        assert len(np.unique(keys[:, t])) == 50
