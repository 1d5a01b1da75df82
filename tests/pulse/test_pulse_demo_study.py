"""The Pulse study on real ICU patients (config/pulse-demo.yaml), replayed from runs recorded
with a real Pulse 4.2 engine (tests/fixtures/pulse-demo/): the study through Snakemake (its
runs, results, summary and three figures) on the open MIMIC-III demo's cohort as the
extraction gives it (skipped when the demo is absent), and every twin run equal to the real
engine's.

A failure here after a change to the extraction, the design or the twin plan means the
recording no longer covers the study's X_0 or sequences: record again
(tests/fixtures/pulse-demo/README.md).
"""

from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT, shared_dir
from helpers.workflow import run_snakemake

FIXTURE = ROOT / "tests" / "fixtures" / "pulse-demo"
DEMO = (shared_dir() or ROOT.parent / "shared") / "data" / "mimic-iii-demo"
FIGURES = ("pvalues", "histograms", "sample_sizes")
needs_demo = pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                                reason=f"MIMIC-III demo not present at {DEMO}")


def _config() -> dict:
    return yaml.safe_load((ROOT / "config" / "pulse-demo.yaml").read_text())


def _recorded_requests() -> list[dict]:
    lines = [json.loads(x) for x in (FIXTURE / "answers.jsonl").read_text().splitlines()]
    return [x["request"] for x in lines if "request" in x]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    work = tmp_path_factory.mktemp("pulse-demo")
    cfg = _config()
    cfg["source"]["mimic3"]["path"] = str(DEMO)
    config = work / "pulse-demo.yaml"
    config.write_text(yaml.safe_dump(cfg))
    # what the tests read (the other figures and tables add half a minute and check nothing
    # of Pulse's runs)
    r, twin = f"results/{cfg['study']}", f"results/{cfg['study']}/twins/pulse"
    targets = [f"{twin}/{rel}" for rel in ("runs.parquet", "run_summary.json",
                                           "results.parquet")]
    targets += [f"{twin}/figures/{fig}.png" for fig in FIGURES] + [f"{r}/summary.md"]
    run = run_snakemake(work, config, "--cores", "2", *targets)
    assert run.returncode == 0, run.stderr[-3000:]
    return work / "results" / cfg["study"]


@needs_demo
@pytest.mark.slow
def test_every_twin_run_equals_the_real_engine(study):
    """runs.parquet of the replayed study == the one the real engine produced (same X_0,
    same prefix nodes, same values, statuses, messages and clamps)."""
    got = pd.read_parquet(study / "twins" / "pulse" / "runs.parquet")
    want = pd.read_parquet(FIXTURE / "runs_real.parquet")
    assert len(got) == len(want) > 0
    pd.testing.assert_frame_equal(got.reset_index(drop=True), want.reset_index(drop=True))


@needs_demo
@pytest.mark.slow
def test_the_study_shows_what_pulse_did(study):
    summary = json.loads((study / "twins" / "pulse" / "run_summary.json").read_text())
    statuses = {s for by in summary["by_hour_and_status"].values() for s in by}
    assert "error" not in statuses and "timeout" not in statuses, summary  # all recorded
    md = (study / "summary.md").read_text()
    assert "clamped" in md and "| pulse |" in md
    res = pd.read_parquet(study / "twins" / "pulse" / "results.parquet")
    assert set(res["method"]) == {"hoeffding", "betting"} and res["p_value"].between(0, 1).all()
    for fig in FIGURES:
        assert (study / "twins" / "pulse" / "figures" / f"{fig}.png").stat().st_size > 0


def test_fixture_readme_says_how_it_was_made():
    readme = (FIXTURE / "README.md").read_text()
    for needed in ("4.2", "9af9d8f6", "runs.record", "pulse.worker", "config/pulse-demo.yaml"):
        assert needed in readme
    assert (FIXTURE / "answers.jsonl").stat().st_size > 0


def test_the_study_pins_nothing():
    """The study reads the cohort users get: the MIMIC-III demo through the extraction with
    its default options, the default (per-patient) split, X_0 drawn by the workflow."""
    cfg = _config()
    assert cfg["source"]["kind"] == "mimic3"
    assert set(cfg["source"]["mimic3"]) <= {"path", "threads"}  # every cohort option default
    assert "by" not in cfg["split"] and "x0_stays" not in cfg["twin_runs"]
    assert isinstance(cfg["twin_runs"]["runs_per_sequence"], int)
    assert not (FIXTURE / "trajectories.parquet").exists()


def test_the_recording_is_one_run_per_x0_and_sequence():
    """answers.jsonl holds exactly the plan's runs: runs_per_sequence X_0 x the design's
    sequences, each (X_0, doses) once, and runs_real.parquet has one row per run."""
    cfg = _config()
    reqs = _recorded_requests()
    m, seqs = cfg["twin_runs"]["runs_per_sequence"], cfg["design"]["sequences"]
    x0s = {json.dumps(r["x0"], sort_keys=True) for r in reqs}
    keys = {(json.dumps(r["x0"], sort_keys=True), json.dumps(r["doses"])) for r in reqs}
    assert len(x0s) == m and len(reqs) == len(keys) == m * len(seqs)
    runs = pd.read_parquet(FIXTURE / "runs_real.parquet")
    assert runs["init_stay_id"].nunique() == m and len(runs) == m * len(seqs)


@needs_demo
@pytest.mark.slow
def test_the_recording_covers_the_studys_own_draw(study):
    """The replayed study's plan (its own draw of X_0 from D) names exactly the recorded
    stays, and hour 0 of each in D is the X_0 the real engine was sent."""
    from twinfalsify.runs.plan import plan_twin_runs
    from twinfalsify.schema import ContractError

    plan = json.loads((study / "twin_plan.json").read_text())
    recorded = pd.read_parquet(FIXTURE / "runs_real.parquet")["init_stay_id"].unique()
    assert sorted(plan["x0_stay_ids"]) == sorted(int(s) for s in recorded)
    d = pd.read_parquet(study / "d.parquet")
    x0 = d[d["t"] == 0].set_index("stay_id")
    sent = [r["x0"] for r in _recorded_requests()]
    for stay in plan["x0_stay_ids"]:
        row = x0.loc[stay]
        assert any(all(v == float(row[f]) for f, v in s.items()) for s in sent), stay
    # twin_runs.x0_stays (the library's way to name recorded X_0) on this D
    hyps = pd.DataFrame({"actions": [[0], [10]]})
    ids = x0.index.to_numpy()
    plan2 = plan_twin_runs(hyps, ids, None, 1, 1, x0_stays=[int(recorded[1])])
    assert plan2.x0_stay_ids == [int(recorded[1])]
    with pytest.raises(ContractError, match=r"stay\(s\) \[1\] are not in D"):
        plan_twin_runs(hyps, ids, None, 1, 1, x0_stays=[1])
    with pytest.raises(ContractError, match="runs_per_sequence to null"):
        plan_twin_runs(hyps, ids, 8, 1, 1, x0_stays=[int(recorded[1])])
