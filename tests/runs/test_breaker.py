"""The circuit breaker judges the twin, not one patient; implausible runs count as failures.

- a twin that cannot simulate one X_0 (init_failed, or a crash) finishes its shard with
  that X_0's runs recorded as failed, even when that X_0's runs come first in the schedule
  and outnumber ``fail_fast_runs``;
- a twin that fails every X_0 still trips after exactly ``fail_fast_runs`` runs, and those
  come from that many distinct X_0;
- ``implausible`` (a value outside the contract's range) is a failure for the progress line
  and the breaker, a shard with implausible runs prints one warning, and the figures' "no
  testable hypothesis" error names the cause when no twin run succeeded.
"""

from __future__ import annotations

import io

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV
from helpers.twins import study_bits

from twinfalsify import summary
from twinfalsify.runs import runner
from twinfalsify.runs.plan import TwinPlan, run_shard
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.runner import plan_groups, simulate_via_protocol
from twinfalsify.schema import FEATURES, ContractError


def _patients(n_x0: int, n_seq: int, t: int = 2):
    """n_x0 X_0 (seed 1000 + k), each with n_seq distinct dose sequences: n_x0 * n_seq runs."""
    from twinfalsify.sources.synthetic import generate

    d = generate({"n_stays": max(40, n_x0)}, seed=3)  # X_0 inside the contract's ranges
    base = d[d.t == 0].iloc[:n_x0][list(FEATURES)].reset_index(drop=True)
    x0 = base.loc[np.repeat(np.arange(n_x0), n_seq)].reset_index(drop=True)
    doses = np.zeros((n_x0 * n_seq, t, 2))
    doses[:, 0, 0] = np.tile(np.arange(n_seq) * 10.0, n_x0)
    seeds = np.repeat(np.arange(1000, 1000 + n_x0), n_seq).astype(np.uint64)
    return x0, doses, seeds


def _first_scheduled_seed(doses, seeds) -> int:
    """The X_0 whose runs the runner's plan puts first (the one that used to trip it)."""
    return int(seeds[plan_groups(seeds, doses)[0][0]])


@pytest.mark.parametrize(("mode", "retries"), [("init_failed", 2), ("crash", 0)])
def test_one_failing_patient_does_not_stop_the_shard(mode, retries):
    x0, doses, seeds = _patients(n_x0=5, n_seq=12)
    bad = _first_scheduled_seed(doses, seeds)
    res = simulate_via_protocol([*FAULTY_TWIN, f"--mode={mode}:{bad}"], x0, doses, seeds,
                                env=ENV, workers=1, retries=retries, fail_fast_runs=5,
                                max_restarts=5, progress=False)
    failed = res.status != "ok"
    assert (failed == (seeds == bad)).all()  # exactly that patient's 12 runs, all recorded
    assert set(res.status[failed]) == {"init_failed" if mode == "init_failed" else "error"}
    ok = np.flatnonzero(~failed)
    assert np.isfinite(res.features[ok]).all()


def test_a_twin_failing_every_patient_trips_after_k_runs_from_k_patients(tmp_path):
    log = tmp_path / "requests.log"
    k = 8
    x0, doses, seeds = _patients(n_x0=30, n_seq=5)
    with pytest.raises(ContractError) as err:
        simulate_via_protocol([*FAULTY_TWIN, "--mode=init_failed", f"--log-requests={log}"],
                              x0, doses, seeds, env=ENV, workers=1, fail_fast_runs=k,
                              progress=False)
    msg = str(err.value)
    assert f"its first {k} runs, from {k} distinct X_0, all failed" in msg and "\n" not in msg
    asked = [int(s) for s in log.read_text().split()]
    assert len(asked) == k and len(set(asked)) == k  # one run per patient, K patients


def test_fewer_patients_than_k_all_failing_still_trips_after_k_runs(tmp_path):
    log = tmp_path / "requests.log"
    x0, doses, seeds = _patients(n_x0=3, n_seq=10)
    with pytest.raises(ContractError, match="its first 8 runs, from 3 distinct X_0, all failed"):
        simulate_via_protocol([*FAULTY_TWIN, "--mode=error", f"--log-requests={log}"],
                              x0, doses, seeds, env=ENV, workers=1, fail_fast_runs=8,
                              progress=False)
    asked = [int(s) for s in log.read_text().split()]
    assert len(asked) == 8 and asked[:3] == sorted(set(asked))  # each X_0 once, then more


def test_probing_keeps_one_worker_per_patient_in_dose_order():
    """With two workers and a failing first patient, each X_0's runs still go to one
    worker (a save/restore twin keeps its prefixes) in dose order, probe first."""
    x0, doses, seeds = _patients(n_x0=4, n_seq=6)
    bad = _first_scheduled_seed(doses, seeds)
    res = simulate_via_protocol([*FAULTY_TWIN, f"--mode=error:{bad}"], x0, doses, seeds,
                                env=ENV, workers=2, retries=0, progress=False)
    for seed in set(seeds.tolist()) - {bad}:
        idx = np.flatnonzero(seeds == seed)
        stamps = [dict(w.split("=") for w in res.message[i].split()) for i in idx]
        assert len({s["pid"] for s in stamps}) == 1
        by_time = idx[np.argsort([float(s["start"]) for s in stamps])]
        assert list(by_time) == sorted(idx, key=lambda i: tuple(doses[i].ravel()))


def test_implausible_trips_the_breaker_and_shows_in_the_progress_line(monkeypatch, capsys):
    x0, doses, seeds = _patients(n_x0=10, n_seq=3)
    with pytest.raises(ContractError) as err:
        simulate_via_protocol([*FAULTY_TWIN, "--mode=implausible"], x0, doses, seeds,
                              env=ENV, fail_fast_runs=5, progress=False, check_range=True)
    assert "its first 5 runs, from 5 distinct X_0, all failed" in str(err.value)
    assert "first failure: implausible: hour 2: HR = 1e+300 /min outside" in str(err.value)
    monkeypatch.setattr(runner, "PROGRESS_INTERVAL_S", 0.0)
    res = simulate_via_protocol([*FAULTY_TWIN, "--mode=implausible:1001"], x0, doses, seeds,
                                env=ENV, check_range=True)
    assert (res.status == "ok").all()  # the twin's answer; a study marks it when storing
    assert (res.features[seeds == 1001, 1, FEATURES.index("HR")] == 1e300).all()
    assert "| failures: implausible 3 |" in capsys.readouterr().err


def test_shard_with_implausible_runs_warns_once():
    x0, plan, actions = study_bits()
    seeds = plan.run_seeds()
    n_bad = int((seeds % 2 == 0).sum())
    twin = ProtocolTwin("faulty", [*FAULTY_TWIN, "--mode=implausible:%2=0"], env=ENV,
                        progress=False, retries=0)
    log = io.StringIO()
    run_shard(twin, plan, 0, x0, actions, log=log)
    warnings = [ln for ln in log.getvalue().splitlines() if "WARNING" in ln]
    assert warnings == [
        f"WARNING: twin faulty shard 0: {n_bad} of {len(seeds)} runs implausible (counted as "
        "failed), e.g. hour 2: HR = 1e+300 /min outside the plausible range [0, 300]"]
    log = io.StringIO()
    plan_ok = TwinPlan(**{**plan.to_json()})
    run_shard(ProtocolTwin("good", FAULTY_TWIN, env=ENV, progress=False), plan_ok, 0, x0,
              actions, log=log)
    assert "WARNING" not in log.getvalue()


def test_no_testable_hypothesis_names_failed_twin_runs_as_the_cause():
    res = pd.DataFrame({"hyp_id": [1, 2], "outcome": ["HR", "HR"], "kind": ["causal"] * 2,
                        "t": [1, 2], "n": [10, 12], "nhat": [0, 0], "p_value": [1.0, 1.0],
                        "rejected": [False, False], "method": ["hoeffding"] * 2,
                        "side": ["lo", "lo"]})
    with pytest.raises(ContractError) as err:
        summary.pick_hypothesis(res, rejected=True, run_status={"implausible": 16800})
    assert str(err.value) == (
        "figures: no testable hypothesis (every one has n = 0 or nhat = 0): no twin run "
        "succeeded (node-runs by status: implausible 16800; see the twin's "
        "run_summary.json)")
    with pytest.raises(ContractError) as err:  # runs did succeed: no cause claimed
        summary.pick_hypothesis(res, rejected=True, run_status={"ok": 5, "implausible": 1})
    assert str(err.value).endswith("nhat = 0)")
