"""The Pulse worker driven by a REAL Pulse 4.2 engine (opt-in: ``pytest -m pulse``).

Skipped, with one line saying why, unless a real Pulse build is reachable:

    PULSE_PYTHON       interpreter with Pulse's Python dependencies (default: this one)
    PULSE_PYTHONPATH   the build's ``install/bin`` and ``install/python`` (os.pathsep-joined)
    PULSE_DATA_ROOT    the build's ``install/bin`` (Pulse's data folders)

``envs/pulse/build.sh SRC PREFIX`` prints ``export PYTHONPATH=...`` (the value to give
PULSE_PYTHONPATH) and ``export PULSE_DATA_ROOT=...``; PULSE_PYTHON is PREFIX/venv/bin/python.
Every test talks to the worker as the runner does (a subprocess over the protocol) except
the refused patient, which needs the worker's clamp turned off. Cost on a 2-core machine:
about 11 simulated engine-hours in all; docs/reference/benchmarks.md has the measured times.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from helpers.paths import TESTS

from twinfalsify.schema import FEATURES

pytestmark = pytest.mark.pulse

SRC = TESTS.parent / "src"
FIXTURE = TESTS / "fixtures" / "pulse-reference"
PYTHON = os.environ.get("PULSE_PYTHON", sys.executable)
ENGINE_PATH = os.environ.get("PULSE_PYTHONPATH", "")
DATA_ROOT = os.environ.get("PULSE_DATA_ROOT", "")
TIMEOUT_S = 3600


def pulse_env() -> dict[str, str]:
    path = os.pathsep.join(p for p in (str(SRC), ENGINE_PATH) if p)
    return {**os.environ, "PYTHONPATH": path, "PULSE_DATA_ROOT": DATA_ROOT}


def _why_no_pulse() -> str | None:
    if not DATA_ROOT:
        return "PULSE_DATA_ROOT is not set (no real Pulse build: envs/pulse/build.sh)"
    probe = subprocess.run(
        [PYTHON, "-c", "import PyPulse, pulse.engine.PulseEngine as e; print(e.version())"],
        capture_output=True, text=True, env=pulse_env(), timeout=120)
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["?"])[-1]
        return f"real Pulse does not import with PULSE_PYTHON={PYTHON}: {last}"
    return None


WHY = _why_no_pulse()
if WHY:
    pytestmark = [pytest.mark.pulse, pytest.mark.skip(reason=WHY)]

RUNS = pd.read_csv(FIXTURE / "runs.csv")
PATIENTS = pd.read_csv(FIXTURE / "patients.csv").set_index("patient_id")
META = json.loads((FIXTURE / "meta.json").read_text())
# Recorded column and factor for a few features (independent of the worker's table).
CHECK = {"HR": ("HeartRate_per_min", 1.0), "MeanBP": ("MeanArterialPressure_mmHg", 1.0),
         "Sodium": ("Sodium_Aorta_Molarity_mmol_per_L", 1.0),
         "Glucose": ("Glucose_Aorta_Molarity_mmol_per_L", 18.0156)}


def x0_of(pid: str, **override: float) -> dict[str, float]:
    p = PATIENTS.loc[pid]
    x0 = {f: 0.0 for f in FEATURES}
    x0.update(age=float(p["age_yr"]), sex=1.0 if p["sex"] == "Female" else 0.0,
              weight=float(p["weight_kg"]), HR=float(p["HR_baseline_per_min"]),
              SysBP=float(p["SBP_baseline_mmHg"]), DiaBP=float(p["DBP_baseline_mmHg"]),
              RR=float(p["RR_baseline_per_min"]), height_cm=float(p["height_cm"]))
    x0.update(override)
    return x0


def request(rid: str, x0: dict, doses: list, hours: int | None = None) -> dict:
    return {"op": "simulate", "id": rid, "x0": x0, "doses": doses,
            "hours": hours or len(doses), "seed": 1}


def serve(requests: list[dict], cache: Path) -> tuple[dict, list[dict], str, float]:
    """Run the worker as the runner does; (hello, results, stderr, wall seconds)."""
    lines = [{"op": "hello", "protocol": 1}, *requests, {"op": "shutdown"}]
    start = time.monotonic()
    proc = subprocess.run(
        [PYTHON, "-m", "twinfalsify.pulse.worker", "--state-cache", str(cache)],
        input="".join(json.dumps(m) + "\n" for m in lines), capture_output=True, text=True,
        env=pulse_env(), cwd=cache.parent, timeout=TIMEOUT_S)
    wall = time.monotonic() - start
    assert proc.returncode == 0, proc.stderr[-2000:]
    answers = [json.loads(x) for x in proc.stdout.splitlines()]
    assert answers[-1] == {"op": "bye"}
    print(f"[pulse] {len(requests)} request(s) in {wall:.0f} s wall; "
          f"{proc.stderr.strip().splitlines()[-1]}")
    return answers[0], answers[1:-1], proc.stderr, wall


def recorded(run_id: str, hour: int, feature: str) -> float:
    col, factor = CHECK[feature]
    row = RUNS[(RUNS["run_id"] == run_id) & (RUNS["hour"] == hour)].iloc[0]
    return float(row[col]) * factor


def test_p3_s4_both_actions_feeding_hour_collapse_and_branching(tmp_path):
    """P3 with 400 mL/h saline + 0.5 ug/kg/min norepinephrine for 4 h (the recorded S4):
    hours 1-3 equal the recording; hour 4 starts with the meal, water and urination and
    ends in the recorded collapsed state (HR 0.001/min), reported "irreversible". Then a
    branch sharing hour 1 reuses the saved state: its hour 1 is bit-identical."""
    s4 = [list(d) for d in META["design"]["sequences"]["S4"]]
    x0 = x0_of("P3")
    branch = [s4[0], [0.0, 0.0]]
    hello, (full, br), err, _ = serve([request("s4", x0, s4), request("br", x0, branch)],
                                      tmp_path / "cache")
    assert hello["ok"] and hello["version"].startswith("4.2")
    assert full["status"] == "irreversible" and "HR" in full["message"]
    assert len(full["hours"]) == 3 and full["clamped"] == {}
    for h in (1, 2, 3):
        for f in CHECK:
            assert full["hours"][h - 1][f] == pytest.approx(recorded("P3-S4", h, f), rel=1e-4)
    assert br["status"] == "ok" and br["hours"][0] == full["hours"][0]  # restored, not redone
    # 4 hours for S4 + 1 new hour for the branch: 5 engine-hours for 6 requested
    assert "simulated 5 engine-hours for 6 requested hours" in err


def test_each_action_type_and_the_state_cache(tmp_path):
    """P1 for one hour with no treatment, saline alone, norepinephrine alone: hour 1 of
    no treatment and of saline equals the recording; norepinephrine raises MAP over no
    treatment. A second worker process restores the cached stabilised state and gives
    bit-identical values."""
    x0 = x0_of("P1")
    reqs = [request("none", x0, [[0.0, 0.0]]), request("iv", x0, [[140.0, 0.0]]),
            request("ne", x0, [[0.0, 0.23]])]
    _, res, err, _ = serve(reqs, tmp_path / "cache")
    assert [r["status"] for r in res] == ["ok"] * 3
    for f in CHECK:
        assert res[0]["hours"][0][f] == pytest.approx(recorded("P1-S1", 1, f), rel=1e-4)
        assert res[1]["hours"][0][f] == pytest.approx(recorded("P1-S2", 1, f), rel=1e-4)
    assert res[2]["hours"][0]["MeanBP"] > res[0]["hours"][0]["MeanBP"]
    assert "1 stabilisations" in err
    _, again, err2, _ = serve(reqs[:1], tmp_path / "cache")
    assert again[0]["hours"] == res[0]["hours"] and "1 stabilised-state cache hits" in err2


def test_depth_truncation_stops_the_engine_and_keeps_the_prefix(tmp_path):
    """P1 with the recorded S2 for 3 hours, and a continue_while path that leaves at hour 1
    (MAP above the recorded hour-1 value + 1): the engine simulates hour 1 only and answers
    it, flagged truncated. A later request for 2 hours continues from the saved hour-1
    state: hour 1 is bit-identical, hour 2 equals the recording."""
    s2 = [list(d) for d in META["design"]["sequences"]["S2"]]
    x0 = x0_of("P1")
    leave = [["MeanBP", ">", recorded("P1-S2", 1, "MeanBP") + 1.0], ["MeanBP", "any", 0.0]]
    cut = {**request("cut", x0, s2[:3]), "continue_while": [leave]}
    hello, (res, rest), err, _ = serve([cut, request("rest", x0, s2[:2])], tmp_path / "cache")
    assert hello["capabilities"]["truncate"] is True
    assert res["status"] == "ok" and res["truncated"] is True and len(res["hours"]) == 1
    assert rest["status"] == "ok" and "truncated" not in rest
    assert rest["hours"][0] == res["hours"][0]
    for h in (1, 2):
        for f in CHECK:
            assert rest["hours"][h - 1][f] == pytest.approx(recorded("P1-S2", h, f), rel=1e-4)
    assert ("simulated 2 engine-hours for 5 requested hours (1 saved by prefix reuse, 2 by "
            "depth truncation in 1 runs)") in err


def test_clamped_patient_runs_and_says_so(tmp_path):
    """HR 130 is outside Pulse's baseline range: the worker clamps it to 110, the engine
    accepts, and the run carries the clamp."""
    _, (res,), _, _ = serve([request("c", x0_of("P1", HR=130.0), [[0.0, 0.0]])],
                            tmp_path / "cache")
    assert res["status"] == "ok" and res["clamped"] == {"HR": [130.0, 110.0]}


def test_refused_patient_gets_the_engines_words(tmp_path):
    """Without the clamp, real Pulse refuses HR 130: init_failed with its [ERROR] line."""
    code = (
        "import json, sys\n"
        "from twinfalsify.pulse.units import InitLimits, load_init_limits\n"
        "from twinfalsify.pulse.worker import PulseWorker\n"
        "lim = load_init_limits()\n"
        "loose = InitLimits({**lim.ranges, 'HR': (0, 300)}, lim.dia_sys_ratio_max, lim.bmi,\n"
        "                   lim.height_cm)\n"
        "w = PulseWorker(state_cache=sys.argv[1], init_limits=loose, data_root=sys.argv[2])\n"
        "print(json.dumps(w.simulate(json.loads(sys.argv[3]))))\n"
    )
    req = request("r", x0_of("P1", HR=130.0), [[0.0, 0.0]])
    proc = subprocess.run([PYTHON, "-c", code, str(tmp_path / "c"), DATA_ROOT, json.dumps(req)],
                          capture_output=True, text=True, env=pulse_env(), timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["status"] == "init_failed"
    assert "heart rate baseline of 130" in res["message"] and "110" in res["message"]
