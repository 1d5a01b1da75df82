"""Two clean runs of a study with a command twin give identical result files.

Every file under ``results/<study>/`` is compared byte for byte, except ``logs/`` and
``benchmarks/``: the measured times (Snakemake's benchmark tables, the twin's timed probe
run ``probe.json`` and the wall time projected from it, ``cost.json``) live there, and
nowhere else (docs/reference/outputs.md).

The study is conftest's ``failing_twin_study`` (a command twin failing some runs, one of its
probe runs slowed down so that the measured time varies, three methods): the first run is
the one built once per test run and shared with tests/core/test_one_path.py, the second a
clean run of the same config here.
"""

from __future__ import annotations

import shutil

import pytest
import yaml
from helpers.workflow import FAILING_TWIN, run_snakemake

pytestmark = pytest.mark.slow

MEASURED = ("logs", "benchmarks")


def _result_files(work):
    r = work / "results" / yaml.safe_load((work / "study.yaml").read_text())["study"]
    return {p.relative_to(r): p.read_bytes() for p in sorted(r.rglob("*"))
            if p.is_file() and not set(MEASURED) & set(p.relative_to(r).parts)}


def test_two_clean_runs_with_a_command_twin_give_identical_result_files(tmp_path,
                                                                       failing_twin_study):
    first, config = failing_twin_study
    second = tmp_path / "b"
    second.mkdir()
    shutil.copy(config, second / "study.yaml")  # the same config, in a clean folder
    done = run_snakemake(second, second / "study.yaml", "--cores", "2")
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    a, b = _result_files(first), _result_files(second)
    assert a.keys() == b.keys()
    assert any(p.name == "hello.json" for p in a) and any(p.name == "results.parquet" for p in a)
    differ = sorted(str(p) for p in a if a[p] != b[p])
    assert differ == [], differ
    for work in (first, second):  # the measurements are kept
        bench = work / "results" / "onepath" / "benchmarks" / "twins" / FAILING_TWIN
        assert (bench / "probe.json").is_file()
        assert (bench / "cost.json").is_file()
