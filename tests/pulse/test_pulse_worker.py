"""The Pulse worker on a fake engine serving recorded real Pulse 4.2 runs.

Expected values are converted INSIDE this test from runs.csv with independent
arithmetic (not the conversions table). One run worked by hand, P1-S2 hour 1
(IV saline 140 mL/h -> 2.33333 mL/min, no norepinephrine), recorded row:
    Sodium_Aorta_Molarity   142.848 mmol/L -> Sodium   142.848 mmol/L
    Chloride_Aorta_Molarity 95.9358 mmol/L -> Chloride 95.9358 mmol/L
    Glucose_Aorta_Molarity  8.16499 mmol/L -> Glucose  8.16499 * 180.156 / 10 = 147.0972 mg/dL
    Calcium_Aorta_Molarity  1.28985 mmol/L (ionised) -> total 2 * 1.28985 = 2.5797 mmol/L
                                              -> Calcium 2.5797 * 40.078 / 10 = 10.33892 mg/dL
    HeartRate 87.689 /min, MAP 96.0435 mmHg, CoreTemperature 37.3759 degC, Weight 79.809 kg,
    age 50 and sex 0 echo X_0.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from helpers.paths import TESTS

from twinfalsify.pulse import units as pu
from twinfalsify.pulse.worker import (
    PulseWorker,
    is_feeding_hour,
    norepinephrine_ml_per_min,
    saline_ml_per_min,
)
from twinfalsify.runs.protocol import check_result
from twinfalsify.schema import FEATURE_TABLE, FEATURES, ContractError

FAKES = TESTS / "fakes"
FIXTURE = TESTS / "fixtures" / "pulse-reference"
SRC = TESTS.parent / "src"
sys.path.insert(0, str(FAKES))
import pulse.engine.PulseEngine as fake_engine  # noqa: E402  (the fake, a test fixture)
from pulse import DATA_ROOT  # noqa: E402  (the fake's stand-in data root)

RUNS = pd.read_csv(FIXTURE / "runs.csv")
PATIENTS = pd.read_csv(FIXTURE / "patients.csv").set_index("patient_id")
META = json.loads((FIXTURE / "meta.json").read_text())
SEQUENCES = META["design"]["sequences"]
RUN_IDS = [f"{p}-{s}" for p in ("P1", "P2", "P3") for s in SEQUENCES]

# Independent conversion: study feature -> (recorded column, factor).
EXPECTED_MAP = {
    "weight": ("Weight_kg", 1.0), "HR": ("HeartRate_per_min", 1.0),
    "SysBP": ("SystolicArterialPressure_mmHg", 1.0),
    "DiaBP": ("DiastolicArterialPressure_mmHg", 1.0),
    "MeanBP": ("MeanArterialPressure_mmHg", 1.0), "RR": ("RespirationRate_per_min", 1.0),
    "Temp_C": ("CoreTemperature_degC", 1.0),
    "Potassium": ("Potassium_Aorta_Molarity_mmol_per_L", 1.0),
    "Sodium": ("Sodium_Aorta_Molarity_mmol_per_L", 1.0),
    "Chloride": ("Chloride_Aorta_Molarity_mmol_per_L", 1.0),
    "Glucose": ("Glucose_Aorta_Molarity_mmol_per_L", 18.0156),
    "Calcium": ("Calcium_Aorta_Molarity_mmol_per_L", 2 * 4.0078),
    "HCO3": ("Bicarbonate_Aorta_Molarity_mmol_per_L", 1.0),
    "paO2": ("ArterialOxygenPressure_mmHg", 1.0),
    "paCO2": ("ArterialCarbonDioxidePressure_mmHg", 1.0), "Arterial_pH": ("BloodPH", 1.0),
}


def x0_of(pid: str) -> dict:
    p = PATIENTS.loc[pid]
    return {"age": float(p.age_yr), "sex": 1.0 if p.sex == "Female" else 0.0,
            "weight": float(p.weight_kg), "HR": float(p.HR_baseline_per_min),
            "SysBP": float(p.SBP_baseline_mmHg), "DiaBP": float(p.DBP_baseline_mmHg),
            "RR": float(p.RR_baseline_per_min), "height_cm": float(p.height_cm),
            # the rest of X_0 (not used by Pulse) as the runner sends it
            "MeanBP": 90.0, "Temp_C": 37.0, "Potassium": 4.0, "Sodium": 140.0,
            "Chloride": 100.0, "Glucose": 100.0, "Calcium": 9.0, "HCO3": 24.0,
            "paO2": 90.0, "paCO2": 40.0, "Arterial_pH": 7.4}


def request(run_id: str, hours: int = 4) -> dict:
    pid, sid = run_id.split("-")
    return {"op": "simulate", "id": run_id, "x0": x0_of(pid), "doses": SEQUENCES[sid],
            "hours": hours, "seed": 1}


def expected(run_id: str) -> tuple[str, list[dict]]:
    rows = RUNS[RUNS.run_id == run_id].set_index("hour")
    x0 = x0_of(run_id.split("-")[0])
    out = []
    for h in range(1, 5):
        r = rows.loc[h]
        feats = {"age": x0["age"], "sex": x0["sex"]}
        feats.update({f: float(r[c]) * k for f, (c, k) in EXPECTED_MAP.items()})
        out.append(feats)
    if run_id == "P3-S4":  # hour 4 collapsed although Pulse reported success
        return "irreversible", out[:3]
    return "ok", out


def assert_hours_equal(got: list[dict], want: list[dict]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert list(g) == list(FEATURES)
        for f in FEATURES:
            assert g[f] == pytest.approx(w[f], rel=1e-12, abs=1e-12), f


@pytest.fixture
def worker(tmp_path):
    w = PulseWorker(state_cache=tmp_path / "cache", data_root=str(DATA_ROOT))
    yield w
    w.close()


def test_hand_worked_run_p1_s2_hour_1(worker):
    res = worker.simulate(request("P1-S2", hours=1))
    h1 = res["hours"][0]
    assert res["status"] == "ok" and res["clamped"] == {}
    assert h1["Sodium"] == pytest.approx(142.848)
    assert h1["Chloride"] == pytest.approx(95.9358)
    assert h1["Glucose"] == pytest.approx(147.0972, abs=1e-4)
    assert h1["Calcium"] == pytest.approx(10.33892, abs=1e-5)
    assert (h1["HR"], h1["MeanBP"], h1["Temp_C"], h1["weight"]) == pytest.approx(
        (87.689, 96.0435, 37.3759, 79.809))
    assert (h1["age"], h1["sex"]) == (50.0, 0.0)


@pytest.mark.parametrize("run_id", RUN_IDS)
def test_worker_output_equals_recorded_values(worker, run_id):
    status, want = expected(run_id)
    res = worker.simulate(request(run_id))
    assert res["status"] == status, res["message"]
    assert_hours_equal(res["hours"], want)
    if status != "ok":
        assert "HR = 0.001" in res["message"] and "hour 4" in res["message"]


def test_every_recorded_run_in_one_worker_reuses_prefixes(tmp_path):
    w = PulseWorker(state_cache=tmp_path / "cache", data_root=str(DATA_ROOT))
    before = dict(fake_engine.CALLS)
    for run_id in RUN_IDS:  # same X_0 consecutively, as the runner sends them
        status, want = expected(run_id)
        res = w.simulate(request(run_id))
        assert res["status"] == status
        assert_hours_equal(res["hours"], want)
    # S5 shares hour 1 with S1: 3 patients x (4 + 4 + 4 + 4 + 3) = 57 of 60 hours
    assert (w.stats.requested_hours, w.stats.simulated_hours) == (60, 57)
    assert fake_engine.CALLS["initialize_engine"] - before["initialize_engine"] == 3
    assert fake_engine.CALLS["advance_hours"] - before["advance_hours"] == 57
    # prefixes of simulated runs cost nothing more, including the collapsed one
    for run_id, hours in (("P3-S1", 2), ("P3-S4", 4), ("P3-S4", 3)):
        res = w.simulate(request(run_id, hours))
        want_status, want = expected(run_id)
        assert res["status"] == (want_status if hours == 4 else "ok")
        assert_hours_equal(res["hours"], want[:hours])
    assert w.stats.simulated_hours == 57
    # a new worker process with the same cache does not stabilise again
    w2 = PulseWorker(state_cache=tmp_path / "cache", data_root=str(DATA_ROOT))
    n_init = fake_engine.CALLS["initialize_engine"]
    assert w2.simulate(request("P2-S3"))["status"] == "ok"
    assert fake_engine.CALLS["initialize_engine"] == n_init and w2.stats.stable_cache_hits == 1
    w.close()
    w2.close()


def _path(run_id: str, holds: list[bool], feature: str = "MeanBP") -> list[list]:
    """A continue_while path over the recorded values of ``run_id``: box s holds on hour s
    iff holds[s-1] (threshold 1 below / above the recorded value, op '>')."""
    want = expected(run_id)[1]
    return [[feature, ">", want[s][feature] + (-1.0 if h else 1.0)] for s, h in enumerate(holds)]


def test_depth_truncation_stops_the_hour_loop_where_no_path_holds(worker):
    """The engine simulates only the hours some continue_while path still needs; the answer
    passes the caller's check of the same rule; a later request continues from the saved
    state, so truncation loses no prefix."""
    run = "P1-S2"
    want = expected(run)[1]
    units = {f.name: f.unit for f in FEATURE_TABLE}
    cases = [  # paths -> hours the engine must simulate
        ([_path(run, [True, False, True])], 2),  # left the path at hour 2
        ([_path(run, [False, True, True]), _path(run, [True, True, False])], 3),
        ([_path(run, [True, True, True])], 4),  # still inside: the run is whole
    ]
    for paths, n in cases:
        w = PulseWorker(state_cache=worker.state_cache, data_root=str(DATA_ROOT))
        before = fake_engine.CALLS["advance_hours"]
        res = w.simulate({**request(run), "continue_while": paths})
        assert fake_engine.CALLS["advance_hours"] - before == n
        assert res["status"] == "ok"
        assert_hours_equal(res["hours"], want[:n])
        assert res.get("truncated", False) is (n < 4)
        assert (w.stats.truncated_runs, w.stats.truncated_hours) == (int(n < 4), 4 - n)
        msg = {"op": "result", "id": run, **res}
        checked = check_result(msg, run, 4, FEATURES, units, FEATURES, paths)
        assert checked.values.shape == (n, len(FEATURES))
        if n == 2:  # the rest of the run continues from the saved hour-2 state
            before = fake_engine.CALLS["advance_hours"]
            rest = w.simulate(request(run))
            assert fake_engine.CALLS["advance_hours"] - before == 2
            assert_hours_equal(rest["hours"], want)
            assert "2 by depth truncation in 1 runs" in w.report()
            # a prefix already simulated is answered whole, at no cost
            again = w.simulate({**request(run), "continue_while": paths})
            assert len(again["hours"]) == 4 and "truncated" not in again
            assert fake_engine.CALLS["advance_hours"] - before == 2
        w.close()
    # a cached prefix the path has left is not continued
    w = PulseWorker(state_cache=worker.state_cache, data_root=str(DATA_ROOT))
    w.simulate(request(run, hours=2))
    before = fake_engine.CALLS["advance_hours"]
    res = w.simulate({**request(run), "continue_while": [_path(run, [False, True, True])]})
    assert len(res["hours"]) == 2 and res["truncated"] is True
    assert fake_engine.CALLS["advance_hours"] == before
    w.close()


def test_bad_continue_while_is_a_clear_error(worker):
    with pytest.raises(ContractError, match="continue_while.*box"):
        worker.simulate({**request("P1-S1"), "continue_while": [[["MeanBP", ">=", 90]]]})


def test_irreversible_state_event_stops_the_run_and_keeps_completed_hours(worker, monkeypatch):
    monkeypatch.setenv(fake_engine.IRREVERSIBLE_ENV, "3")
    res = worker.simulate(request("P1-S2"))
    assert res["status"] == "irreversible"
    assert "IrreversibleState" in res["message"] and "hour 3" in res["message"]
    assert_hours_equal(res["hours"], expected("P1-S2")[1][:2])


def test_out_of_range_baselines_give_init_failed_with_engine_message(tmp_path):
    # Loosen the clamp table so the refused baseline reaches the (fake) engine.
    loose = pu.load_init_limits()
    loose = pu.InitLimits({**loose.ranges, "HR": (0, 300)}, loose.dia_sys_ratio_max,
                          loose.bmi, loose.height_cm)
    w = PulseWorker(state_cache=tmp_path / "c", data_root=str(DATA_ROOT), init_limits=loose)
    req = request("P1-S1")
    req["x0"]["HR"] = 130.0  # recorded R1_HR130
    res = w.simulate(req)
    assert res["status"] == "init_failed" and res["hours"] == []
    assert "heart rate baseline of 130 bpm is too high" in res["message"]
    assert res["message"].split("False): ")[1].replace("[ERROR] [0(s)] ", "") in \
        PATIENTS.loc["R1_HR130"].init_message
    w.close()


def test_default_clamp_reports_and_fixes_r1(worker):
    req = request("P1-S1")
    req["x0"]["HR"] = 130.0
    with pytest.raises(LookupError, match="no recorded patient"):  # clamped HR 110 not recorded
        worker.simulate(req)
    patient, clamped = pu.clamp_x0(req["x0"], height_cm=178)
    assert clamped == {"HR": [130.0, 110.0]} and patient.HR == 110


def test_dose_conversions_and_feeding_schedule():
    assert saline_ml_per_min(140) == pytest.approx(2.33333, rel=1e-5)
    assert norepinephrine_ml_per_min(0.5, 90) == pytest.approx(2.8125)  # recorded P3-S4
    assert [h for h in range(1, 8) if is_feeding_hour(h)] == [4, 7]  # t = 3, 6


def test_actions_sent_only_on_change_and_urination_has_a_comment(worker):
    worker.simulate(request("P1-S1", hours=1))
    acts = worker._actions(4, (140.0, 0.1), (140.0, 0.0), 80.0)
    names = [type(a).__name__ for a in acts]
    assert names == ["SEConsumeNutrients", "SEUrinate", "SESubstanceInfusion"]
    assert acts[1].get_comment()
    assert worker._actions(2, (140.0, 0.1), (140.0, 0.1), 80.0) == []


def test_bad_requests_raise_clear_errors(worker):
    from twinfalsify.schema import ContractError

    req = request("P1-S1")
    with pytest.raises(ContractError, match="hours"):
        worker.simulate({**req, "hours": 5})
    with pytest.raises(ContractError, match=r"doses\[1\]"):
        worker.simulate({**req, "doses": [[0, 0], [-1, 0], [0, 0], [0, 0]]})


def test_module_imports_without_pulse():
    code = ("import sys; sys.modules['pulse'] = None; "
            "import twinfalsify.pulse.worker as w; print(w.PulseWorker.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(SRC)}, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "PulseWorker", out.stderr


def test_worker_subprocess_over_the_protocol(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), str(FAKES)])}
    cut = {**request("P1-S3"), "id": "cut", "continue_while": [_path("P1-S3", [False])]}
    lines = ([{"op": "hello", "protocol": 1}, cut] + [request(r) for r in RUN_IDS]
             + [{"op": "shutdown"}])
    proc = subprocess.run(
        [sys.executable, "-m", "twinfalsify.pulse.worker", "--state-cache",
         str(tmp_path / "cache"), "--data-root", str(DATA_ROOT)],
        input="".join(json.dumps(m) + "\n" for m in lines), capture_output=True, text=True,
        env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    answers = [json.loads(x) for x in proc.stdout.splitlines()]  # stdout = protocol only
    hello, cut, results, bye = answers[0], answers[1], answers[2:-1], answers[-1]
    assert cut["status"] == "ok" and cut["truncated"] is True and len(cut["hours"]) == 1
    assert hello["name"] == "pulse" and hello["version"] == "4.2.0" and hello["protocol"] == 1
    assert [f["name"] for f in hello["features"]] == list(FEATURES)
    assert hello["capabilities"] == {"save_restore": True, "max_hours": 4, "truncate": True}
    assert bye == {"op": "bye"} and len(results) == len(RUN_IDS)
    for run_id, res in zip(RUN_IDS, results, strict=True):
        status, want = expected(run_id)
        assert res["id"] == run_id and res["status"] == status
        assert_hours_equal(res["hours"], want)
    # P1-S3's hour 1 was simulated by the truncated request: 57 of 64 requested hours,
    # 3 saved by depth truncation, 4 by prefix reuse
    assert ("simulated 57 engine-hours for 64 requested hours (4 saved by prefix reuse, 3 by "
            "depth truncation in 1 runs)") in proc.stderr


def _serve(args: list[str], env: dict, cwd) -> subprocess.CompletedProcess:
    lines = [{"op": "hello", "protocol": 1}, request("P1-S1"), {"op": "shutdown"}]
    return subprocess.run(
        [sys.executable, "-m", "twinfalsify.pulse.worker", *args],
        input="".join(json.dumps(m) + "\n" for m in lines), capture_output=True, text=True,
        env=env, cwd=cwd, timeout=120)


def test_wrong_data_root_answers_hello_not_ok(tmp_path):
    """Default --data-root ./ in a folder that is not Pulse's bin/ (as under Snakemake): the
    worker answers hello with ok: false naming --data-root / PULSE_DATA_ROOT and exits 2,
    before any engine starts (the fake, like real Pulse, would die with SIGSEGV)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), str(FAKES)])}
    env.pop("PULSE_DATA_ROOT", None)
    proc = _serve(["--state-cache", str(tmp_path / "c")], env, tmp_path)
    assert proc.returncode == 2, proc.stderr
    hello = json.loads(proc.stdout.splitlines()[0])
    assert hello["op"] == "hello" and hello["ok"] is False
    msg = hello["message"]
    assert "--data-root" in msg and "PULSE_DATA_ROOT" in msg and "substances/" in msg
    assert len(proc.stdout.splitlines()) == 1  # nothing simulated after a refused hello
    # the environment variable is honoured
    ok = _serve(["--state-cache", str(tmp_path / "c")], {**env, "PULSE_DATA_ROOT": str(DATA_ROOT)},
                tmp_path)
    assert ok.returncode == 0 and json.loads(ok.stdout.splitlines()[0])["ok"] is True


def test_fake_engine_crashes_like_real_pulse_without_data_root(tmp_path):
    """The check above is needed: an engine started on a bad data root dies with SIGSEGV."""
    code = ("import sys; sys.path[:0] = [sys.argv[1], sys.argv[2]]\n"
            "from twinfalsify.pulse.worker import PulseWorker\n"
            "w = PulseWorker(state_cache=sys.argv[3], data_root=sys.argv[3])\n"
            "w._ready = True  # skip the worker's check: what would the engine do?\n"
            f"w.simulate({request('P1-S1')!r})\n")
    proc = subprocess.run([sys.executable, "-c", code, str(SRC), str(FAKES), str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -11, (proc.returncode, proc.stderr[-500:])


def test_runner_stops_at_once_on_a_refused_hello(tmp_path):
    """Through the runner: one line naming the fix, no run attempted, no retries."""
    from twinfalsify.runs.runner import simulate_via_protocol

    x0 = pd.DataFrame([{f: 1.0 for f in FEATURES}])
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {"PYTHONPATH": os.pathsep.join([str(SRC), str(FAKES)]), "PULSE_DATA_ROOT": str(tmp_path),
           "TMPDIR": str(tmp)}
    with pytest.raises(ContractError, match="PULSE_DATA_ROOT") as err:
        simulate_via_protocol([sys.executable, "-m", "twinfalsify.pulse.worker"], x0,
                              np.zeros((1, 1, 2)), np.array([1], dtype=np.uint64), env=env,
                              progress=False)
    assert "\n" not in str(err.value).split("; stderr tail")[0]
    # the killed worker's temporary folder (prefix states) went with the runner's scratch
    assert list(tmp.iterdir()) == []
