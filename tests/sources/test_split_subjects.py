"""Repeat patients: the D0 / D split keeps a patient's stays on one side, and the twin's X_0
are a sample of D's stays (law of X_0 = law of D's stays, repeat stays included, in an order
that follows no covariate); without a subject column nothing changes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify.runs.plan import plan_twin_runs
from twinfalsify.schema import STAY_ID, SUBJECT_ID, TIME, ContractError, validate_trajectories
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.split import split_stays


def _stays(n_subjects: int = 40, seed: int = 0) -> pd.DataFrame:
    """One row per stay; subject k has 1 + (k mod 4) stays (as the demo: one patient with
    many stays, most with one), stay ids interleaved across subjects."""
    subj = np.repeat(np.arange(n_subjects), 1 + np.arange(n_subjects) % 4)
    ids = np.random.default_rng(seed).permutation(len(subj)) + 1000
    return pd.DataFrame({STAY_ID: ids, TIME: 0, SUBJECT_ID: subj})


@pytest.mark.parametrize("seed", range(20))
def test_no_subject_on_both_sides(seed):
    df = _stays()
    d0, d = split_stays(df, 0.4, seed)
    assert not set(d0[SUBJECT_ID]) & set(d[SUBJECT_ID])
    assert d0[SUBJECT_ID].nunique() == 16  # floor(0.4 x 40) patients
    assert len(d0) + len(d) == len(df) and not set(d0[STAY_ID]) & set(d[STAY_ID])
    again, _ = split_stays(df.sample(frac=1, random_state=seed), 0.4, seed)  # row order
    assert set(again[STAY_ID]) == set(d0[STAY_ID])


def test_the_per_stay_split_mixes_patients_and_equals_the_old_one():
    df = _stays()
    mixed = 0
    for seed in range(20):
        d0, d = split_stays(df, 0.4, seed, by="stay")
        mixed += bool(set(d0[SUBJECT_ID]) & set(d[SUBJECT_ID]))
        # the paper's split: floor(0.4 n) stays, the first of a permutation of sorted ids
        perm = np.random.default_rng(seed).permutation(np.sort(df[STAY_ID].unique()))
        assert set(d0[STAY_ID]) == set(perm[: int(0.4 * len(df))].tolist())
    assert mixed >= 18  # 60 % of the stays belong to repeat patients: nearly always


def test_without_subjects_by_subject_is_by_stay():
    traj = SyntheticWorld(n_stays=200).sample_observational(1)
    a0, a = split_stays(traj, 0.2, 3)
    b0, b = split_stays(traj, 0.2, 3, by="stay")
    pd.testing.assert_frame_equal(a0, b0)
    pd.testing.assert_frame_equal(a, b)
    with pytest.raises(ContractError, match="split.by"):
        split_stays(traj, 0.2, 3, by="patient")


def test_x0_law_equals_the_stays_law_with_repeat_patients():
    """Over 10,000 plans (seeds) with m < |D|: the share of X_0 from patients with 4 stays
    equals their share of D's stays (hypergeometric z-test), every stay is drawn equally often
    (chi-square), and the list order follows neither the patient's stay count nor X_0 (the
    order is a keyed hash of X_0, not the stay numbering: ids here sorted by X_0)."""
    from scipy import stats

    df = _stays()
    x0 = np.random.default_rng(1).normal(size=(len(df), 2))
    order = np.argsort(x0[:, 0])
    ids = np.sort(df[STAY_ID].to_numpy())  # stay ids ranked by the covariate: worst case
    ids_by_row = np.empty(len(df), np.int64)
    ids_by_row[order] = ids
    n_stays = df.groupby(SUBJECT_ID)[STAY_ID].transform("size").to_numpy()
    many = dict(zip(ids_by_row.tolist(), (n_stays == 4).tolist(), strict=True))
    cov = dict(zip(ids_by_row.tolist(), x0[:, 0].tolist(), strict=True))
    hyps = pd.DataFrame({"actions": [(0,)]})
    big, m, reps = len(df), 30, 10_000
    share = np.mean(list(many.values()))
    drawn = np.zeros(big)
    pos_index = {s: i for i, s in enumerate(ids_by_row.tolist())}
    n_many, first_half_cov, second_half_cov, many_pos = 0, [], [], []
    for seed in range(reps):
        x = plan_twin_runs(hyps, ids_by_row, m, 1, seed, x0=x0).x0_stay_ids
        flags = np.array([many[s] for s in x])
        n_many += flags.sum()
        drawn[[pos_index[s] for s in x]] += 1
        c = np.array([cov[s] for s in x])
        first_half_cov.append(c[: m // 2].mean())
        second_half_cov.append(c[m // 2:].mean())
        many_pos.extend(np.flatnonzero(flags).tolist())
    # share: each plan's count is hypergeometric(N = big, K = share N, m)
    var = m * share * (1 - share) * (big - m) / (big - 1)
    z = (n_many - reps * m * share) / np.sqrt(reps * var)
    assert abs(z) < 4, (n_many / (reps * m), share)
    # every stay equally likely (expected reps m / N each)
    assert stats.chisquare(drawn).pvalue > 1e-4
    # order: repeat stays are not pushed to the end; the covariate does not trend
    assert abs(np.mean(many_pos) - (m - 1) / 2) < 4 * np.sqrt((m * m - 1) / 12 / len(many_pos))
    d = np.array(first_half_cov) - np.array(second_half_cov)
    assert abs(d.mean()) < 4 * d.std() / np.sqrt(reps)


def test_contract_keeps_and_checks_the_subject_column():
    traj = SyntheticWorld(n_stays=20).sample_observational(1)
    traj[SUBJECT_ID] = traj[STAY_ID] // 2
    out = validate_trajectories(traj)
    assert (out[SUBJECT_ID] == out[STAY_ID] // 2).all()
    bad = traj.copy()
    bad.loc[bad.index[0], SUBJECT_ID] = -7
    with pytest.raises(ContractError, match="more than one subject"):
        validate_trajectories(bad)
    assert SUBJECT_ID not in validate_trajectories(traj.drop(columns=SUBJECT_ID))
