"""The twin's hello is checked at the start of a study (rule twin_hello), not after its
extraction, design and plan: a bad hello stops the study in one line naming the twin, the
field and the problem, before any shard runs; a dry run and a start with nothing to do never
start the twin. The hello's probe run gives the twin's seconds per simulated hour, and the
rule twin_cost turns the plan into engine-hours and a projected wall time.
"""

from __future__ import annotations

import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import ENV, FAKES
from helpers.workflow import BASE_CONFIG
from slurm.runs import run

from twinfalsify.runs.hello import (
    PROBE_RUNS,
    cost_line,
    projected_cost,
    seconds_per_hour,
    seconds_per_hour_range,
    split_timing,
    twin_hello,
    with_timing,
)
from twinfalsify.schema import ContractError


def _command(*args: str) -> dict:
    return {"kind": "command", "command": [*FAULTY_TWIN, *args], "timeout_s": 30, "env": ENV}


@pytest.mark.parametrize(("mode", "field"), [
    ("bad_hello", "hello does not declare required feature(s) HR"),
    ("no_version", "hello field 'version' must be a string, got None"),
    ("bad_units", "hello declares wrong unit(s): HR in 'Hz' (expected '/min')"),
])
def test_a_bad_hello_is_one_line_naming_twin_field_and_problem(mode, field):
    with pytest.raises(ContractError) as err:
        twin_hello("mine", _command(f"--mode={mode}"))
    msg = str(err.value)
    assert msg.startswith("twins.mine: ") and "bad hello" in msg and field in msg, msg
    assert "\n" not in msg


def test_a_good_hello_is_kept_with_its_timed_probe_runs(tmp_path):
    import numpy as np

    log = tmp_path / "requests.log"
    out = twin_hello("mine", _command("--mode=slow", "--delay=0.3", f"--log-requests={log}"))
    assert out["checked"] == "hello" and out["hello"]["version"] == "1"
    # PROBE_RUNS runs of one hour each, each timed; seconds is their median
    assert len(log.read_text().splitlines()) == PROBE_RUNS == out["probe"]["runs"] == 3
    assert out["probe"]["status"] == "ok" and out["probe"]["hours"] == 1
    each = out["probe"]["seconds_each"]
    assert len(each) == 3 and out["probe"]["seconds"] == float(np.median(each))
    assert 0.3 <= seconds_per_hour(out) < 5.0  # the twin's own delay, start-up excluded
    assert seconds_per_hour_range(out) == (min(each), max(each))
    # hello.json keeps no measured time (the same at every run); the rule writes the
    # times under benchmarks/, and twin_cost puts them back
    kept, timing = split_timing(out)
    assert "seconds" not in kept["probe"] and "seconds_each" not in kept["probe"]
    assert timing == {"seconds": out["probe"]["seconds"], "seconds_each": each}
    assert with_timing(kept, timing) == out
    assert seconds_per_hour(kept) is None


def test_python_and_builtin_twins_are_checked_in_process():
    out = twin_hello("py", {"kind": "python", "factory": "py_twin:make", "path": str(FAKES)})
    assert out["checked"] == "in-process" and out["probe"]["status"] == "ok"
    with pytest.raises(ContractError, match="twins.py.factory: cannot find module"):
        twin_hello("py", {"kind": "python", "factory": "no_such_twin:make",
                          "path": str(FAKES)})
    assert twin_hello("o", {"kind": "oracle"}) == {"twin": "o", "kind": "oracle",
                                                   "checked": "builtin", "probe": None}


def test_projected_cost_is_engine_hours_times_seconds_over_workers():
    plan_hours = {"from_scratch": 900, "leaves": 600, "prefix_tree": 240}
    hello = {"probe": {"hours": 2, "seconds": 300.0, "status": "ok"}, "hello": {}}
    cost = projected_cost(plan_hours, 200, hello, workers=4)
    # 600 engine-hours x 150 s / 4 workers = 22,500 s
    assert cost["engine_hours"] == 600 and cost["wall_seconds"] == pytest.approx(22_500)
    assert "about 6h15m00s wall" in cost_line("p", cost)
    branched = {**hello, "hello": {"capabilities": {"save_restore": True}}}
    assert projected_cost(plan_hours, 200, branched, 4)["engine_hours"] == 240
    failed = {"probe": {"hours": 1, "seconds": 9.0, "status": "timeout", "message": "slow"}}
    cost = projected_cost(plan_hours, 200, failed, 1)
    assert cost["wall_seconds"] is None and "ended timeout: slow" in cost_line("p", cost)
    assert cost["seconds_per_hour_range"] is None and cost["wall_seconds_range"] is None


def test_the_cost_line_says_the_probe_runs_spread():
    """Three probe runs of 2 h: the median gives the projection, the fastest and slowest
    its range, in cost.json and in the line."""
    plan_hours = {"from_scratch": 900, "leaves": 600, "prefix_tree": 240}
    hello = {"probe": {"hours": 2, "runs": 3, "seconds": 300.0,
                       "seconds_each": [200.0, 300.0, 800.0], "status": "ok"}, "hello": {}}
    cost = projected_cost(plan_hours, 200, hello, workers=4)
    assert cost["seconds_per_hour"] == 150.0 and cost["probe_runs"] == 3
    assert cost["seconds_per_hour_range"] == [100.0, 400.0]
    # 600 engine-hours x 100 .. 400 s / 4 workers
    assert cost["wall_seconds_range"] == [15_000.0, 60_000.0]
    line = cost_line("p", cost)
    assert line.endswith("; at 150 s per simulated hour (median of 3 probe runs, 100-400 s) "
                         "on 4 worker(s): about 6h15m00s wall (4h10m00s to 16h40m00s)"), line


@pytest.mark.slow
def test_bad_hello_stops_the_study_before_any_shard_and_dry_runs_start_no_twin(tmp_path):
    cfg = yaml.safe_load(BASE_CONFIG.read_text())
    log = tmp_path / "requests.log"
    cfg["twins"] = {"good": _command("--mode=ok", f"--log-requests={log}"),
                    "nover": _command("--mode=no_version")}
    config = tmp_path / "study.yaml"
    config.write_text(yaml.safe_dump(cfg))
    twins = tmp_path / "results" / cfg["study"] / "twins"
    dry = run(tmp_path, config, "--cores", "1", "-n", timeout=600)
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert "twin_hello" in dry.stdout + dry.stderr and not log.exists()  # no twin started
    done = run(tmp_path, config, "--cores", "1", timeout=600)
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]  # the run's last line names twin and field
    assert last.startswith("ERROR: twins.nover: ") and "bad hello: hello field 'version' " \
        "must be a string, got None" in last, done.stderr[-2000:]
    assert not list(twins.glob("*/shards/*.parquet"))  # no shard of any twin ran
    assert (twins / "good" / "hello.json").is_file() or not log.exists()
    # a start with nothing new to do for the good twin's hello starts no twin again
    target = f"results/{cfg['study']}/twins/good/hello.json"
    assert run(tmp_path, config, "--cores", "1", target, timeout=600).returncode == 0
    asked = log.read_text().splitlines()
    assert len(asked) == PROBE_RUNS  # the probe runs, once
    assert run(tmp_path, config, "--cores", "1", target, timeout=600).returncode == 0
    assert log.read_text().splitlines() == asked


def test_job_errors_are_read_from_the_failed_jobs_logs(tmp_path):
    from twinfalsify.io import job_errors

    (tmp_path / "a.log").write_text("2026-01-01 10:00:00,000 started\n"
                                    "2026-01-01 10:00:01,000 ERROR: t.csv: row 3, column HR\n")
    (tmp_path / "b.log").write_text("no error line here\n")
    main = tmp_path / "snakemake.log"
    main.write_text(f"Error in rule trajectories:\n    jobid: 3\n"
                    f"    log: {tmp_path / 'a.log'}, {tmp_path / 'b.log'} (check log file(s) "
                    f"for error details)\nError in rule twin_hello:\n"
                    f"    log: {tmp_path / 'gone.log'} (check log file(s) for error details)\n")
    assert job_errors(main) == ["ERROR: t.csv: row 3, column HR"]
    assert job_errors(tmp_path / "missing.log") == []


def test_the_probe_patient_is_the_checks_first_patient():
    from twinfalsify.runs.check import shipped_x0
    from twinfalsify.runs.hello import probe_x0

    assert probe_x0() == shipped_x0(1)[0]
