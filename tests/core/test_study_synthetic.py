"""Known answers on the synthetic world: the oracle survives, wrong twins are falsified."""

from __future__ import annotations

import pytest
from helpers.studies import build_study, evaluate_twin


@pytest.fixture(scope="module")
def study():
    # moderate study: 6,000 stays, D0 = 10 %, 2,000 twin runs per sequence
    return build_study(6000, seed=21, d0_fraction=0.1, min_support=10, runs=2000)


def test_oracle_is_not_rejected(study, tmp_path):
    res = evaluate_twin(study, "oracle", {"kind": "oracle"}, tmp_path)
    assert len(res) > 500
    assert res["rejected"].sum() == 0
    # not vacuous: the oracle is tested on hypotheses with data on both sides
    assert ((res["n"] >= 100) & (res["nhat"] >= 100)).sum() > 100


def test_strongly_biased_twin_is_rejected_on_the_biased_outcome(study, tmp_path):
    res = evaluate_twin(study, "biased", {"kind": "biased", "shift": {"HR": 30.0}}, tmp_path)
    rej = res[res["rejected"]]
    assert len(rej) >= 5
    assert set(rej["outcome"]) == {"HR"}
    assert set(rej["side"]) == {"up"}  # the twin is too high: H_up: Q_twin <= Q_up fails


def test_naively_fitted_twin_is_rejected(study, tmp_path):
    res = evaluate_twin(study, "fitted", {"kind": "fitted"}, tmp_path)
    rej = res[res["rejected"]]
    assert len(rej) >= 2  # 4 with these seeds
    assert set(rej["kind"]) == {"causal"}  # found by the B-sets, invisible to Manski bounds


def test_more_bias_more_rejections(study, tmp_path):
    counts = [
        evaluate_twin(study, "b", {"kind": "biased", "shift": {"Sodium": s}}, tmp_path)[
            "rejected"
        ].sum()
        for s in (0.0, 3.0, 8.0)
    ]
    assert counts[0] == 0 and counts[0] <= counts[1] <= counts[2] and counts[2] > 0
