"""Shared fixtures: small synthetic studies built in-process (fast, seeded)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")


def shared_dir() -> Path | None:
    """The shared data folder: ``$TWINFALSIFY_SHARED`` if set, else ``../shared`` next to the
    checkout (the CI layout); None when absent (the tests that need it skip)."""
    env = os.environ.get("TWINFALSIFY_SHARED")
    cand = Path(env) if env else ROOT.parent / "shared"
    return cand if cand.is_dir() else None


@pytest.fixture(scope="session")
def root() -> Path:
    return ROOT


def copy_repo(repo: Path) -> Path:
    """A copy of what a study needs from the checkout (Snakefile, workflow, scripts, src,
    config, envs) in ``repo``, so a test may edit code without touching the checkout."""
    import shutil

    repo.mkdir(parents=True)
    for part in ("Snakefile", "workflow", "scripts", "src", "config", "envs"):
        src, dst = ROOT / part, repo / part
        if src.is_dir():
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(src, dst)
    return repo


def run_snakemake(workdir: Path, config: Path, *args: str, timeout: int = 900):
    """``snakemake -s <repo>/Snakefile --directory workdir --configfile config *args``."""
    import subprocess

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


@pytest.fixture(scope="session")
def test_study(tmp_path_factory):
    """The tiny study of config/test.yaml, run once per session with every output:
    (workdir, config path). Tests that modify it must leave it complete."""
    import shutil

    work = tmp_path_factory.mktemp("test-study")
    config = work / "test.yaml"
    shutil.copy(ROOT / "config" / "test.yaml", config)
    run = run_snakemake(work, config, "--cores", "2")
    assert run.returncode == 0, run.stderr[-3000:]
    return work, config
