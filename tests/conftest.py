"""Shared fixtures: small synthetic studies built in-process (fast, seeded)."""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")

pytest_plugins = ["cpu_report"]


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
    """The tiny study of config/test.yaml with every output, built once per test run and
    shared by every worker: (workdir, config path). Read it; to rerun or change it, work on
    ``copy_study`` of it."""

    def build(work: Path) -> None:
        shutil.copy(ROOT / "config" / "test.yaml", work / "test.yaml")
        run = run_snakemake(work, work / "test.yaml", "--cores", "2")
        assert run.returncode == 0, run.stderr[-3000:]

    work = built_once(tmp_path_factory, "test-study", build)
    return work, work / "test.yaml"


@pytest.fixture(scope="session")
def reference_runs(tmp_path_factory):
    """``reference_runs(cores)``: one uninterrupted run of the small study of
    ``tests/slurm/study.yaml`` with ``--cores cores``, built once per test run (shared by the
    determinism, resume and Slurm tests): (workdir, config path)."""
    from slurm.runs import build_reference_run

    def get(cores: int) -> tuple[Path, Path]:
        work = built_once(tmp_path_factory, f"reference-c{cores}",
                          lambda w: build_reference_run(w, cores))  # fmt: skip
        return work, work / "study.yaml"

    return get


# ---- running on several workers (pytest-xdist, `make test`) -------------------------------
# `make test` runs `pytest -n 2 --dist loadfile`: a test file runs whole on one worker, so its
# module fixtures are built once and its tests may share them in order; what several files
# share is built once per run by `built_once`.

# The files whose tests take longest (CPU or waiting), started first so that no worker is left
# with a long file at the end while the other idles (longest-first scheduling); the rest keep
# their order. From `--cpu-report` and `--durations` of a full run.
LONG_FIRST = (
    "test_reruns.py", "test_sequential.py", "test_twin_check.py", "test_slurm.py",
    "test_tutorial_own_twin.py", "test_table_source.py", "test_twin_integration_workflow.py",
    "test_adaptive.py", "test_figures_workflow.py", "test_resume.py", "test_mimic3_causality.py",
    "test_mimic3_staging.py", "test_mimic4.py", "test_bad_inputs.py", "test_pulse_demo_study.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        name = item.path.name
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: the order within a file is kept
