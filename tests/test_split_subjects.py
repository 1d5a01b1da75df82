"""Repeat patients: the D0 / D split keeps a patient's stays on one side, and X_0 draws take
one stay per patient while they can; without a subject column nothing changes."""

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


def test_x0_draws_one_stay_per_patient_first():
    df = _stays()
    hyps = pd.DataFrame({"actions": [(0,)]})
    subjects = dict(zip(df[STAY_ID].tolist(), df[SUBJECT_ID].tolist(), strict=True))
    for seed in range(10):
        plain = plan_twin_runs(hyps, df[STAY_ID].to_numpy(), None, 1, seed)
        grouped = plan_twin_runs(hyps, df[STAY_ID].to_numpy(), None, 1, seed, subjects=subjects)
        x = grouped.x0_stay_ids
        assert sorted(x) == sorted(plain.x0_stay_ids)  # the same stays, reordered
        first = [subjects[s] for s in x[:40]]
        assert len(set(first)) == 40  # every patient once before any twice
        # within the first round, the permutation's order
        pos = {s: i for i, s in enumerate(plain.x0_stay_ids)}
        assert [pos[s] for s in x[:40]] == sorted(pos[s] for s in x[:40])
        # 30 draws: 30 patients
        part = plan_twin_runs(hyps, df[STAY_ID].to_numpy(), 30, 1, seed, subjects=subjects)
        assert len({subjects[s] for s in part.x0_stay_ids}) == 30
    # one stay per patient: exactly the old draws
    one = {s: s for s in df[STAY_ID].tolist()}
    assert plan_twin_runs(hyps, df[STAY_ID].to_numpy(), 25, 1, 4, subjects=one).x0_stay_ids == \
        plan_twin_runs(hyps, df[STAY_ID].to_numpy(), 25, 1, 4).x0_stay_ids


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
