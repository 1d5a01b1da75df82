"""End to end: `twin_runs.mode: adaptive` on a tiny study; accounting and resumption."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT
from helpers.workflow import run_snakemake as snakemake

pytestmark = pytest.mark.slow


# what the tests read: figures would add minutes and are checked elsewhere
TWIN = "results/adaptive/twins/biased"
TARGETS = (f"{TWIN}/results.parquet", f"{TWIN}/adaptive/summary.json",
           f"{TWIN}/tables/rejections.csv")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    work = tmp_path_factory.mktemp("adaptive_study")
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["study"] = "adaptive"
    cfg["twin_runs"] = {"runs_per_sequence": 200, "n_shards": 2, "mode": "adaptive",
                        "batch_size": 50}
    # served over the twin protocol, as the default study's twins: the shard must hand the
    # served twin its context file, not the parsed dict
    cfg["twins"] = {"biased": {"kind": "biased", "shift": {"HR": 25.0}, "protocol": True,
                               "workers": 1}}
    config = work / "adaptive.yaml"
    config.write_text(yaml.safe_dump(cfg))
    run = snakemake(work, config, "--cores", "2", *TARGETS)
    assert run.returncode == 0, run.stderr[-3000:]
    return work, config


def test_adaptive_results_account_for_every_run(study):
    work, _ = study
    r = work / "results" / "adaptive"
    res = pd.read_parquet(r / "twins" / "biased" / "results.parquet")
    hyps = pd.read_parquet(r / "design" / "hypotheses.parquet")
    assert set(res["method"]) == {"betting_sequential"}
    assert set(res["failed_runs"]) == {"conservative"}  # the schema's default reaches the test
    assert len(res) == 2 * len(hyps) and set(res["hyp_id"]) == set(hyps["hyp_id"])
    assert res["p_value"].between(0, 1).all()
    assert set(res["decision"]) <= {"rejected", "futile", "undecided"}
    # rejected after Holm <=> p-value small; early rejections are all Holm rejections
    assert res.loc[res["decision"] == "rejected", "rejected"].all()
    assert not res.loc[res["decision"] == "futile", "rejected"].any()
    summary = json.loads((r / "twins" / "biased" / "adaptive" / "summary.json").read_text())
    shards = [pd.read_parquet(p) for p in sorted(
        (r / "twins" / "biased" / "adaptive" / "shards").glob("[0-9].parquet"))]
    assert summary["node_rows_simulated"] == sum(len(s) for s in shards)
    assert summary["twin_hours_adaptive"] == summary["node_rows_simulated"]
    assert summary["twin_hours_adaptive"] < summary["twin_hours_fixed"]
    # prefix reuse: a twin without it would simulate more hours than the node-runs
    assert summary["twin_hours_requested"] >= summary["twin_hours_adaptive"]
    assert not (r / "twins" / "biased" / "shards").exists()  # no fixed-scheme runs
    assert (r / "twins" / "biased" / "tables" / "rejections.csv").exists()


def test_adaptive_mode_resumes_per_shard(study):
    """An interrupted run (shard 1 and the merge missing) redoes shard 1 only."""
    work, config = study
    dry = snakemake(work, config, "--cores", "2", "-n", *TARGETS)
    assert dry.returncode == 0 and "Nothing to be done" in dry.stdout + dry.stderr
    twin = work / "results" / "adaptive" / "twins" / "biased"
    for name in ("1.parquet", "1.decisions.parquet", "1.json"):
        (twin / "adaptive" / "shards" / name).unlink()
    (twin / "results.parquet").unlink()
    dry = snakemake(work, config, "--cores", "2", "-n", *TARGETS)
    out = dry.stdout + dry.stderr
    assert dry.returncode == 0, out[-2000:]
    jobs = re.findall(r"^rule (\w+):\n(?:.*\n)*?\s+wildcards: ([^\n]*)", out, re.M)
    shard_jobs = [w for rule, w in jobs if rule == "twin_shard_adaptive"]
    assert len(shard_jobs) == 1 and "shard=1" in shard_jobs[0], jobs
    assert any(rule == "tests_adaptive" for rule, _ in jobs)
