"""Determinism: the same config and seed give identical results.parquet.

Compared: a run with --cores 1 against one with --cores 2 (different job order and
concurrency), and a full forced rerun (--forceall) against the first run in the same
directory. "Identical" is checked twice: equal tables (every value, dtype and row order) and
equal Parquet bytes: pyarrow writes no timestamp or host name into the file, so the bytes are
equal too. The Slurm run is compared with the local run in tests/test_slurm.py.
"""

from __future__ import annotations

import pytest
import yaml
from slurm.runs import assert_same_results, reference_run, results_dir, results_files, run

pytestmark = pytest.mark.slow


def test_cores_1_and_cores_2_give_identical_results():
    w1, c1 = reference_run(cores=1)
    w2, c2 = reference_run(cores=2)
    assert_same_results(results_files(w1, c1), results_files(w2, c2))
    # not only the end result: every intermediate table is identical too
    for name in ("trajectories", "d0", "d", "design/hypotheses", "observational/counts"):
        a = results_dir(w1, c1) / f"{name}.parquet"
        b = results_dir(w2, c2) / f"{name}.parquet"
        assert a.read_bytes() == b.read_bytes(), name


def test_forced_rerun_gives_identical_results():
    work, config = reference_run(cores=2)
    files = results_files(work, config)
    before = {t: p.read_bytes() for t, p in files.items()}
    stamps = {t: p.stat().st_mtime_ns for t, p in files.items()}
    targets = [str(p.relative_to(work)) for p in files.values()]
    again = run(work, config, "--cores", "2", "--forceall", *targets)
    assert again.returncode == 0, again.stderr[-3000:]
    for twin, path in files.items():
        assert path.stat().st_mtime_ns != stamps[twin], "rerun did not rewrite the file"
        assert path.read_bytes() == before[twin], f"{twin}: rerun changed results.parquet"
    seed = yaml.safe_load(config.read_text())["seed"]
    assert isinstance(seed, int)
