"""The order seed: recorded in the results, another valid randomisation of the order-dependent
tests only, and the seed check marking exactly the decisions another seed changes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.studies import build_study, twin_samples

from twinfalsify import twin_tests
from twinfalsify.runs.registry import make_twin
from twinfalsify.summary import tie_table

TESTING = {"alpha": 0.05, "correction": "holm", "failed_runs": "conservative",
           "order_seed": None, "seed_check": 0,
           "methods": {"hoeffding": {}, "betting": {}}}


@pytest.fixture(scope="module")
def study():
    st = build_study(1500, seed=11, runs=300, min_support=5)
    twin = make_twin("biased", {"kind": "biased", "shift": {"HR": 12.0}},
                     {"source": {"kind": "synthetic", "synthetic": {"n_stays": 1500}}})
    samples, n_failed = twin_samples(st, twin)
    return st, samples, n_failed


def _res(study, **testing):
    st, samples, n_failed = study
    return twin_tests.study_results(st.hyps, samples, n_failed, {**TESTING, **testing}, 11)


def test_default_order_seed_is_recorded_as_null_and_changes_nothing(study):
    st, samples, n_failed = study
    res = _res(study)
    assert res["order_seed"].isna().all() and not res["seed_fragile"].any()
    from twinfalsify.falsify import make_methods, run_tests

    plain = run_tests(st.hyps, samples, n_failed, make_methods(TESTING["methods"], 11))
    np.testing.assert_array_equal(res["p_value"].to_numpy(), plain["p_value"].to_numpy())
    assert res["rejected"].sum() > 0


def test_another_order_seed_moves_only_order_dependent_p_values(study):
    a, b = _res(study, order_seed=3), _res(study, order_seed=4)
    assert (a["order_seed"] == 3).all() and (b["order_seed"] == 4).all()
    hoef = a["method"] == "hoeffding"
    np.testing.assert_array_equal(a.loc[hoef, "p_value"], b.loc[hoef, "p_value"])
    bet = (a["method"] == "betting") & ((a["p_value"] < 1) | (b["p_value"] < 1))
    assert bet.sum() > 20
    assert (a.loc[bet, "p_value"].to_numpy() != b.loc[bet, "p_value"].to_numpy()).mean() > 0.9


def test_seed_check_marks_exactly_the_decisions_other_seeds_change(study):
    res = _res(study, seed_check=3)
    flips = np.zeros(len(res), dtype=bool)
    for k in (1, 2, 3):
        other = _res(study, order_seed=11 + k)  # the check's seeds: the study seed + k
        flips |= other["rejected"].to_numpy() != res["rejected"].to_numpy()
    flips &= (res["method"] == "betting").to_numpy()
    np.testing.assert_array_equal(res["seed_fragile"].to_numpy(), flips)
    assert not res.loc[res["method"] == "hoeffding", "seed_fragile"].any()


def test_tie_table_counts_identical_contents(study):
    """100 stays of D written twice under new ids: 200 of the records tie at every hour."""
    st = study[0]
    d = st.d
    ids = d["stay_id"].unique()
    copies = d[d["stay_id"].isin(ids[:100])].assign(stay_id=lambda f: f["stay_id"] + 10**7)
    both = pd.concat([d, copies], ignore_index=True).sort_values(["stay_id", "t"])
    table = tie_table(both, st.actions, 11)
    want = f"{200 / (len(ids) + 100):.1%}"
    assert (table["tied"] == want).all(), table
    assert (tie_table(d, st.actions, 11)["tied"] == "0.0%").all()
