"""Errors that used to come late: figure hyp_ids, and the cluster time a twin shard asks for.

- a ``hyp_id`` in a figure config that names no hypothesis stops the study when the
  hypotheses are built (rule design), and at every start once they exist, in one line;
- a twin shard's Slurm time request follows the plan and, for a twin served over the
  protocol, its ``timeout_s`` (known answers).
"""

from __future__ import annotations

import re

import pytest
import yaml
from helpers.workflow import BASE_CONFIG
from slurm.runs import run

from twinfalsify.figure_ids import figure_ids_error
from twinfalsify.runs.plan import shard_runtime_minutes


def test_figure_ids_error_names_key_ids_and_range():
    cfg = {"figures": {"histograms": {"hyp_ids": [3, 999999, 7]}}}
    assert figure_ids_error(cfg, range(10)) == (
        "config key figures.histograms.hyp_ids: 999999 not a hypothesis of this study "
        "(hyp_id 0..9, 10 hypotheses; see design/hypotheses.parquet)")
    cfg = {"figures": {"longitudinal": {"hyp_id": 12}}}
    assert figure_ids_error(cfg, [0, 1]).startswith("config key figures.longitudinal.hyp_id: 12")
    assert figure_ids_error({"figures": {"histograms": {"hyp_ids": [1]}}}, [0, 1]) is None
    assert figure_ids_error({}, [0]) is None


def test_shard_runtime_follows_the_plan_and_the_twins_timeout():
    plan = {"x0_stay_ids": list(range(10)), "shards": [["1-2-3", "4"], ["5"]]}
    # 10 X_0 x (3 h + 1 h) x 150 s / 2 workers = 3000 s, doubled = 100 min (+1)
    assert shard_runtime_minutes(plan, 0, 150.0, None, 2) == 101
    # a run is killed at timeout_s = 300 s: the 3-hour leaf costs at most 300 s per run
    assert shard_runtime_minutes(plan, 0, 150.0, 300.0, 2) == 76
    assert shard_runtime_minutes(plan, 1, 0.01, None, 1) == 10  # at least 10 minutes


@pytest.mark.slow
def test_figure_hyp_id_that_does_not_exist_stops_the_study_at_the_design_rule(tmp_path):
    cfg = yaml.safe_load(BASE_CONFIG.read_text())
    cfg["figures"] = {"histograms": {"hyp_ids": [999999]}}
    config = tmp_path / "study.yaml"
    config.write_text(yaml.safe_dump(cfg))
    done = run(tmp_path, config, "--cores", "1", timeout=600)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    assert "config key figures.histograms.hyp_ids: 999999 not a hypothesis" in out, out[-3000:]
    results = tmp_path / "results" / cfg["study"]
    assert not (results / "design" / "hypotheses.parquet").exists()
    assert not (results / "twin_plan.json").exists()  # no twin stage
    # with the hypotheses built, the same mistake is refused at once, before any job
    del cfg["figures"]
    config.write_text(yaml.safe_dump(cfg))
    target = f"results/{cfg['study']}/design/hypotheses.parquet"
    assert run(tmp_path, config, "--cores", "1", target, timeout=600).returncode == 0
    cfg["figures"] = {"longitudinal": {"hyp_id": 999999}}
    config.write_text(yaml.safe_dump(cfg))
    done = run(tmp_path, config, "--cores", "1", "-n", timeout=600)
    line = next((ln for ln in (done.stdout + done.stderr).splitlines()
                 if ln.startswith("invalid config: ")), "")
    assert done.returncode != 0
    assert line.startswith("invalid config: config key figures.longitudinal.hyp_id: 999999")


def test_a_local_run_does_not_speak_of_slurm(test_study, tmp_path):
    """A command twin with the default timeout_s asks days per shard, which is worth a
    warning on Slurm (a queue may refuse it) and is no concern on a local run: a local dry
    run plans its shards (runtime in days) without a word about Slurm."""
    import yaml
    from helpers.paths import ROOT
    from helpers.workflow import copy_study, run_snakemake

    work = copy_study(test_study[0], tmp_path / "study")
    cfg = yaml.safe_load((work / "test.yaml").read_text())
    cfg["twins"]["mine"] = {"kind": "command",
                            "command": f"python {ROOT / 'docs/examples/template_twin.py'}"}
    (work / "test.yaml").write_text(yaml.safe_dump(cfg))
    done = run_snakemake(work, work / "test.yaml", "-n")
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    days = [int(m) for m in re.findall(r"runtime=(\d+)", out) if int(m) > 24 * 60]
    assert days, out[-3000:]  # the shards were planned, at more than a day each
    assert "Slurm" not in out
