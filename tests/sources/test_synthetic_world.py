"""The synthetic world: contract, confounding, exact interventional law, valid bounds."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify import bounds, design, noise
from twinfalsify.schema import FEATURES, STAY_ID, TIME, to_array, validate_trajectories
from twinfalsify.sources.synthetic import SyntheticWorld

WORLD = SyntheticWorld(n_stays=40_000)


@pytest.fixture(scope="module")
def cohort() -> pd.DataFrame:
    return WORLD.sample_observational(seed=5)


def test_contract_and_plausible_ranges(cohort):
    out = validate_trajectories(cohort, source="synthetic")
    assert out[STAY_ID].nunique() == WORLD.n_stays
    assert set(out[TIME]) == {0, 1, 2, 3, 4}
    used = out[out[TIME] < 4]
    assert 0.2 < (used["iv_fluid"] == 0).mean() < 0.9  # many exact zeros, as in ICU data
    assert 0.7 < (used["vasopressor"] == 0).mean() < 0.97
    assert 7.2 < out["Arterial_pH"].quantile(0.01) and out["Arterial_pH"].quantile(0.99) < 7.6


def test_same_seed_same_cohort_and_other_seed_differs():
    a = SyntheticWorld(n_stays=300).sample_observational(1)
    pd.testing.assert_frame_equal(a, SyntheticWorld(n_stays=300).sample_observational(1))
    assert not a.equals(SyntheticWorld(n_stays=300).sample_observational(2))


def test_treated_patients_are_sicker_confounding(cohort):
    """Vasopressor at hour 0 is given to patients with lower blood pressure at hour 1 even
    though the drug raises blood pressure: the naive contrast has the wrong sign."""
    x = to_array(cohort, FEATURES)
    vaso0 = cohort[cohort[TIME] == 0]["vasopressor"].to_numpy() > 0
    sbp1 = x[:, 1, FEATURES.index("SysBP")]
    assert sbp1[vaso0].mean() < sbp1[~vaso0].mean() - 5


def test_posterior_of_u_is_exact():
    """Regressing U on X_0 by simulation recovers the closed-form posterior mean and sd."""
    rng = np.random.default_rng(0)
    w = SyntheticWorld(n_stays=1)
    n = 200_000
    age = rng.uniform(20, 90, n).round()
    sex = (rng.random(n) < 0.5).astype(float)
    u = rng.standard_normal(n)
    m = w.baseline_mean(age, sex)
    z = m + w._vec(2) * u[:, None] + w._vec(1) * rng.standard_normal(m.shape)
    demo = np.column_stack([age, sex, np.full(n, 80.0)])
    x0 = pd.DataFrame(w.features_frame(demo, z, rng.standard_normal(n)), columns=list(FEATURES))
    mean, sd = w.posterior_u(x0)
    resid = u - mean
    assert abs(resid.mean()) < 0.01
    assert resid.std() == pytest.approx(sd[0], rel=0.01)
    assert abs(np.corrcoef(resid, mean)[0, 1]) < 0.01  # E[U | X_0] is the posterior mean


def test_oracle_matches_a_randomised_trial_in_the_world():
    """Giving everyone a fixed dose sequence in the world (a trial) and simulating the same
    sequence with the oracle from the trial's X_0 give the same law of X_1:4."""
    doses = np.array([[400.0, 0.3], [400.0, 0.3], [0.0, 0.0], [150.0, 0.0]])
    trial = SyntheticWorld(n_stays=40_000).sample_observational(9, fixed_doses=doses)
    x = to_array(trial, FEATURES)
    x0 = pd.DataFrame(x[:, 0, :], columns=list(FEATURES))
    seeds = noise.combine(np.uint64(3), np.arange(len(x0), dtype=np.uint64))
    sim = WORLD.simulate_interventional(x0, np.broadcast_to(doses, (len(x0), 4, 2)).copy(), seeds)
    _assert_same_law(x, sim, ("SysBP", "HR", "Chloride", "HCO3", "Glucose", "MeanBP"))


def _assert_same_law(x: np.ndarray, sim: np.ndarray, features: tuple[str, ...]) -> None:
    """Trial hours x[:, t] and oracle hours sim[:, t - 1] (t = 1, 4) agree in mean, sd and,
    conditionally on X_0 and not just marginally, in their covariance with the initial state."""
    for k in features:
        j = FEATURES.index(k)
        for t in (1, 4):
            a, b = x[:, t, j], sim[:, t - 1, j]
            se = np.sqrt(a.var() / len(a) + b.var() / len(b))
            assert abs(a.mean() - b.mean()) < 4 * se, (k, t)
            assert b.std() == pytest.approx(a.std(), rel=0.04), (k, t)
            ca = np.cov(a, x[:, 0, j])[0, 1]
            cb = np.cov(b, x[:, 0, j])[0, 1]
            assert cb == pytest.approx(ca, rel=0.1, abs=0.05 * a.var()), (k, t)


def test_oracle_prefix_consistency():
    """Hour s depends only on doses 1..s: sequences sharing a prefix share those hours."""
    x0 = WORLD.sample_observational(2).query("t == 0").head(50)[list(FEATURES)]
    seeds = np.arange(50, dtype=np.uint64)
    a = np.broadcast_to(np.array([[100.0, 0.0], [0.0, 0.2], [50.0, 0.0]]), (50, 3, 2)).copy()
    b = a.copy()
    b[:, 2] = [400.0, 0.5]
    sa = WORLD.simulate_interventional(x0, a, seeds)
    sb = WORLD.simulate_interventional(x0, b, seeds)
    np.testing.assert_array_equal(sa[:, :2], sb[:, :2])
    assert not np.allclose(sa[:, 2], sb[:, 2])
    np.testing.assert_array_equal(
        sa[:10], WORLD.simulate_interventional(x0[:10], a[:10], seeds[:10])
    )


def test_true_interventional_mean_lies_within_bounds(cohort):
    """Monte-Carlo E[f(X_t(a)) | X_0:t(a) in B_0:t] of the world is inside [Q_lo, Q_up]
    computed on a large observational sample (the paper's theorem), for a sample of
    causal and Manski hypotheses, up to Monte-Carlo error."""
    d0 = cohort[cohort[STAY_ID] < cohort[STAY_ID].min() + 2000]
    d = cohort[~cohort[STAY_ID].isin(d0[STAY_ID])]
    actions = design.fit_action_bins(d0)
    states = design.fit_state_bins(d0)
    hyps, _ = design.build_hypotheses(d0, actions, states, min_support=20)
    hyps = hyps.groupby(["kind", "t"]).head(6).reset_index(drop=True)
    x = to_array(d, FEATURES)
    obs = bounds.observational_side(hyps, x, design.action_codes(d, actions), states)
    # a fresh population from the world, every member given a_1:t by intervention
    pop = to_array(SyntheticWorld(n_stays=60_000).sample_observational(77), FEATURES)
    x0 = pd.DataFrame(pop[:, 0, :], columns=list(FEATURES))
    seeds = np.arange(len(x0), dtype=np.uint64)
    checked = 0
    for _, h in hyps.iterrows():
        seq = np.asarray(h.actions)
        sim = WORLD.simulate_interventional(
            x0, np.broadcast_to(actions.doses(seq), (len(x0), len(seq), 2)).copy(), seeds
        )
        traj = np.concatenate([pop[:, :1, :], sim], axis=1)
        codes = design.state_codes(
            np.pad(traj, ((0, 0), (0, 4 - len(seq)), (0, 0)), mode="edge"), states, h.outcome
        )[:, : h.t + 1]
        inside = np.all((np.asarray(h.bins) == -1) | (codes == np.asarray(h.bins)), axis=1)
        if inside.sum() < 200:
            continue
        f = np.clip(traj[inside, h.t, FEATURES.index(h.outcome)], h.y_lo, h.y_up)
        q_true, q_se = f.mean(), f.std() / np.sqrt(len(f))
        i = int(h.name)
        fol = np.clip(obs.follow.group(i), h.y_lo, h.y_up)
        n, nf = obs.n[i], len(fol)
        q_lo = (fol.sum() + (n - nf) * h.y_lo) / n
        q_up = (fol.sum() + (n - nf) * h.y_up) / n
        slack = 4 * (q_se + (h.y_up - h.y_lo) / np.sqrt(4 * n))  # MC error of both estimates
        assert q_lo - slack <= q_true <= q_up + slack, (h.kind, h.outcome, h.t)
        checked += 1
    assert checked >= 20


def test_paper_scale_x4_world_keeps_every_value_plausible():
    """46,708 stays (4x the paper's cohort): the Gaussian tails once put paCO2 at 3.8 mmHg
    (range [5, 200]) and the study stopped at its first rule. Now X_0 is drawn inside the
    ranges and later hours are clipped to them."""
    from twinfalsify.sources.synthetic import generate

    traj = generate({"n_stays": 46_708, "confounding": 1.0}, seed=20260522)
    validate_trajectories(traj, source="synthetic")


def test_oracle_stays_exact_when_ranges_truncate_x0_and_clip_later_hours(monkeypatch):
    """With ranges narrow enough that many X_0 are drawn again and many later values are
    clipped (HCO3 in [20, 26], paCO2 in [36, 200]), every value lies inside them and the
    oracle still matches a randomised trial in that world, conditionally on X_0: the
    truncation depends on X_0 alone, so p(U | X_0) is unchanged, and both clip alike."""
    from twinfalsify.sources import synthetic

    lo, hi = synthetic._LO.copy(), synthetic._HI.copy()
    lo[FEATURES.index("HCO3")], hi[FEATURES.index("HCO3")] = 20.0, 26.0
    lo[FEATURES.index("paCO2")] = 36.0
    monkeypatch.setattr(synthetic, "_LO", lo)
    monkeypatch.setattr(synthetic, "_HI", hi)
    doses = np.array([[400.0, 0.3], [400.0, 0.3], [0.0, 0.0], [150.0, 0.0]])
    world = SyntheticWorld(n_stays=40_000)
    trial = world.sample_observational(9, fixed_doses=doses)
    x = to_array(trial, FEATURES)
    assert (x >= lo).all() and (x <= hi).all()
    j_hco3 = FEATURES.index("HCO3")
    assert (x[:, 1:, j_hco3] == 20.0).mean() > 0.02  # the clip is active
    x0 = pd.DataFrame(x[:, 0, :], columns=list(FEATURES))
    seeds = noise.combine(np.uint64(3), np.arange(len(x0), dtype=np.uint64))
    sim = world.simulate_interventional(x0, np.broadcast_to(doses, (len(x0), 4, 2)).copy(),
                                        seeds)
    assert (sim >= lo).all() and (sim <= hi).all()
    _assert_same_law(x, sim, ("HCO3", "paCO2", "SysBP"))
