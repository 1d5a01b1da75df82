"""Snakemake studies run from the tests, and folders built once per test run."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from filelock import FileLock

from helpers.paths import ROOT

# the tiny study's config: the base of the bad-config cases and of small edited studies
BASE_CONFIG = ROOT / "config" / "test.yaml"


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str,
               build: Callable[[Path], None]) -> Path:
    """A folder ``build`` fills once per test run, however many pytest-xdist workers ask.

    The pattern of pytest-xdist's docs for session fixtures that must run once: the folder
    lives in the temporary directory all workers of a run share, and the first worker to ask
    builds it under a file lock while the others wait, then read it. A failed build is
    recorded, so the other workers fail with its message instead of building it again.
    Readers must not change the folder: copy it (``copy_study``) to change it.
    """
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "built-once"
    shared.mkdir(exist_ok=True)
    folder, done, failed = shared / name, shared / f"{name}.done", shared / f"{name}.failed"
    with FileLock(str(shared / f"{name}.lock")):
        if failed.exists():
            raise AssertionError(f"building {name} failed (in another worker):\n"
                                 + failed.read_text())
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            try:
                build(folder)
            except BaseException as exc:
                failed.write_text(f"{type(exc).__name__}: {exc}"[-5000:])
                raise
            done.touch()
    return folder


def copy_study(folder: Path, dest: Path) -> Path:
    """A private copy of a built study folder (file times kept, so Snakemake sees it
    complete), for a test that reruns or edits it."""
    shutil.copytree(folder, dest, symlinks=True)
    return dest


def copy_repo(repo: Path) -> Path:
    """A copy of what a study needs from the checkout (Snakefile, workflow, scripts, src,
    config, envs) in ``repo``, so a test may edit code without touching the checkout."""
    repo.mkdir(parents=True)
    for part in ("Snakefile", "profiles", "workflow", "scripts", "src", "config", "envs"):
        src, dst = ROOT / part, repo / part
        if src.is_dir():
            shutil.copytree(src, dst)  # bytecode and numba's caches too: still valid
        else:
            shutil.copy(src, dst)
    return repo


def run_snakemake(workdir: Path, config: Path, *args: str, timeout: int = 900):
    """``snakemake -s <repo>/Snakefile --directory workdir --configfile config *args``."""
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
           str(workdir), "--configfile", str(config), *args]  # fmt: skip
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)


def mimic_study_config(study: str, kind: str, path: str | None) -> dict:
    """A study config reading a small MIMIC folder (``kind`` mimic3 or mimic4; ``path`` None:
    the environment variable) with one fitted twin and Hoeffding: enough for the
    extraction rule and the small rules after it."""
    return {"study": study, "seed": 1,
            "source": {"kind": kind, kind: {"path": path, "threads": 1}},
            "split": {"d0_fraction": 0.4}, "design": {"min_support": 1},
            "twin_runs": {"runs_per_sequence": None, "n_shards": 1},
            "twins": {"fitted": {"kind": "fitted", "inputs": "init"}},
            "testing": {"alpha": 0.05, "correction": "holm",
                        "methods": {"hoeffding": {"factor": 2}}}}


# The study of a command twin that fails some runs, shared by tests/core/test_one_path.py (one
# path from stored runs to p-values) and tests/workflow/test_command_twin_reproducible.py (a
# second clean run gives identical files): conftest's ``failing_twin_study`` builds it once.
FAILING_TWIN = "faulty"
FAILING_TWIN_METHODS = {"hoeffding": {"factor": 2}, "betting": {}, "bootstrap": {"min_n": 20}}


def failing_twin_config() -> dict:
    """config/test.yaml with one command twin (tests/fakes/faulty_twin.py) that fails about
    one run in five (irreversible in hour 2, or refusing X_0) and starts the others from one
    fixed patient whatever their X_0 (so subgroups are rejected), under
    ``failed_runs: conservative`` with three methods (200 runs per sequence: fewer reject
    nothing) and a sensitivity sweep of two widenings (Delta = 0, which is checked, among
    them). Its timed probe runs (seeds 0, 1, 2; no study run has so small a seed)
    include one slowed down (``slow:0``): a measured time that varies between runs, which
    must stay out of the result files; its answers carry no pid or time (``--no-stamp``),
    so a failed run's message is the same in every run."""
    from fakes import FAULTY_TWIN

    cfg = yaml.safe_load(BASE_CONFIG.read_text())
    cfg["study"] = "onepath"
    cfg["twin_runs"] = {"runs_per_sequence": 200, "n_shards": 2}
    cfg["twins"] = {FAILING_TWIN: {
        "kind": "command", "workers": 1, "timeout_s": 60,
        "command": [*FAULTY_TWIN, "--mode=slow:0", "--delay=0.05",
                    "--mode=irreversible:%7=0", "--mode=init_failed:%11=4",
                    "--mode=x0_ignored", "--irreversible-hour=2", "--no-stamp"],
        "env": {"PYTHONPATH": str(ROOT / "src")}}}
    cfg["testing"] = {"alpha": 0.05, "correction": "holm", "failed_runs": "conservative",
                      "methods": FAILING_TWIN_METHODS}
    cfg["figures"] = {"sensitivity": {"deltas": [0.0, 0.05]}}  # Delta = 0 is what is checked
    return cfg


def build_failing_twin_study(work: Path) -> None:
    """A clean run of ``failing_twin_config()`` in ``work`` (config ``work/study.yaml``),
    every output built."""
    (work / "study.yaml").write_text(yaml.safe_dump(failing_twin_config()))
    run = run_snakemake(work, work / "study.yaml", "--cores", "2")
    assert run.returncode == 0, run.stderr[-3000:]
