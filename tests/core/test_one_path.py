"""One path from stored runs to p-values: on a study whose twin fails some runs, under
``failed_runs: conservative``, the summary, ``explain`` and the sensitivity sweep at
Delta = 0 give exactly the decisions of ``results.parquet``, and every consumer rebuilds the
same samples (failed runs at their places) as the tests rule."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT
from helpers.workflow import FAILING_TWIN as TWIN
from helpers.workflow import FAILING_TWIN_METHODS as METHODS

from twinfalsify import summary, twin_tests
from twinfalsify.explain import explain

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def failing_study(failing_twin_study):
    """config/test.yaml with one command twin that fails about one run in five (irreversible
    in hour 2, or refusing X_0) and starts the others from one fixed patient whatever their
    X_0 (so subgroups are rejected), every output built: conftest's ``failing_twin_study``
    (``helpers.workflow.failing_twin_config``), shared with the reproducibility test."""
    work, _ = failing_twin_study
    return work / "results" / "onepath"


def _paths(r: Path) -> dict[str, Path]:
    t = r / "twins" / TWIN
    return {"d": r / "d.parquet", "d0": r / "d0.parquet", "bins": r / "design" / "bins.json",
            "actions": r / "design" / "actions.json",
            "hypotheses": r / "design" / "hypotheses.parquet",
            "counts": r / "observational" / "counts.parquet",
            "follow": r / "observational" / "follow.parquet", "plan": r / "twin_plan.json",
            "runs": t / "runs.parquet", "results": t / "results.parquet"}


def test_the_study_has_failed_runs_that_move_p_values(failing_study):
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    assert (res["n_failed"] > 0).mean() > 0.2, res["n_failed"].describe()
    assert res["rejected"].sum() > 0
    tt = twin_tests.load_twin_tests(_paths(failing_study))
    drop = twin_tests.study_results(tt.hyps, tt.samples, tt.n_failed,
                                    {"alpha": 0.05, "correction": "holm",
                                     "failed_runs": "drop", "methods": METHODS,
                                     "order_seed": None, "seed_check": 0}, 7)
    assert (drop["p_value"].to_numpy() < res["p_value"].to_numpy()).any()


def test_tests_rule_results_are_the_one_path_results(failing_study):
    """Recomputing results.parquet from the stored files with the one path gives it back."""
    cfg = yaml.safe_load((failing_study.parent.parent / "study.yaml").read_text())
    tt = twin_tests.load_twin_tests(_paths(failing_study))
    testing = {"alpha": 0.05, "correction": "holm", "order_seed": None, "seed_check": 0,
               **cfg["testing"]}
    again = tt.results(testing, cfg["seed"])
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    pd.testing.assert_frame_equal(again, res, check_exact=True)


def test_summary_rebuilds_the_tests_samples(failing_study):
    st = summary.load_study_twin(_paths(failing_study))
    tt = twin_tests.load_twin_tests(_paths(failing_study))
    np.testing.assert_array_equal(st.n_failed, tt.n_failed)
    np.testing.assert_array_equal(st.samples.failed_run.sizes, tt.n_failed)
    np.testing.assert_array_equal(st.samples.twin.values, tt.samples.twin.values)
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    first = res.drop_duplicates("hyp_id")
    np.testing.assert_array_equal(first["n_failed"].to_numpy(), st.n_failed)


def test_summary_rejection_table_equals_results(failing_study):
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    text = (failing_study / "summary.md").read_text()
    for (method, kind), n_rej in res.groupby(["method", "kind"])["rejected"].sum().items():
        row = re.search(rf"\|\s*{TWIN}\s*\|\s*{method}\s*\|\s*{kind}\s*\|([^\n]*)", text)
        assert row, f"no rejections row for {method}/{kind}"
        cells = [c.strip() for c in row.group(1).split("|") if c.strip()]
        assert int(cells[1]) == n_rej, (method, kind, cells)


def test_sensitivity_at_delta_zero_equals_results(failing_study):
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    sweep = pd.read_csv(failing_study / "twins" / TWIN / "tables" / "sensitivity.csv")
    at0 = sweep[sweep["delta"] == 0].set_index(["method", "kind", "group"])["n_rejected"]
    want = res.groupby(["method", "kind", "outcome"])["rejected"].sum()
    assert want.sum() > 0
    assert len(at0) == len(want)
    for key, n in want.items():
        assert at0[key] == n, key


def test_explain_gives_the_results_decisions(failing_study):
    res = pd.read_parquet(failing_study / "twins" / TWIN / "results.parquet")
    rejected = res.loc[res["rejected"], "hyp_id"].unique()[:3].tolist()
    kept = res.groupby("hyp_id")["rejected"].any()
    kept = kept[~kept].index[:2].tolist()
    for hyp_id in rejected + kept:
        text = explain(failing_study, int(hyp_id), TWIN)
        mine = res[res["hyp_id"] == hyp_id]
        for m in mine.itertuples():
            line = re.search(rf"{m.method}\s+H_{m.side}: p = [^,]+, (REJECTED|not rejected)",
                             text)
            assert line, (hyp_id, m.method, m.side)
            assert (line.group(1) == "REJECTED") == bool(m.rejected)


def test_no_consumer_rebuilds_samples_its_own_way():
    """Only the one path builds hypothesis samples from twin runs (bounds.twin_runs is
    called by twin_tests alone; the drop-only twin_side is gone)."""
    users = []
    for folder in ("src", "scripts"):
        for py in (ROOT / folder).rglob("*.py"):
            text = py.read_text()
            if re.search(r"\btwin_runs\(", text) and py.name not in ("bounds.py",
                                                                     "twin_tests.py"):
                users.append(str(py.relative_to(ROOT)))
            assert not re.search(r"\bbounds\.twin_side\b|import[^\n]*\btwin_side\b", text), py
    assert users == []
