"""Determinism: the same config and seed give identical results.parquet.

Compared: two independent runs from scratch, one with --cores 1 and one with --cores 2
(different job order and concurrency). The resumed runs of tests/workflow/test_resume.py are
compared with the same --cores 1 run, and the Slurm run of tests/workflow/test_slurm.py with the
--cores 2 run.
"Identical" is checked twice: equal tables (every value, dtype and row order) and equal
Parquet bytes: pyarrow writes no timestamp or host name into the file, so the bytes are
equal too.
"""

from __future__ import annotations

import pytest
from slurm.runs import assert_same_results, results_dir, results_files

pytestmark = pytest.mark.slow


def test_cores_1_and_cores_2_give_identical_results(reference_runs):
    w1, c1 = reference_runs(1)
    w2, c2 = reference_runs(2)
    assert_same_results(results_files(w1, c1), results_files(w2, c2))
    # not only the end result: every intermediate table is identical too
    for name in ("trajectories", "d0", "d", "design/hypotheses", "observational/counts"):
        a = results_dir(w1, c1) / f"{name}.parquet"
        b = results_dir(w2, c2) / f"{name}.parquet"
        assert a.read_bytes() == b.read_bytes(), name
