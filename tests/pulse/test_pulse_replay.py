"""The replay twin recorded-pulse: serves recorded real Pulse 4.2 runs, fails clearly otherwise."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pandas as pd
import pytest
from helpers.paths import TESTS

from twinfalsify.pulse.replay import RecordedPulse
from twinfalsify.schema import FEATURES

FIXTURE = TESTS / "fixtures" / "pulse-reference"
SRC = TESTS.parent / "src"
RUNS = pd.read_csv(FIXTURE / "runs.csv")
PATIENTS = pd.read_csv(FIXTURE / "patients.csv").set_index("patient_id")
SEQUENCES = json.loads((FIXTURE / "meta.json").read_text())["design"]["sequences"]


def x0_of(pid: str) -> dict:
    p = PATIENTS.loc[pid]
    return {"age": float(p.age_yr), "sex": 1.0 if p.sex == "Female" else 0.0,
            "weight": float(p.weight_kg), "HR": float(p.HR_baseline_per_min),
            "SysBP": float(p.SBP_baseline_mmHg), "DiaBP": float(p.DBP_baseline_mmHg),
            "RR": float(p.RR_baseline_per_min)}


def sim(twin, pid, doses, hours=4):
    return twin.simulate({"x0": x0_of(pid), "doses": doses, "hours": hours, "seed": 0})


def test_serves_recorded_runs_in_study_units():
    twin = RecordedPulse(FIXTURE)
    res = sim(twin, "P2", SEQUENCES["S3"])
    rows = RUNS[RUNS.run_id == "P2-S3"].set_index("hour")
    assert res["status"] == "ok" and len(res["hours"]) == 4
    for h, feats in enumerate(res["hours"], start=1):
        assert list(feats) == list(FEATURES)
        assert feats["HR"] == rows.at[h, "HeartRate_per_min"]
        assert feats["Glucose"] == pytest.approx(rows.at[h, "Glucose_Aorta_Molarity_mmol_per_L"]
                                                 * 18.0156)
        assert (feats["age"], feats["sex"]) == (30.0, 1.0)
    # a prefix of S5 (hour 1 = S1's hour 1)
    res = sim(twin, "P1", SEQUENCES["S5"][:2], hours=2)
    assert res["status"] == "ok" and len(res["hours"]) == 2


def test_collapsed_recorded_state_is_a_failure():
    res = sim(RecordedPulse(FIXTURE), "P3", SEQUENCES["S4"])
    assert res["status"] == "irreversible" and len(res["hours"]) == 3
    assert "HR = 0.001" in res["message"]


def test_unknown_inputs_fail_clearly():
    twin = RecordedPulse(FIXTURE)
    res = sim(twin, "P1", [[75, 0]] * 4)
    assert res["status"] == "error" and res["hours"] == []
    assert "no recorded run of P1" in res["message"] and "P1-S2" in res["message"]
    res = twin.simulate({"x0": {**x0_of("P1"), "HR": 96.0}, "doses": [[0, 0]], "hours": 1})
    assert res["status"] == "error" and "no recorded patient" in res["message"]
    res = twin.simulate({"x0": {**x0_of("P1"), "HR": 130.0}, "doses": [[0, 0]], "hours": 1})
    assert res["status"] == "init_failed" and "too high" in res["message"]


def test_missing_data_dir_is_a_clear_error(tmp_path):
    from twinfalsify.schema import ContractError

    with pytest.raises(ContractError, match="patients.csv: recorded Pulse data not found"):
        RecordedPulse(tmp_path)


def test_small_study_end_to_end_through_the_protocol():
    """A small study: every recorded patient x sequence x horizon, plus unheld inputs,
    through a real subprocess; collected into the twin-runs contract and checked."""
    reqs, meta = [], []
    for pid in ("P1", "P2", "P3"):
        for sid, doses in SEQUENCES.items():
            for t in (1, 2, 3, 4):
                reqs.append({"op": "simulate", "id": f"{pid}-{sid}-t{t}", "x0": x0_of(pid),
                             "doses": doses, "hours": t, "seed": 0})
                meta.append((pid, sid, t))
    reqs.append({"op": "simulate", "id": "unheld", "x0": x0_of("P1"), "doses": [[20, 0.06]],
                 "hours": 1, "seed": 0})
    meta.append(("P1", "unheld", 1))
    lines = [{"op": "hello", "protocol": 1}, *reqs, {"op": "shutdown"}]
    proc = subprocess.run(
        [sys.executable, "-m", "twinfalsify.pulse.replay", "--data", str(FIXTURE)],
        input="".join(json.dumps(m) + "\n" for m in lines), capture_output=True, text=True,
        env={**os.environ, "PYTHONPATH": str(SRC)}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    answers = [json.loads(x) for x in proc.stdout.splitlines()]
    assert answers[0]["name"] == "recorded-pulse" and answers[-1] == {"op": "bye"}
    results = answers[1:-1]
    assert [r["id"] for r in results] == [r["id"] for r in reqs]  # no run dropped
    rows = []
    for (pid, sid, _t), res in zip(meta, results, strict=True):
        for h, feats in enumerate(res["hours"], start=1):
            rows.append({"run_id": res["id"], "init_stay_id": pid, "actions": sid, "t": h,
                         **feats, "status": res["status"]})
        if not res["hours"]:
            rows.append({"run_id": res["id"], "init_stay_id": pid, "actions": sid, "t": 0,
                         "status": res["status"]})
    df = pd.DataFrame(rows)
    status = {r["id"]: r["status"] for r in results}
    assert status["unheld"] == "error"
    assert status["P3-S4-t4"] == "irreversible" and status["P3-S4-t3"] == "ok"
    assert sum(s == "ok" for s in status.values()) == 59
    # the study-side quantity: mean HR at t = 1 under no treatment over the 3 patients
    t1 = df[(df.actions == "S1") & (df.run_id.str.endswith("t1"))]
    want = RUNS[(RUNS.sequence_id == "S1") & (RUNS.hour == 1)].HeartRate_per_min.mean()
    assert t1.HR.mean() == pytest.approx(want)
