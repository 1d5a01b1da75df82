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
    for part in ("Snakefile", "profiles", "workflow", "scripts", "src", "config", "envs"):
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


# Tests not marked `slow` in their file that still take more than about 2 CPU-seconds (from
# `--cpu-report`): marked slow here, so `make test-fast` (`-m "not slow"`) stays a quick inner
# loop; `make test` runs them all.
SLOW_UNIT_TESTS = (
    "test_adaptive.py::test_a_budget_too_small_to_reject_spends_no_twin_time_and_says_so",
    "test_adaptive.py::test_adaptive_batches_let_a_save_restore_twin_branch_shared_prefixes",
    "test_adaptive.py::test_depth_truncation_drops_only_hours_no_hypothesis_can_use",
    "test_breaker.py::test_one_failing_patient_does_not_stop_the_shard",
    "test_calibration.py::test_run_adaptive_equals_adaptive_test",
    "test_calibration.py::test_tiny_run_tables_and_known_answers",
    "test_failfast.py::test_breaker_leaves_a_partly_failing_twin_alone",
    "test_failfast.py::test_crashing_twin_stops_after_max_restarts",
    "test_failfast.py::test_stdout_logging_twin_stops_within_k_runs",
    "test_mimic3_causality.py::test_fixture_values_never_see_later_rows",
    "test_mimic3_staging.py::test_staged_extraction_equals_unstaged_on_the_fixture",
    "test_mimic3_synth.py::test_extraction_gives_the_cohort_and_values_built_in",
    "test_mimic3_synth.py::test_parquet_extracts_like_csv",
    "test_mimic3_synth.py::test_tables_have_full_mimic_proportions",
    "test_mimic3_workflow.py::test_another_mimic3_dir_reruns_the_extraction",
    "test_mimic4.py::test_mimic4_gives_the_mimic3_cohort_on_the_demo_metavision_stays",
    "test_record_replay.py::test_replay_equals_the_recorded_runs",
    "test_sequential.py::test_conservative_failures_keep_p_values_valid_when_failures_depend_on_the_outcome",
    "test_sequential.py::test_futility_never_loses_a_rejection_and_early_rejection_matches_p",
    "test_sequential.py::test_p_values_at_the_stopping_time_are_valid_at_the_null_boundary",
    "test_study_synthetic.py::test_more_bias_more_rejections",
    "test_study_synthetic.py::test_oracle_is_not_rejected",
    "test_synthetic_world.py::test_true_interventional_mean_lies_within_bounds",
    "test_twin_batch.py::test_batches_are_sent_and_results_identical",
    "test_twin_batch.py::test_mixed_faults_in_batches_match_unbatched",
    "test_twin_batch.py::test_served_builtin_batches_bit_identical_to_in_process",
    "test_twin_check.py::test_command_line_exit_codes_and_table",
    "test_twin_integration.py::test_protocol_twin_is_bit_identical_to_in_process",
    "test_twin_runner.py::test_mixed_faults_every_run_accounted_once",
    "test_twin_runner.py::test_retry_then_success",
    "test_twin_runner.py::test_same_results_for_one_or_two_workers_and_any_input_order",
)


@pytest.hookimpl(tryfirst=True)  # before `-m "not slow"` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.nodeid.removeprefix("tests/").split("[")[0] in SLOW_UNIT_TESTS:
            item.add_marker(pytest.mark.slow)

    def rank(item: pytest.Item) -> int:
        name = item.path.name
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: the order within a file is kept
