"""Split and design on D0: sizes, bins, hypothesis parameters against direct computations."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify import design
from twinfalsify.schema import FEATURES, STAY_ID, TIME, ContractError, to_array
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.split import split_stays


@pytest.fixture(scope="module")
def data():
    traj = SyntheticWorld(n_stays=3000).sample_observational(4)
    d0, d = split_stays(traj, 0.2, 4)
    return traj, d0, d


def test_split_sizes_disjoint_and_seeded(data):
    traj, d0, d = data
    assert d0[STAY_ID].nunique() == 600 and d[STAY_ID].nunique() == 2400
    assert not set(d0[STAY_ID]) & set(d[STAY_ID])
    again, _ = split_stays(traj, 0.2, 4)
    pd.testing.assert_frame_equal(d0, again)
    paper = pd.DataFrame({STAY_ID: np.repeat(np.arange(11677), 1), TIME: 0})
    assert split_stays(paper, 0.05, 0)[0][STAY_ID].nunique() == 583  # the paper's D0


def test_action_bins_are_quartiles_of_nonzero_d0_doses(data):
    _, d0, _ = data
    bins = design.fit_action_bins(d0)
    iv = d0.loc[(d0[TIME] < 4) & (d0["iv_fluid"] > 0), "iv_fluid"].to_numpy()
    np.testing.assert_allclose(bins.iv_edges, np.quantile(iv, [0.25, 0.5, 0.75]))
    codes = design.action_codes(d0, bins)
    iv_bin = codes // 5
    raw = d0["iv_fluid"].to_numpy().reshape(-1, 5)[:, :4]
    assert np.all((iv_bin == 0) == (raw == 0))
    for k in range(1, 5):  # each non-zero bin holds about a quarter of the non-zero doses
        assert abs((iv_bin == k).sum() / (raw > 0).sum() - 0.25) < 0.02
        np.testing.assert_allclose(bins.iv_medians[k], np.median(raw[iv_bin == k]))
    assert bins.iv_medians[0] == 0.0
    doses = bins.doses(np.array([[0, 24, 7]]))
    np.testing.assert_allclose(doses[0, 1], [bins.iv_medians[4], bins.vaso_medians[4]])
    np.testing.assert_allclose(doses[0, 2], [bins.iv_medians[1], bins.vaso_medians[2]])


def test_state_codes(data):
    _, d0, _ = data
    states = design.fit_state_bins(d0)
    x = to_array(d0, FEATURES)
    codes = design.state_codes(x, states, "HR")
    assert codes.min() >= 0 and codes.max() <= 15
    sex = x[:, 0, FEATURES.index("sex")]
    assert np.all((codes >= 8) == (sex[:, None] == 1))
    above = x[:, :, FEATURES.index("HR")] > np.median(x[:, :, FEATURES.index("HR")], axis=0)
    assert np.all((codes % 2 == 1) == above)
    counts = np.bincount((codes[:, 0] % 8) // 2, minlength=4)  # age quartiles ~ equal
    assert counts.min() > 0.2 * len(x)


def test_hypotheses_match_a_direct_pandas_computation(data):
    _, d0, _ = data
    actions, states = design.fit_action_bins(d0), design.fit_state_bins(d0)
    hyps, report = design.build_hypotheses(d0, actions, states, min_support=5)
    assert set(hyps["kind"]) == {"causal", "manski"}
    assert (hyps["y_up"] > hyps["y_lo"]).all() and (hyps["support"] >= 5).all()
    assert report["kept"].sum() == len(hyps)
    x = to_array(d0, FEATURES)
    a = design.action_codes(d0, actions)
    for _, h in hyps.sample(40, random_state=0).iterrows():
        codes = design.state_codes(x, states, h.outcome)
        match = np.all(a[:, : h.t] == np.asarray(h.actions), axis=1)
        if h.kind == "causal":
            match &= np.all(codes[:, : h.t + 1] == np.asarray(h.bins), axis=1)
        y = x[match, h.t, FEATURES.index(h.outcome)]
        assert len(y) == h.support
        assert h.y_lo == pytest.approx(np.quantile(y, 0.2))
        assert h.y_up == pytest.approx(np.quantile(y, 0.8))
    assert hyps["hyp_id"].is_unique


def test_design_errors_are_clear():
    tiny = SyntheticWorld(n_stays=30).sample_observational(1)
    tiny["vasopressor"] = 0.0
    bins = design.fit_action_bins(tiny)  # no vasopressor in D0: one unused bin, no crash
    assert bins.vaso_edges == (0.0, 0.0, 0.0) and set(bins.vaso_medians) == {0.0}
    with pytest.raises(ContractError, match="non-zero vasopressor"):
        design.fit_action_bins(tiny, min_nonzero=8)
    with pytest.raises(ContractError, match="d0_fraction"):
        split_stays(tiny, 1.5, 0)


def test_action_space_table_counts_all_hours(data):
    _, _, d = data
    bins = design.fit_action_bins(d)
    table = design.action_space_table(d, bins)
    assert len(table) == 25 and table["n_hours"].sum() == 4 * d[STAY_ID].nunique()
    assert table["share"].sum() == pytest.approx(1.0)


def test_restrict_hypotheses_keeps_exactly_the_listed_prefixes(data):
    """horizon / sequences keep every hypothesis with t <= horizon whose a_1:t prefixes a
    listed sequence (brute force), unchanged, and count the rest in the report."""
    _, d0, _ = data
    _, _, full, report = design.design_on_d0(d0, min_support=10)
    seqs = [list(a) for a in full.loc[full["t"] == 2, "actions"].head(3)]
    _, _, got, rep = design.design_on_d0(d0, min_support=10, horizon=2, sequences=seqs)
    want = [r for r in full.itertuples()
            if r.t <= 2 and any(list(r.actions) == s[: r.t] for s in seqs)]
    assert len(got) == len(want) > 0
    np.testing.assert_array_equal(got["hyp_id"], np.arange(len(got)))
    cols = ["kind", "outcome", "t", "y_lo", "y_up", "support"]
    pd.testing.assert_frame_equal(
        got[cols].reset_index(drop=True),
        full.loc[[r.Index for r in want], cols].reset_index(drop=True))
    assert got["actions"].map(tuple).tolist() == [tuple(r.actions) for r in want]
    assert rep["kept"].sum() == len(got)
    assert (rep["kept"] + rep["dropped_outside_design"]).sum() == report["kept"].sum()
    with pytest.raises(ContractError, match="no hypothesis left"):
        design.design_on_d0(d0, min_support=10, sequences=[[24, 24, 24, 24]], horizon=1)


def test_subgroup_parts_inverts_the_codes_of_state_codes():
    from twinfalsify.design import StateBins, subgroup_parts

    bins = StateBins(age_edges=(40.0, 55.0, 70.0), medians={"HR": (90.0,)})
    for sex in (0, 1):
        for age, q in ((30.0, 0), (40.0, 1), (60.0, 2), (70.0, 3)):  # edges: right side
            x0 = np.zeros(len(FEATURES))
            x0[FEATURES.index("sex")], x0[FEATURES.index("age")] = sex, age
            for hr, above in ((90.0, 0), (90.5, 1)):  # a tie with the median is not above
                code = int(bins.base_codes(x0)) + int(bins.above("HR", np.array(hr), 0))
                assert subgroup_parts(code) == (sex, q, above)
