"""The Pulse study on real ICU patients (config/pulse-demo.yaml), replayed from runs recorded
with a real Pulse 4.2 engine (tests/fixtures/pulse-demo/): the whole study through Snakemake,
and every twin run equal to the real engine's. Needs the open MIMIC-III demo in ../shared.

A failure here after a change to the MIMIC-III extraction or the design means the recording
no longer covers the study's X_0 or sequences: record again (tests/fixtures/pulse-demo/README.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import yaml
from conftest import run_snakemake, shared_dir

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "pulse-demo"
SHARED = shared_dir()
DEMO = SHARED / "data" / "mimic-iii-demo" if SHARED else None
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(DEMO is None or not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                                 reason="MIMIC-III demo not present in ../shared/data")]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    work = tmp_path_factory.mktemp("pulse-demo")
    cfg = yaml.safe_load((ROOT / "config" / "pulse-demo.yaml").read_text())
    cfg["source"]["mimic3"]["path"] = str(DEMO)
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
