"""A real one-node Slurm cluster: the study runs through Snakemake's Slurm executor plugin.

The test starts munged, slurmctld and slurmd by hand (tests/slurm/cluster.py), runs the small
study with the project's Slurm profile (placeholders filled in as a user would), checks that the
jobs really went through Slurm (the controller's job-completion log and submit RPCs), that the
results equal a local run bit for bit, and stops every daemon it started.

Skips where a cluster cannot run (not root, packages missing, plugin missing) unless
TWINFALSIFY_REQUIRE_SLURM=1, which `.ci/run` sets after installing the packages: on CI the
test must really run.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from slurm import cluster as slurm_cluster
from slurm.runs import (
    ROOT,
    assert_same_results,
    new_study,
    results_files,
    run,
)

pytestmark = [pytest.mark.slurm, pytest.mark.slow]

# The plugin's first status check comes this many seconds after a submission; MinJobAge (300 s
# in the generated slurm.conf) must be >= 3x this for squeue-based status to be reliable.
INIT_SECONDS = 2


def _unavailable() -> str | None:
    why = slurm_cluster.missing_requirements()
    if why is None and importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        why = "snakemake-executor-plugin-slurm is not installed (pip install it)"
    return why


def _live(name: str) -> list[str]:
    """Live (not zombie) processes with this exact name: this machine's init reaps no zombies."""
    out = subprocess.run(["pgrep", "-x", name], capture_output=True, text=True).stdout.split()
    live = []
    for pid in out:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            live.append(pid)
    return live


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    why = _unavailable()
    if why:
        if os.environ.get("TWINFALSIFY_REQUIRE_SLURM") == "1":
            pytest.fail(f"Slurm test required but cannot run: {why}")
        pytest.skip(f"no local Slurm cluster: {why}")
    munged_before = bool(_live("munged"))
    for daemon in ("slurmctld", "slurmd"):
        if _live(daemon):
            pytest.skip(f"a {daemon} is already running here; not starting a second cluster")
    state = Path("/tmp") / f"tf-slurm-{os.getpid()}"  # short path: Slurm limits socket paths
    t0 = time.monotonic()
    try:
        c = slurm_cluster.start(state)
    except slurm_cluster.ClusterUnavailable as exc:
        pytest.fail(f"Slurm cluster did not start: {exc}")
    print(f"cluster up in {time.monotonic() - t0:.1f} s")
    yield c
    slurm_cluster.stop(state)
    left = {d: _live(d) for d in ("slurmctld", "slurmd", "slurmstepd")}
    if not munged_before:
        left["munged"] = _live("munged")
    assert not any(left.values()), f"daemons left behind after teardown: {left}"
    assert not slurm_cluster.SYSTEM_CONF.exists()


def slurm_profile(dest: Path, partition: str) -> Path:
    """The shipped profile with its placeholders filled in, as the docs tell a user to do."""
    text = (ROOT / "workflow" / "profiles" / "slurm" / "config.yaml").read_text()
    assert "YOUR_PARTITION" in text and "YOUR_ACCOUNT" in text
    # no accounting storage here, so no accounts: delete the line, as docs/how-to/cluster.md says
    lines = [ln for ln in text.splitlines() if "YOUR_ACCOUNT" not in ln]
    text = "\n".join(lines).replace("YOUR_PARTITION", partition)
    text = text.replace(
        "slurm-init-seconds-before-status-checks: 40",
        f"slurm-init-seconds-before-status-checks: {INIT_SECONDS}",
    )
    # a bundle of N one-core shards asks Slurm for N CPUs; this node has 2
    text = text.replace("twin_shards=4", "twin_shards=2")
    dest.mkdir(parents=True)
    (dest / "config.yaml").write_text(text + "\n")
    return dest


def test_study_runs_through_slurm_and_equals_a_local_run(cluster, tmp_path, reference_runs):
    work = tmp_path / "slurm-study"
    config = new_study(work)
    profile = slurm_profile(tmp_path / "profile", cluster.partition)
    t0 = time.monotonic()
    # only what is compared (every twin's results.parquet): tables and figures add Slurm jobs
    targets = [str(p.relative_to(work)) for p in results_files(work, config).values()]
    done = run(work, config, "--profile", str(profile), *targets, env=cluster.env, timeout=900)
    wall = time.monotonic() - t0
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    log = done.stdout + done.stderr

    # the jobs went through Slurm: snakemake says so, and so does the controller
    submitted = [ln for ln in log.splitlines() if "has been submitted with SLURM jobid" in ln]
    jobs = cluster.completed_jobs()
    assert len(submitted) >= 3, log[-3000:]
    assert len(jobs) == len(submitted)
    assert all(j["JobState"] == "COMPLETED" and j["ExitCode"] == "0:0" for j in jobs), jobs
    assert cluster.ctld_log.read_text().count("_slurm_rpc_submit_batch_job") == len(jobs)
    # grouping: the prep chain, 4 shards in 2 bundles, the post chain: a handful of Slurm
    # jobs instead of one per rule job
    # rule jobs behind the targets: the prep chain (trajectories, split, design,
    # observational_side, twin_plan), per twin its hello and cost, one job per shard, then
    # twin_runs and tests
    cfg = yaml.safe_load(config.read_text())
    n_rule_jobs = 5 + len(cfg["twins"]) * (cfg["twin_runs"]["n_shards"] + 4)
    assert len(jobs) < n_rule_jobs, (len(jobs), n_rule_jobs)
    overhead = wall - sum(_seconds(j) for j in jobs)
    print(f"Slurm study: {wall:.0f} s wall, {len(jobs)} Slurm jobs, {overhead:.0f} s overhead")

    local_work, local_config = reference_runs(2)
    assert_same_results(results_files(work, config), results_files(local_work, local_config))


def _seconds(job: dict[str, str]) -> float:
    from datetime import datetime

    start = datetime.fromisoformat(job["StartTime"])
    end = datetime.fromisoformat(job["EndTime"])
    return (end - start).total_seconds()
