"""The Pulse study on real ICU patients (config/pulse-demo.yaml), replayed from runs recorded
with a real Pulse 4.2 engine (tests/fixtures/pulse-demo/): the whole study through Snakemake,
and every twin run equal to the real engine's. The study reads the demo cohort's trajectories
as they were when the runs were recorded (tests/fixtures/pulse-demo/trajectories.parquet) and
simulates the recorded X_0 (twin_runs.x0_stays).

A failure here after a change to the design or the twin plan means the recording no longer
covers the study's X_0 or sequences: record again (tests/fixtures/pulse-demo/README.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import yaml
from conftest import run_snakemake

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "pulse-demo"
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    work = tmp_path_factory.mktemp("pulse-demo")
    cfg = yaml.safe_load((ROOT / "config" / "pulse-demo.yaml").read_text())
    cfg["source"]["table"]["path"] = str(ROOT / cfg["source"]["table"]["path"])
    config = work / "pulse-demo.yaml"
    config.write_text(yaml.safe_dump(cfg))
    run = run_snakemake(work, config, "--cores", "2")
    assert run.returncode == 0, run.stderr[-3000:]
    return work / "results" / cfg["study"]


def test_every_twin_run_equals_the_real_engine(study):
    """runs.parquet of the replayed study == the one the real engine produced (same X_0,
    same prefix nodes, same values, statuses, messages and clamps)."""
    got = pd.read_parquet(study / "twins" / "pulse" / "runs.parquet")
    want = pd.read_parquet(FIXTURE / "runs_real.parquet")
    assert len(got) == len(want) > 0
    pd.testing.assert_frame_equal(got.reset_index(drop=True), want.reset_index(drop=True))


def test_the_study_shows_what_pulse_did(study):
    summary = json.loads((study / "twins" / "pulse" / "run_summary.json").read_text())
    statuses = {s for by in summary["by_hour_and_status"].values() for s in by}
    assert "error" not in statuses and "timeout" not in statuses, summary  # all recorded
    md = (study / "summary.md").read_text()
    assert "clamped" in md and "| pulse |" in md
    res = pd.read_parquet(study / "twins" / "pulse" / "results.parquet")
    assert set(res["method"]) == {"hoeffding", "betting"} and res["p_value"].between(0, 1).all()
    for fig in ("pvalues", "histograms", "sample_sizes"):
        assert (study / "twins" / "pulse" / "figures" / f"{fig}.png").stat().st_size > 0


def test_fixture_readme_says_how_it_was_made():
    readme = (FIXTURE / "README.md").read_text()
    for needed in ("4.2", "9af9d8f6", "runs.record", "pulse.worker", "config/pulse-demo.yaml"):
        assert needed in readme
    assert (FIXTURE / "answers.jsonl").stat().st_size > 0


def test_the_frozen_cohort_holds_the_recorded_x0():
    """The table the study reads gives every recorded X_0 exactly (the replay matches runs
    by X_0 values): hour 0 of each x0_stays stay equals the recording's initial state."""
    from twinfalsify.runs.plan import plan_twin_runs
    from twinfalsify.schema import ContractError

    cfg = yaml.safe_load((ROOT / "config" / "pulse-demo.yaml").read_text())
    table = pd.read_parquet(ROOT / cfg["source"]["table"]["path"])
    x0 = table[table["t"] == 0].set_index("stay_id")
    recorded = pd.read_parquet(FIXTURE / "runs_real.parquet")["init_stay_id"].unique()
    assert sorted(recorded) == sorted(cfg["twin_runs"]["x0_stays"])
    assert set(recorded) <= set(x0.index)
    hyps = pd.DataFrame({"actions": [[0], [10]]})
    plan = plan_twin_runs(hyps, x0.index.to_numpy(), None, 1, 1, x0_stays=[int(recorded[1])])
    assert plan.x0_stay_ids == [int(recorded[1])]
    with pytest.raises(ContractError, match=r"stay\(s\) \[1\] are not in D"):
        plan_twin_runs(hyps, x0.index.to_numpy(), None, 1, 1, x0_stays=[1])
    with pytest.raises(ContractError, match="runs_per_sequence to null"):
        plan_twin_runs(hyps, x0.index.to_numpy(), 8, 1, 1, x0_stays=[int(recorded[1])])
