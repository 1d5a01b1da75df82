"""Two clean runs of a study with a command twin give identical result files.

Every file under ``results/<study>/`` is compared byte for byte, except ``logs/`` and
``benchmarks/``: the measured times (Snakemake's benchmark tables, the twin's timed probe
run ``probe.json`` and the wall time projected from it, ``cost.json``) live there, and
nowhere else (docs/reference/outputs.md).
"""

from __future__ import annotations

import shutil

import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import ROOT
from helpers.workflow import run_snakemake

pytestmark = pytest.mark.slow

MEASURED = ("logs", "benchmarks")


def _run(work):
    (work / "twin").mkdir(parents=True)
    shutil.copy(FAULTY_TWIN[1], work / "twin" / "faulty_twin.py")
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["twin_runs"].update(runs_per_sequence=30, n_shards=2)
    # a probe run that takes a measurable, varying time
    cfg["twins"] = {"ext": {"kind": "command", "workers": 1,
                            "command": "python twin/faulty_twin.py --mode=slow:0 --delay=0.05"}}
    config = work / "study.yaml"
    config.write_text(yaml.safe_dump(cfg))
    done = run_snakemake(work, config, "--cores", "2")
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    r = work / "results" / cfg["study"]
    return {p.relative_to(r): p.read_bytes() for p in sorted(r.rglob("*"))
            if p.is_file() and not set(MEASURED) & set(p.relative_to(r).parts)}


def test_two_clean_runs_with_a_command_twin_give_identical_result_files(tmp_path):
    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    assert a.keys() == b.keys()
    assert any(p.name == "hello.json" for p in a) and any(p.name == "results.parquet" for p in a)
    differ = sorted(str(p) for p in a if a[p] != b[p])
    assert differ == [], differ
    for work in (tmp_path / "a", tmp_path / "b"):  # the measurements are kept
        assert (work / "results/test/benchmarks/twins/ext/probe.json").is_file()
        assert (work / "results/test/benchmarks/twins/ext/cost.json").is_file()
