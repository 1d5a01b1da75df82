"""`snakemake calibration` end to end on a tiny config; not part of the default target."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT

TINY = {
    "replicates": 4, "chunks": 2, "n_stays": 1000, "d0_fraction": 0.2, "min_support": 10,
    "runs_per_sequence": 150, "bias_sizes": [0.0, 8.0], "coverage_per_replicate": 2,
    "coverage_population": 15000, "coverage_min_inside": 100,
    "methods": {"hoeffding": {}, "bootstrap": {"n_resamples": 50}, "betting": {}, "bernstein": {}},
}  # fmt: skip


def snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    config = str(ROOT / "config" / "test.yaml")
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"),
           "--directory", str(work), *args, "--configfile", config]  # fmt: skip
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)


@pytest.fixture
def work(tmp_path):
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "calibration.yaml").write_text(yaml.safe_dump(TINY))
    shutil.copy(ROOT / "config" / "test.yaml", tmp_path / "config" / "test.yaml")
    return tmp_path


@pytest.mark.slow
def test_default_target_does_not_run_the_calibration(work):
    run = snakemake(work, "-n", "--quiet", "rules")
    assert run.returncode == 0, run.stderr[-2000:]
    jobs = run.stdout + run.stderr  # (the tmp path itself contains "calibration")
    assert "calibration_chunk" not in jobs and "calibration_report" not in jobs
    run = snakemake(work, "calibration", "-n", "--quiet", "rules")
    assert "calibration_chunk" in run.stdout + run.stderr


@pytest.mark.slow
def test_calibration_target_writes_table_figures_summary_and_reruns_on_config_edit(work):
    run = snakemake(work, "--cores", "2", "calibration")
    assert run.returncode == 0, run.stderr[-3000:]
    out = work / "results" / "calibration"
    table = pd.read_csv(out / "calibration.csv")
    assert {"method", "kind", "bias", "any_rejection_rate", "ci_low", "ci_high"} <= set(
        table.columns
    )
    assert set(table["bias"]) == {0.0, 8.0} and (table["replicates"] == 4).all()
    for f in ("power.png", "power.pdf", "coverage.png", "coverage.pdf"):
        assert (out / "figures" / f).stat().st_size > 0
    assert "Family-wise error of the oracle twin" in (out / "summary.md").read_text()
    # adaptive rows (default adaptive: true): in the table with twin-hours, and per bias
    seq = table[table["method"] == "betting_sequential"]
    assert len(seq) == 4 and seq["hours_ratio"].between(0, 1, inclusive="right").all()
    assert (seq[seq["bias"] == 0]["mean_rejections"] == 0).all()
    adaptive = pd.read_csv(out / "adaptive.csv")
    assert sorted(adaptive["bias"]) == [0.0, 8.0] and (adaptive["replicates"] == 4).all()
    assert "## Adaptive twin runs" in (out / "summary.md").read_text()
    assert snakemake(work, "-n", "calibration").stdout.count("rule calibration_chunk") == 0
    (work / "config" / "calibration.yaml").write_text(yaml.safe_dump({**TINY, "seed": 5}))
    dry = snakemake(work, "-n", "calibration")
    assert dry.stdout.count("rule calibration_chunk") == 2, dry.stdout[-2000:]
