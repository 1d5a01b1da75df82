"""Vectorised bounds and counts agree with a direct per-trajectory implementation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify import bounds, design
from twinfalsify.bounds import TwinNodes
from twinfalsify.design import WHOLE_SPACE, StateBins
from twinfalsify.schema import FEATURES, T_MAX

RNG = np.random.default_rng(11)
OUT = ("HR", "Sodium")


def random_world(n: int, n_actions: int = 3):
    """Random features/actions with few distinct actions so that prefixes match often."""
    x = RNG.normal(size=(n, T_MAX + 1, len(FEATURES)))
    x[:, :, FEATURES.index("sex")] = RNG.integers(0, 2, size=(n, 1))
    x[:, :, FEATURES.index("age")] = RNG.uniform(20, 90, size=(n, 1))
    actions = RNG.integers(0, n_actions, size=(n, T_MAX))
    states = StateBins((40.0, 55.0, 70.0), {k: tuple([0.0] * (T_MAX + 1)) for k in OUT})
    return x, actions, states


def random_hyps(h: int, x, actions, states, manski_share: float = 0.3) -> pd.DataFrame:
    rows = []
    for i in range(h):
        k = OUT[i % 2]
        t = int(RNG.integers(1, T_MAX + 1))
        j = int(
            RNG.integers(len(x))
        )  # copy a real trajectory's (a, B) so that groups are non-empty
        codes = design.state_codes(x, states, k)[j]
        manski = RNG.random() < manski_share
        a = actions[j, :t].tolist() if RNG.random() < 0.8 else RNG.integers(0, 3, t).tolist()
        b = [WHOLE_SPACE] * (t + 1) if manski else codes[: t + 1].tolist()
        rows.append(
            {
                "hyp_id": i,
                "kind": "manski" if manski else "causal",
                "outcome": k,
                "t": t,
                "actions": a,
                "bins": b,
                "y_lo": -0.5,
                "y_up": 0.7,
            }
        )
    return pd.DataFrame(rows)


def brute_obs(hyps, x, actions, states):
    """Direct transcription of docs/explanation/method.md, one trajectory at a time, in the
    data order of hour t (``inference.order``: by the keyed hash of X_0:t, A_1:t)."""
    from twinfalsify.inference.order import content_keys

    keys = content_keys(x, actions, 0)
    out = []
    for _, h in hyps.iterrows():
        codes = design.state_codes(x, states, h.outcome)
        n, follow = 0, []
        for i in np.argsort(keys[:, h.t], kind="stable"):
            big_n = 0
            while big_n < h.t and actions[i, big_n] == h.actions[big_n]:
                big_n += 1
            if all(h.bins[s] in (WHOLE_SPACE, codes[i, s]) for s in range(big_n + 1)):
                n += 1
                if big_n == h.t:  # (value, position among the entering ones, data order)
                    follow.append((x[i, h.t, FEATURES.index(h.outcome)], n - 1))
        out.append((n, sorted(follow)))
    return out


def test_observational_side_matches_brute_force():
    x, actions, states = random_world(300)
    hyps = random_hyps(60, x, actions, states)
    obs = bounds.observational_side(hyps, x, actions, states)
    for h, (n, follow) in enumerate(brute_obs(hyps, x, actions, states)):
        assert obs.n[h] == n
        got = sorted(zip(obs.follow.group(h), obs.follow_pos.group(h), strict=True))
        np.testing.assert_allclose(np.array(got).reshape(-1, 2),
                                   np.array(follow).reshape(-1, 2))


def test_observational_side_chunking_does_not_change_results(monkeypatch):
    x, actions, states = random_world(200)
    hyps = random_hyps(40, x, actions, states)
    whole = bounds.observational_side(hyps, x, actions, states)
    monkeypatch.setattr(bounds, "_CHUNK_CELLS", 200 * 5 * 3)  # 3 hypotheses per chunk
    chunked = bounds.observational_side(hyps, x, actions, states)
    np.testing.assert_array_equal(whole.n, chunked.n)
    np.testing.assert_array_equal(whole.follow.values, chunked.follow.values)
    np.testing.assert_array_equal(whole.follow_pos.values, chunked.follow_pos.values)


def test_bounds_identity_and_sandwich():
    """(Qhat_up - Qhat_lo)/R = 1 - propensity, and Qhat_lo <= naive mean <= Qhat_up."""
    x, actions, states = random_world(400)
    hyps = random_hyps(80, x, actions, states)
    obs = bounds.observational_side(hyps, x, actions, states)
    twin = bounds.Ragged.from_groups([np.zeros(3)] * len(hyps))
    s = bounds.hypothesis_samples(hyps, obs, twin)
    ok = s.n > 0
    np.testing.assert_allclose(((s.q_up_hat - s.q_lo_hat) / s.width)[ok], 1 - s.propensity[ok])
    has = s.n_follow > 0
    assert np.all(s.q_lo_hat[has] <= s.q_obs_hat[has] + 1e-12)
    assert np.all(s.q_obs_hat[has] <= s.q_up_hat[has] + 1e-12)


def test_manski_hypothesis_counts_every_trajectory():
    x, actions, states = random_world(150)
    hyps = random_hyps(30, x, actions, states, manski_share=1.0)
    obs = bounds.observational_side(hyps, x, actions, states)
    assert np.all(obs.n == len(x))


def test_twin_side_matches_brute_force():
    x, actions, states = random_world(50)
    hyps = random_hyps(40, x, actions, states)
    seqs = {tuple(a[:s]) for a in hyps["actions"] for s in range(1, len(a) + 1)}
    index = {s: i for i, s in enumerate(sorted(seqs))}
    m = 120
    values = RNG.normal(size=(len(index), m, len(FEATURES)))
    failed_node, failed_run = 0, 5
    values[failed_node, failed_run, :] = np.nan  # one failed run at the first node
    x0 = x[RNG.integers(0, len(x), m), 0, :]
    nodes = TwinNodes(index=index, values=values, x0=x0)
    side = bounds.twin_runs(hyps, nodes, states)
    twin, n_failed = side.values, side.n_failed
    for h, row in hyps.iterrows():
        k = FEATURES.index(row.outcome)
        base = states.base_codes(x0)
        expected, fails = [], 0
        for i in range(m):
            path = [index[tuple(row.actions[:s])] for s in range(1, row.t + 1)]
            code0 = base[i] + int(x0[i, k] > 0)
            if row.bins[0] not in (WHOLE_SPACE, code0):
                continue
            traj = [values[p, i, k] for p in path]
            if any(np.isnan(v) for v in traj):
                fails += 1
                continue
            codes = [base[i] + int(v > 0) for v in traj]
            if all(row.bins[s + 1] in (WHOLE_SPACE, codes[s]) for s in range(row.t)):
                expected.append(traj[-1])
        np.testing.assert_allclose(np.sort(twin.group(h)), np.sort(expected))
        assert n_failed[h] == fails


@pytest.mark.parametrize("t", [1, 3])
def test_follow_values_are_raw_and_clipped_by_methods(t):
    x, actions, states = random_world(100)
    hyps = random_hyps(10, x, actions, states)
    hyps["t"] = [min(t, len(a)) for a in hyps["actions"]]
    hyps["actions"] = [a[:tt] for a, tt in zip(hyps["actions"], hyps["t"], strict=True)]
    hyps["bins"] = [b[: tt + 1] for b, tt in zip(hyps["bins"], hyps["t"], strict=True)]
    obs = bounds.observational_side(hyps, x, actions, states)
    s = bounds.hypothesis_samples(hyps, obs, bounds.Ragged.from_groups([np.zeros(1)] * 10))
    assert np.all((s.follow_f.values >= -0.5) & (s.follow_f.values <= 0.7))
    assert s.follow.values.min() < -0.5 or s.follow.values.max() > 0.7


def test_renumbering_or_reordering_the_stays_changes_no_follower_position():
    """The data order is a keyed hash of each trajectory's content: listing D's stays in
    another order (any renumbering) gives every follower the same position, and the positions
    do not follow the outcome even when the rows are sorted by it."""
    x, actions, states = random_world(300)
    hyps = random_hyps(60, x, actions, states)
    base = bounds.observational_side(hyps, x, actions, states, order_seed=7)
    for perm in (RNG.permutation(len(x)), np.argsort(x[:, 1, FEATURES.index("HR")])):
        got = bounds.observational_side(hyps, x[perm], actions[perm], states, order_seed=7)
        np.testing.assert_array_equal(got.n, base.n)
        for h in range(len(hyps)):
            a = sorted(zip(base.follow.group(h), base.follow_pos.group(h), strict=True))
            b = sorted(zip(got.follow.group(h), got.follow_pos.group(h), strict=True))
            assert a == b
    other = bounds.observational_side(hyps, x, actions, states, order_seed=8)
    assert not np.array_equal(other.follow_pos.values, base.follow_pos.values)  # seed keyed
