"""The fixtures several test files use (studies built once per run, the check for leftover
child processes), the order and slow marks of the whole suite, and the session's bytecode and
heap hooks. Plain helpers live in ``tests/helpers/``."""

from __future__ import annotations

import compileall
import gc
import os
import shutil
import sys
import time
from pathlib import Path

import pytest
from helpers.paths import ROOT, SRC, TESTS
from helpers.workflow import build_failing_twin_study, built_once, run_snakemake

sys.path.insert(0, str(SRC))
os.environ.setdefault("MPLBACKEND", "Agg")

pytest_plugins = ["cpu_report"]


@pytest.fixture(scope="session")
def root() -> Path:
    return ROOT


def _children() -> list[tuple[int, str]]:
    """(pid, state) of every process whose parent is this test process (from /proc)."""
    me, out = os.getpid(), []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[1]) == me:
            out.append((int(entry.name), fields[0]))
    return out


@pytest.fixture
def no_leftover_processes():
    """Fails the test when a child process it started is still there 3 s after it ended.
    A file checks every test with ``pytestmark = pytest.mark.usefixtures(...)``."""
    before = {pid for pid, _ in _children()}
    yield
    deadline = time.monotonic() + 3.0
    while True:
        left = [(p, s) for p, s in _children() if p not in before]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert not left, f"child processes left behind (pid, state): {left}"


def pytest_sessionstart(session: pytest.Session) -> None:
    # the library's bytecode, written once before any test: the suite starts hundreds of
    # processes that import it (Snakemake jobs, twins, command lines), and where Python is told
    # not to write bytecode itself (PYTHONDONTWRITEBYTECODE) each would compile it again
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        compileall.compile_dir(SRC / "twinfalsify", quiet=1)


def pytest_runtest_teardown(item: pytest.Item) -> None:
    # a test that ran a rule script's body in this process (io.run_rule) froze its heap, as a
    # job's process does at its end: thawed, this worker's later garbage is collected again
    if gc.get_freeze_count():
        gc.unfreeze()


@pytest.fixture(scope="session")
def test_study(tmp_path_factory):
    """The tiny study of config/test.yaml with every output, built once per test run and
    shared by every worker: (workdir, config path). Read it; to rerun or change it, work on
    ``copy_study`` of it. ``build.log`` beside the config is Snakemake's output of the build
    (every job that ran)."""

    def build(work: Path) -> None:
        shutil.copy(ROOT / "config" / "test.yaml", work / "test.yaml")
        run = run_snakemake(work, work / "test.yaml", "--cores", "2")
        assert run.returncode == 0, run.stderr[-3000:]
        (work / "build.log").write_text(run.stdout + run.stderr)

    work = built_once(tmp_path_factory, "test-study", build)
    return work, work / "test.yaml"


@pytest.fixture(scope="session")
def failing_twin_study(tmp_path_factory):
    """The study of ``helpers.workflow.failing_twin_config`` (a command twin failing some
    runs, three methods) with every output, built once per test run and shared by every
    worker: (workdir, config path). Read it; to rerun or change it, work on a copy."""
    work = built_once(tmp_path_factory, "failing-twin-study", build_failing_twin_study)
    return work, work / "study.yaml"


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
# `make test` runs `pytest -n 3 --dist loadfile`: a test file runs whole on one worker, so its
# module fixtures are built once and its tests may share them in order; what several files
# share is built once per run by `built_once`.

# The files whose tests take longest (CPU or waiting), started first so that no worker is left
# with a long file at the end while the other idles (longest-first scheduling); the rest keep
# their order (pytest_configure below keeps pytest-xdist from reordering the files). From
# `--cpu-report` and `--durations` of a full run. Paths are relative to tests/.
LONG_FIRST = (
    "workflow/test_reruns.py",  # builds test_study first, then its own study on a copy
    "runs/test_twin_check.py",  # mostly waiting for twins that hang or start slowly
    "workflow/test_slurm.py",  # mostly waiting for the Slurm cluster
    "workflow/test_tutorial_own_twin.py",
    "sources/test_table_source.py",
    "core/test_one_path.py",  # builds failing_twin_study
    "workflow/test_twin_integration_workflow.py",
    "workflow/test_resume.py",
    "runs/test_adaptive.py",
    "sources/mimic3/test_mimic3_causality.py",
    "sources/mimic3/test_mimic3_staging.py",
    "workflow/test_command_twin_reproducible.py",  # after test_one_path: its study is built
    "runs/test_failfast.py",
    "sources/meds/test_meds.py",
    "sources/mimic4/test_mimic4.py",
    "pulse/test_pulse_demo_study.py",
    "workflow/test_self_writing_twin.py",
    "inference/test_sequential.py",
    "workflow/test_bad_inputs.py",
    "workflow/test_mimic3_workflow.py",
    "workflow/test_module_deploy.py",
)


# Tests not marked `slow` in their file that still take more than about 2 CPU-seconds (from
# `--cpu-report`): marked slow here, so `make test-fast` (`-m "not slow"`) stays a quick inner
# loop; `make test` runs them all. Node ids are relative to tests/ (`runs/test_x.py::test_y`).
SLOW_UNIT_TESTS = (
    "runs/test_adaptive.py::test_a_budget_too_small_to_reject_spends_no_twin_time_and_says_so",
    "runs/test_adaptive.py::test_adaptive_batches_let_a_save_restore_twin_branch_shared_prefixes",
    "runs/test_adaptive.py::test_depth_truncation_drops_only_hours_no_hypothesis_can_use",
    "runs/test_breaker.py::test_one_failing_patient_does_not_stop_the_shard",
    "calibration/test_calibration.py::test_run_adaptive_equals_adaptive_test",
    "calibration/test_calibration.py::test_tiny_run_tables_and_known_answers",
    "runs/test_failfast.py::test_breaker_leaves_a_partly_failing_twin_alone",
    "runs/test_failfast.py::test_crashing_twin_stops_after_max_restarts",
    "runs/test_failfast.py::test_stdout_logging_twin_stops_within_k_runs",
    "sources/mimic3/test_mimic3_causality.py::test_fixture_values_never_see_later_rows",
    "sources/mimic3/test_mimic3_staging.py::test_staged_extraction_equals_unstaged_on_the_fixture",
    "sources/mimic3/test_mimic3_synth.py::test_extraction_gives_the_cohort_and_values_built_in",
    "sources/mimic3/test_mimic3_synth.py::test_parquet_extracts_like_csv",
    "sources/mimic3/test_mimic3_synth.py::test_tables_have_full_mimic_proportions",
    "workflow/test_mimic3_workflow.py::test_another_mimic3_dir_reruns_the_extraction",
    "sources/mimic4/test_mimic4.py::test_mimic4_gives_the_mimic3_cohort_on_the_demo_metavision_stays",
    "runs/test_record_replay.py::test_replay_equals_the_recorded_runs",
    "inference/test_sequential.py::test_conservative_failures_keep_p_values_valid_when_failures_depend_on_the_outcome",
    "inference/test_sequential.py::test_futility_never_loses_a_rejection_and_early_rejection_matches_p",
    "inference/test_sequential.py::test_p_values_at_the_stopping_time_are_valid_at_the_null_boundary",
    "core/test_study_synthetic.py::test_more_bias_more_rejections",
    "core/test_study_synthetic.py::test_oracle_is_not_rejected",
    "sources/test_synthetic_world.py::test_true_interventional_mean_lies_within_bounds",
    "runs/test_twin_batch.py::test_batches_are_sent_and_results_identical",
    "runs/test_twin_batch.py::test_mixed_faults_in_batches_match_unbatched",
    "runs/test_twin_batch.py::test_served_builtin_batches_bit_identical_to_in_process",
    "runs/test_twin_check.py::test_command_line_exit_codes_and_table",
    "runs/test_twin_integration.py::test_protocol_twin_is_bit_identical_to_in_process",
    "runs/test_twin_runner.py::test_mixed_faults_every_run_accounted_once",
    "runs/test_twin_runner.py::test_retry_then_success",
    "runs/test_twin_runner.py::test_same_results_for_one_or_two_workers_and_any_input_order",
)


def pytest_configure(config: pytest.Config) -> None:
    # pytest-xdist 3 hands the files out by their number of tests, most first, unless told
    # otherwise (its --loadscope-reorder, on by default): that would undo LONG_FIRST (the
    # collection's order, set below), so the collection's order is kept
    if getattr(config.option, "loadscopereorder", None):
        config.option.loadscopereorder = False


@pytest.hookimpl(tryfirst=True)  # before `-m "not slow"` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def file_of(item: pytest.Item) -> str:
        """The item's file relative to tests/ (``runs/test_twin_runner.py``)."""
        return Path(os.path.relpath(item.path, TESTS)).as_posix()

    for item in items:
        test = item.nodeid.partition("::")[2].split("[")[0]
        if f"{file_of(item)}::{test}" in SLOW_UNIT_TESTS:
            item.add_marker(pytest.mark.slow)

    def rank(item: pytest.Item) -> int:
        name = file_of(item)
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: the order within a file is kept
