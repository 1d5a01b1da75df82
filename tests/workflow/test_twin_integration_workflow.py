"""End to end with protocol twins: served builtin twin = in-process twin; kill -9 and resume."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import ROOT
from helpers.workflow import copy_study

pytestmark = pytest.mark.slow


def _cmd(work: Path, config: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
            str(work), "--configfile", str(config), *args]


def _run(work: Path, config: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(_cmd(work, config, *args), capture_output=True, text=True, env=env,
                          timeout=900)


def _config(tmp_path: Path, twins: dict, **runs) -> Path:
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["twins"] = twins
    cfg["twin_runs"].update(runs)
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_served_builtin_twin_gives_the_in_process_results(tmp_path, test_study):
    """config/test.yaml's biased twin served over the twin protocol (2 workers) beside the
    in-process one: the same runs and results, bit for bit. The in-process twin's are those
    of the shared config/test.yaml study (``test_study``), which this config continues on a
    copy: only the served twin runs."""
    work = copy_study(test_study[0], tmp_path / "study")
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    local = cfg["twins"]["biased"]
    cfg["twins"] = {"biased": local, "served": {**local, "protocol": True, "workers": 2,
                                                 "timeout_s": 30}}
    config = work / "served.yaml"
    config.write_text(yaml.safe_dump(cfg))
    # only what is compared: tables and figures (the sensitivity sweep above all) add minutes
    out = work / "results" / "test" / "twins"
    targets = [str((out / t / f).relative_to(work))
               for t in ("biased", "served") for f in ("runs.parquet", "results.parquet")]
    run = _run(work, config, "--cores", "2", *targets)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stderr.count("rule twin_shard:") == cfg["twin_runs"]["n_shards"]  # served's
    # the served twin's shard jobs were given both cores
    assert "threads: 2" in run.stderr
    runs = [pd.read_parquet(out / t / "runs.parquet") for t in ("biased", "served")]
    pd.testing.assert_frame_equal(*runs, check_exact=True)
    res = [pd.read_parquet(out / t / "results.parquet") for t in ("biased", "served")]
    pd.testing.assert_frame_equal(*res, check_exact=True)
    assert (res[0]["p_value"] < 0.5).any()  # informative tests, not all p = 1


def test_kill_9_during_twin_stage_then_resume_recomputes_no_finished_shard(tmp_path,
                                                                           test_study):
    """A slow command twin's study killed (kill -9 of Snakemake and its job) when some of
    its shards are done: after --unlock, --rerun-incomplete reruns only the unfinished
    shards. The study continues a copy of the shared config/test.yaml study
    (``test_study``: every step before the twin plan is the same), so the twin stage is
    what runs."""
    cmd = [*FAULTY_TWIN, "--mode", "slow", "--delay", "0.02"]
    spec = {"kind": "command", "command": cmd, "workers": 1, "timeout_s": 30,
            "env": {"PYTHONPATH": str(ROOT / "src")}}
    work = copy_study(test_study[0], tmp_path / "study")
    config = _config(work, {"slow": spec}, runs_per_sequence=80, n_shards=3)
    shards = work / "results" / "test" / "twins" / "slow" / "shards"
    target = "results/test/twins/slow/runs.parquet"  # the twin stage: what is checked
    proc = subprocess.Popen(_cmd(work, config, "--cores", "1", target),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True,
                            env={**os.environ, "MPLBACKEND": "Agg"})
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not list(shards.glob("*.parquet")):
            assert proc.poll() is None, "snakemake ended before the first shard was written"
            time.sleep(0.2)
        # Snakemake records a job as finished just after its output appears: give it a
        # moment, so that "finished" means finished for Snakemake too.
        time.sleep(1.5)
        done = {p.name: p.stat().st_mtime_ns for p in shards.glob("*.parquet")}
        assert done, "no shard finished in time"
        os.killpg(proc.pid, signal.SIGKILL)  # snakemake and its running job, at once
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert len(done) < 3, "every shard finished before the kill: make the twin slower"
    assert _run(work, config, "--unlock").returncode == 0
    dry = _run(work, config, "--cores", "1", "--rerun-incomplete", "--dry-run", target)
    for name in done:
        # finished shards are not scheduled (they only appear as inputs of twin_runs)
        assert f"output: results/test/twins/slow/shards/{name}" not in dry.stdout + dry.stderr
    assert "rule twin_shard" in dry.stdout + dry.stderr  # the unfinished ones are
    run = _run(work, config, "--cores", "1", "--rerun-incomplete", target)
    assert run.returncode == 0, run.stderr[-3000:]
    for name, mtime in done.items():
        assert (shards / name).stat().st_mtime_ns == mtime
    assert len(list(shards.glob("*.parquet"))) == 3
    runs = pd.read_parquet(work / "results" / "test" / "twins" / "slow" / "runs.parquet")
    assert (runs["status"] == "ok").all()
