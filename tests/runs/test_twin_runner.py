"""The twin runner against real subprocesses: faults, retries, timeouts, parallelism.

Every test drives ``python tests/fakes/faulty_twin.py`` (or a shell wrapper
around it) as a real subprocess and checks that every requested run comes back
exactly once with the right status, values computed independently from the
faulty twin's documented formula, and no child process left behind.
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fakes import FAULTY_TWIN
from fakes.faulty_twin import expected
from helpers.paths import ENV
from helpers.twins import expected_features, make_inputs, stamps

from twinfalsify.runs import runner
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.runner import plan_groups, simulate_via_protocol
from twinfalsify.schema import FEATURES, TWIN_STATUSES, ContractError

FAULTY = FAULTY_TWIN
HR = FEATURES.index("HR")
pytestmark = pytest.mark.usefixtures("no_leftover_processes")


def test_good_runs_exact_values_with_two_workers():
    x0, doses, seeds = make_inputs(12)
    res = simulate_via_protocol(FAULTY, x0, doses, seeds, workers=2, env=ENV, progress=False)
    assert list(res.status) == ["ok"] * 12
    np.testing.assert_allclose(res.features, expected_features(x0, doses, seeds), rtol=0,
                               atol=1e-9)
    # the module's own helper agrees with the independent formula above
    row = expected(x0.iloc[3].to_dict(), doses[3].tolist(), int(seeds[3]))
    np.testing.assert_allclose([h["HR"] for h in row], res.features[3, :, HR])
    assert set(res.clamped) == {"{}"}


def test_mixed_faults_every_run_accounted_once():
    """One study mixing every fault: each run gets exactly its expected status."""
    plan = {  # seed -> (mode, expected status, message fragment)
        100: ("ok", "ok", "pid="),
        101: ("crash", "error", "exited with code 3"),
        102: ("hang", "timeout", "no answer within 2 s"),
        103: ("garbage", "error", "not JSON"),
        104: ("malformed", "error", "not JSON"),
        105: ("wrong_id", "error", "does not match request id"),
        106: ("wrong_features", "error", "unknown feature(s) heart_rate"),
        107: ("fewer_hours", "error", "only 2 of 3 hours"),
        108: ("non_numeric", "error", "HR is not a finite number"),
        109: ("irreversible", "irreversible", "irreversible state during hour 2"),
        110: ("init_failed", "init_failed", "patient rejected"),
        111: ("error", "error", "engine error"),
        112: ("clamp", "ok", "pid="),
        113: ("ok", "ok", "pid="),
        # the twin's own act, not the runner's kill: not reported as "exit code -9"
        114: ("close_stdout", "error", "closed its stdout but kept running (killed by the "
                                       "runner)"),
    }
    x0, doses, seeds = make_inputs(len(plan))
    x0.loc[12, "HR"] = 150.0  # the clamp twin clamps HR > 110
    modes = [f"--mode={mode}:{seed}" for seed, (mode, _, _) in plan.items() if mode != "ok"]
    res = simulate_via_protocol([*FAULTY, *modes], x0, doses, seeds, workers=2, timeout_s=2.0,
                                retries=1, env=ENV, progress=False)
    assert len(res.status) == len(plan)
    good = expected_features(x0, doses, seeds)
    for i, (_seed, (mode, status, fragment)) in enumerate(plan.items()):
        assert res.status[i] == status, (mode, res.message[i])
        assert fragment in res.message[i], (mode, res.message[i])
        if status == "ok" and mode == "ok":
            np.testing.assert_allclose(res.features[i], good[i], atol=1e-9)
        elif mode == "irreversible":  # hour 1 kept, hours 2.. NaN
            np.testing.assert_allclose(res.features[i, 0], good[i, 0], atol=1e-9)
            assert np.isnan(res.features[i, 1:]).all()
        elif mode != "clamp":
            assert np.isnan(res.features[i]).all()
    assert "(failed 2 attempt(s))" in res.message[1] and "crashing on seed 101" in res.message[1]
    assert "hanging on seed 102" in res.message[2]
    clamp = 12
    assert res.clamped[clamp] == '{"HR": [150.0, 110.0]}'
    assert res.features[clamp, 0, HR] == pytest.approx(good[clamp, 0, HR] - 40.0)
    assert set(res.status) <= set(TWIN_STATUSES)


def test_retry_then_success(tmp_path):
    """A twin that crashes once per seed: every run succeeds on its retry."""
    x0, doses, seeds = make_inputs(4)
    cmd = [*FAULTY, "--mode=crash_once", f"--state-dir={tmp_path}"]
    res = simulate_via_protocol(cmd, x0, doses, seeds, workers=2, retries=1, env=ENV,
                                progress=False)
    assert list(res.status) == ["ok"] * 4
    np.testing.assert_allclose(res.features, expected_features(x0, doses, seeds), atol=1e-9)
    assert len(list(tmp_path.iterdir())) == 4  # each seed crashed exactly once
    # Without retries the same crashes are final errors.
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    res0 = simulate_via_protocol([*FAULTY, "--mode=crash_once", f"--state-dir={fresh}"], x0,
                                 doses, seeds, retries=0, env=ENV, progress=False)
    assert list(res0.status) == ["error"] * 4
    assert all("(failed 1 attempt(s))" in m for m in res0.message)


def test_same_results_for_one_or_two_workers_and_any_input_order():
    x0, doses, seeds = make_inputs(10)
    cmd = [*FAULTY, "--mode=irreversible:%3=0", "--mode=init_failed:%4=1", "--mode=clamp"]
    x0["HR"] = np.linspace(90, 130, 10)
    kw = {"env": ENV, "progress": False}
    r1 = simulate_via_protocol(cmd, x0, doses, seeds, workers=1, **kw)
    r2 = simulate_via_protocol(cmd, x0, doses, seeds, workers=2, **kw)
    perm = np.random.default_rng(5).permutation(10)
    rp = simulate_via_protocol(cmd, x0.iloc[perm].reset_index(drop=True), doses[perm],
                               seeds[perm], workers=2, **kw)
    assert {"ok", "irreversible", "init_failed"} <= set(r1.status)
    for other, idx in ((r2, np.arange(10)), (rp, np.argsort(perm))):
        np.testing.assert_array_equal(other.features[idx], r1.features)
        np.testing.assert_array_equal(other.status[idx], r1.status)
        np.testing.assert_array_equal(other.clamped[idx], r1.clamped)


def test_two_workers_really_run_in_parallel():
    """Two slow runs on two workers overlap in time (the twins' own timestamps)."""
    x0, doses, seeds = make_inputs(2)
    cmd = [*FAULTY, "--mode=slow", "--delay=2.0"]
    res = simulate_via_protocol(cmd, x0, doses, seeds, workers=2, env=ENV, progress=False)
    (pid_a, start_a, end_a), (pid_b, start_b, end_b) = map(stamps, res.message)
    assert pid_a != pid_b
    overlap = min(end_a, end_b) - max(start_a, start_b)
    # serial execution would give overlap <= 0; full parallelism ~2 s (less
    # only by the workers' start-up skew)
    assert overlap > 1.0, f"runs did not overlap: {res.message}"


def test_runs_of_one_seed_go_to_one_worker_in_dose_order():
    x0, doses, seeds = make_inputs(8)
    seeds = np.array([7, 9] * 4, dtype=np.uint64)  # two X_0 draws, four sequences each
    x0.iloc[1::2] = x0.iloc[1].to_numpy()
    x0.iloc[0::2] = x0.iloc[0].to_numpy()
    res = simulate_via_protocol(FAULTY, x0, doses, seeds, workers=2, env=ENV, progress=False)
    for seed in (7, 9):
        idx = np.flatnonzero(seeds == seed)
        info = [stamps(res.message[i]) for i in idx]
        assert len({pid for pid, _, _ in info}) == 1
        by_time = idx[np.argsort([start for _, start, _ in info])]
        by_dose = sorted(idx, key=lambda i: tuple(doses[i].ravel()))
        assert list(by_time) == by_dose


def test_plan_groups_orders_prefixes_depth_first():
    seeds = np.array([5, 3, 5, 5, 3], dtype=np.uint64)
    doses = np.array([[[1, 0], [2, 0]], [[0, 0], [0, 0]], [[0, 0], [3, 0]], [[1, 0], [0, 0]],
                      [[0, 0], [1, 0]]], dtype=float)
    groups = plan_groups(seeds, doses)
    assert [list(g) for g in groups] == [[2, 3, 0], [1, 4]]


def test_shorter_runs_with_trailing_nan_hours():
    x0, doses, seeds = make_inputs(4, t=3)
    doses[1, 2] = np.nan
    doses[3, 1:] = np.nan
    res = simulate_via_protocol(FAULTY, x0, doses, seeds, env=ENV, progress=False)
    assert list(res.status) == ["ok"] * 4
    good = expected_features(x0, np.nan_to_num(doses), seeds)
    np.testing.assert_allclose(res.features[1, :2], good[1, :2])
    assert np.isnan(res.features[1, 2]).all() and np.isnan(res.features[3, 1:]).all()
    with pytest.raises(ContractError, match="run 0 has non-finite doses"):
        bad = doses.copy()
        bad[0, 0, 1] = np.nan
        simulate_via_protocol(FAULTY, x0, bad, seeds, env=ENV, progress=False)


def test_hang_in_shell_wrapper_kills_the_grandchild():
    """A timeout kills the whole process group, not just the wrapper shell."""
    x0, doses, seeds = make_inputs(1)
    inner = " ".join([*FAULTY, "--mode=hang"])
    cmd = ["sh", "-c", f"{inner}; echo after"]  # no exec: python is sh's child
    res = simulate_via_protocol(cmd, x0, doses, seeds, timeout_s=1.0, retries=0, env=ENV,
                                progress=False)
    assert res.status[0] == "timeout"
    pids = [int(p) for p in re.findall(r"faulty twin pid (\d+)", res.message[0])]
    assert pids, res.message[0]
    time.sleep(0.2)
    for pid in pids:
        stat = Path(f"/proc/{pid}/stat")
        assert not stat.exists() or stat.read_text().split(") ")[1][0] == "Z"


def test_missing_command_fails_fast_and_clearly():
    x0, doses, seeds = make_inputs(2)
    t0 = time.monotonic()
    with pytest.raises(FileNotFoundError, match="no-such-twin-binary"):
        simulate_via_protocol(["no-such-twin-binary", "--x"], x0, doses, seeds, progress=False)
    with pytest.raises(FileNotFoundError, match="/nonexistent/twin"):
        simulate_via_protocol(["/nonexistent/twin"], x0, doses, seeds, progress=False)
    # an existing interpreter with a missing module: cannot say hello -> ContractError
    with pytest.raises(ContractError, match="cannot start.*no_such_module"):
        simulate_via_protocol([sys.executable, "-m", "no_such_module"], x0, doses, seeds,
                              env=ENV, progress=False)
    assert time.monotonic() - t0 < 5.0


@pytest.mark.parametrize(
    ("mode", "fragment"),
    [
        ("bad_hello", "does not declare required feature(s) HR"),
        ("bad_units", "HR in 'Hz' (expected '/min')"),
        ("bad_protocol", "speaks protocol 2"),
        ("no_hello", "cannot start: worker exited with code 4"),
    ],
)
def test_bad_hello_is_a_contract_error(mode, fragment):
    x0, doses, seeds = make_inputs(2)
    with pytest.raises(ContractError) as err:
        simulate_via_protocol([*FAULTY, f"--mode={mode}"], x0, doses, seeds, workers=2,
                              env=ENV, progress=False)
    assert fragment in str(err.value)
    assert "faulty_twin.py" in str(err.value)


def test_hours_beyond_twin_max_hours_rejected():
    x0, doses, seeds = make_inputs(2, t=3)
    with pytest.raises(ContractError, match="at most 2"):
        simulate_via_protocol([*FAULTY, "--max-hours=2"], x0, doses, seeds, env=ENV,
                              progress=False)


def test_bad_inputs_rejected_before_starting_anything():
    x0, doses, seeds = make_inputs(3)
    kw = {"env": ENV, "progress": False}
    with pytest.raises(ContractError, match="missing column"):
        simulate_via_protocol(FAULTY, x0.drop(columns="Sodium"), doses, seeds, **kw)
    with pytest.raises(ContractError, match="shape"):
        simulate_via_protocol(FAULTY, x0, doses[:2], seeds, **kw)
    neg = doses.copy()
    neg[2, 1, 1] = -0.1
    with pytest.raises(ContractError, match="run 2 hour 2 has a negative vasopressor"):
        simulate_via_protocol(FAULTY, x0, neg, seeds, **kw)
    nan_x0 = x0.copy()
    nan_x0.loc[1, "HR"] = np.nan
    with pytest.raises(ContractError, match="column HR .*row 1"):
        simulate_via_protocol(FAULTY, nan_x0, doses, seeds, **kw)
    with pytest.raises(TypeError, match="not a string"):
        simulate_via_protocol("python -m x", x0, doses, seeds, **kw)
    empty = simulate_via_protocol(FAULTY, x0.iloc[:0], doses[:0], seeds[:0], **kw)
    assert empty.features.shape == (0, 3, len(FEATURES))


def test_progress_line(monkeypatch, capsys):
    monkeypatch.setattr(runner, "PROGRESS_INTERVAL_S", 0.0)
    x0, doses, seeds = make_inputs(3)
    simulate_via_protocol([*FAULTY, "--mode=init_failed:101"], x0, doses, seeds, env=ENV)
    err = capsys.readouterr().err
    assert "[twin] 3/3 runs (100.0%) | failures: init_failed 1 |" in err
    assert "runs/s" in err and "took" in err


def test_protocol_twin_interface():
    x0, doses, seeds = make_inputs(3)
    twin = ProtocolTwin("faulty", FAULTY, workers=2, env=ENV, progress=False)
    hello = twin.hello()
    assert hello["name"] == "faulty" and hello["protocol"] == 1
    assert [f["name"] for f in hello["features"]] == list(FEATURES)
    res = twin.simulate(x0, doses, seeds)
    np.testing.assert_allclose(res.features, expected_features(x0, doses, seeds), atol=1e-9)


def _child_pids(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat[stat.rindex(")") + 2 :].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def test_sigterm_to_the_caller_kills_its_workers(tmp_path):
    """Snakemake cancels a job with SIGTERM: the twin workers must not outlive it."""
    import signal
    import subprocess

    script = tmp_path / "caller.py"
    script.write_text(
        "import sys, numpy as np, pandas as pd\n"
        "from twinfalsify.schema import FEATURES\n"
        "from twinfalsify.runs.runner import simulate_via_protocol\n"
        "x0 = pd.DataFrame({f: [70.0, 71.0] for f in FEATURES})\n"
        f"simulate_via_protocol({[*FAULTY, '--mode=hang']!r}, x0, np.ones((2, 2, 2)),\n"
        "    np.array([1, 2], dtype=np.uint64), workers=2, timeout_s=60, progress=False)\n"
    )
    caller = subprocess.Popen([sys.executable, str(script)], env={**os.environ, **ENV},
                              stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 10
        while len(_child_pids(caller.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = _child_pids(caller.pid)
        assert len(workers) == 2
        time.sleep(0.3)  # let both hellos finish and the hanging requests go out
        caller.send_signal(signal.SIGTERM)
        _, err = caller.communicate(timeout=15)
    finally:
        if caller.poll() is None:
            caller.kill()
            caller.communicate()
    assert caller.returncode == 128 + signal.SIGTERM, err
    time.sleep(0.2)
    assert not any(Path(f"/proc/{pid}").exists() for pid in workers)
