"""Fake pulse.engine.PulseEngine serving recorded Pulse 4.2 values (test fixture).

The engine's "state" is (recorded patient, hour, infusion settings, per-hour
history of settings); advancing one hour looks up the recorded run whose
settings for hours 1..h equal the history and serves its row h. The patient
checks mirror Pulse 4.2's initialisation errors (constants from Pulse's source
messages, written here independently of the worker's clamp table).
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
from enum import Enum
from pathlib import Path

from pulse.cdm.engine import SEDataRequestManager
from pulse.cdm.patient import SEPatientConfiguration, eSex
from pulse.cdm.patient_actions import (
    SEConsumeNutrients,
    SESubstanceCompoundInfusion,
    SESubstanceInfusion,
    SEUrinate,
)
from pulse.cdm.scalars import MassPerVolumeUnit, VolumePerTimeUnit

FIXTURE = Path(__file__).resolve().parents[3] / "fixtures" / "pulse-reference"
STANDARD_MEAL = {"carbohydrate": 130, "carbohydrate_digestion_rate": 1.083, "fat": 27,
                 "fat_digestion_rate": 0.055, "protein": 20, "protein_digestion_rate": 0.071,
                 "calcium": 500, "sodium": 1.0, "water": 0.5}
IRREVERSIBLE_ENV = "FAKE_PULSE_IRREVERSIBLE_AT_HOUR"

# Counters the tests read (how much the "engine" was used in this process).
CALLS = {"initialize_engine": 0, "serialize_from_file": 0, "serialize_to_file": 0,
         "advance_hours": 0}


class eModelType(Enum):
    HumanAdultWholeBody = 0


def version() -> str:
    return "4.2.0"


def hash() -> str:  # noqa: A001 - same name as the real module's function
    return ""


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=2e-5, abs_tol=1e-9)


def _recordings(root: Path | None = None):
    root = Path(os.environ.get("FAKE_PULSE_RECORDINGS", root or FIXTURE))
    with open(root / "patients.csv", newline="") as f:
        patients = [r for r in csv.DictReader(f) if r["kind"] == "in_range"]
    with open(root / "runs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    runs: dict[str, dict[int, dict]] = {}
    for r in rows:
        runs.setdefault(r["run_id"], {})[int(r["hour"])] = r
    return patients, runs


def _settings(row: dict) -> tuple[float, float, bool]:
    """(saline mL/min, norepinephrine ug/min, meal+urination sent) of a recorded hour."""
    saline = float(row["pulse_saline_rate_mL_per_min"] or 0)
    ne_rate = float(row["pulse_ne_rate_mL_per_min"] or 0)
    ne_conc = float(row["pulse_ne_concentration_ug_per_mL"] or 0)
    return saline, ne_rate * ne_conc, row["nutrition_urinate_applied"] == "yes"


def patient_errors(sex: eSex, age: float, weight: float, height_cm: float, hr: float,
                   sbp: float, dbp: float, rr: float) -> list[str]:
    """Pulse 4.2's initialisation [ERROR]s for these baselines (empty = accepted)."""
    e = []
    if age < 18:
        e.append(f"Patient age of {age:g} years is too young. We do not model pediatrics. "
                 "Minimum age allowed is 18 years.")
    if age > 65:
        e.append(f"Patient age of {age:g} years is too old. We do not model geriatrics. "
                 "Maximum age allowed is 65 years.")
    height_ft = height_cm / 30.48
    if height_ft < 4.5 or height_ft > 7.0:
        e.append("Patient height setting is outrageous. It must be between 4.5 and 7.0 ft")
    bmi = weight / (height_cm / 100) ** 2
    if bmi > 30:
        e.append(f"Patient Body Mass Index (BMI) of {bmi:g}  kg/m^2 is too high. Obese patients "
                 "must be modeled by adding/using a condition. Maximum BMI allowed is 30 kg/m^2.")
    if bmi < 16:
        e.append(f"Patient Body Mass Index (BMI) of {bmi:g} kg/m^2 is too low.")
    if hr > 110:
        e.append(f"Patient heart rate baseline of {hr:g} bpm is too high. Maximum heart rate "
                 "baseline allowed is 110 bpm.")
    if hr < 50:
        e.append(f"Patient heart rate baseline of {hr:g} is too low. Minimum heart rate "
                 "baseline allowed is 50 bpm.")
    if sbp < 90:
        e.append(f"Patient systolic pressure baseline of {sbp:g} mmHg is too low. Hypotension "
                 "must be modeled by adding/using a condition. Minimum systolic pressure "
                 "baseline allowed is 90 mmHg.")
    if sbp > 120:
        e.append(f"Patient systolic pressure baseline of {sbp:g} mmHg is too high.")
    if dbp < 60:
        e.append(f"Patient diastolic pressure baseline of {dbp:g} mmHg is too low.")
    if dbp > 80:
        e.append(f"Patient diastolic pressure baseline of {dbp:g} mmHg is too high.")
    if dbp > 0.75 * sbp:
        e.append(f"Patient baseline pulse pressure (systolic vs. diastolic pressure fraction) of "
                 f"{dbp / sbp:g} is abnormally narrow. Minimum fraction allowed is 0.75 .")
    if rr < 8:
        e.append(f"Patient respiration rate baseline of {rr:g} is too low.")
    if rr > 20:
        e.append(f"Patient respiration rate baseline of {rr:g} is too high.")
    return e


class PulseEngine:
    def __init__(self, eModelType=eModelType.HumanAdultWholeBody, data_root_dir: str = "./"):
        self._data_root_dir = data_root_dir
        self._log_file: str | None = None
        self._is_ready = False
        self._requests: list = []
        self._state: dict | None = None
        self._row: dict | None = None
        self._pending: list = []
        self._dt_s = 0.02

    # -------------------------------------------------------------- logging
    def set_log_filename(self, filename: str) -> None:
        self._log_file = filename

    def log_to_console(self, b: bool) -> None:
        pass  # the fake never writes to stdout

    def _log(self, level: str, msg: str) -> None:
        if self._log_file:
            with open(self._log_file, "a") as f:
                f.write(f"[{level}] [0(s)] {msg}\n")

    # -------------------------------------------------------------- set up
    def _check_data_root(self) -> None:
        """Real Pulse 4.2 logs this, then segfaults, when its data root lacks substances/."""
        if not (Path(self._data_root_dir) / "substances").is_dir():
            self._log("ERROR", f"Unable to find substance directory : {self._data_root_dir}")
            os.kill(os.getpid(), signal.SIGSEGV)

    def _set_requests(self, drm: SEDataRequestManager) -> None:
        if not isinstance(drm, SEDataRequestManager):
            raise TypeError(f"data_request_mgr must be SEDataRequestManager, got {drm!r}")
        self._requests = [r.column() for r in drm.get_data_requests()]

    def initialize_engine(self, patient_configuration: SEPatientConfiguration,
                          data_request_mgr: SEDataRequestManager) -> bool:
        CALLS["initialize_engine"] += 1
        self._check_data_root()
        self._set_requests(data_request_mgr)
        p = patient_configuration.get_patient()
        vals = dict(sex=p.get_sex(), age=p.get_age().get_value(), weight=p.get_weight().get_value(),
                    height_cm=p.get_height().get_value(),
                    hr=p.get_heart_rate_baseline().get_value(),
                    sbp=p.get_systolic_arterial_pressure_baseline().get_value(),
                    dbp=p.get_diastolic_arterial_pressure_baseline().get_value(),
                    rr=p.get_respiration_rate_baseline().get_value())
        units = (p.get_age().unit_string(), p.get_weight().unit_string(),
                 p.get_height().unit_string(), p.get_heart_rate_baseline().unit_string())
        if units != ("yr", "kg", "cm", "1/min"):
            raise NotImplementedError(f"fake pulse: patient units {units} not supported")
        errors = patient_errors(**vals)
        if errors:
            for e in errors:
                self._log("ERROR", e)
            self._is_ready = False
            return False
        patients, runs = _recordings()
        for rec in patients:
            sex = eSex.Female if rec["sex"] == "Female" else eSex.Male
            if sex == vals["sex"] and all(_close(float(rec[c]), vals[k]) for c, k in (
                    ("age_yr", "age"), ("weight_kg", "weight"), ("height_cm", "height_cm"),
                    ("HR_baseline_per_min", "hr"), ("SBP_baseline_mmHg", "sbp"),
                    ("DBP_baseline_mmHg", "dbp"), ("RR_baseline_per_min", "rr"))):
                pid = rec["patient_id"]
                break
        else:
            raise LookupError(f"fake pulse: no recorded patient with baselines {vals}")
        self._state = {"patient_id": pid, "hour": 0, "saline": 0.0, "ne_ug_min": 0.0,
                       "history": [], "failed": False}
        self._row = runs[f"{pid}-S1"][0]
        self._is_ready = True
        return True

    def serialize_to_file(self, state_file: str) -> bool:
        if not self._is_ready:
            return False
        CALLS["serialize_to_file"] += 1
        with open(state_file, "w") as f:
            json.dump({"fake_pulse_state": 1, **self._state}, f)
        return True

    def serialize_from_file(self, state_file: str,
                            data_request_mgr: SEDataRequestManager) -> bool:
        CALLS["serialize_from_file"] += 1
        self._check_data_root()
        self._set_requests(data_request_mgr)
        try:
            with open(state_file) as f:
                state = json.load(f)
        except (OSError, json.JSONDecodeError):
            self._is_ready = False
            return False
        state.pop("fake_pulse_state", None)
        self._state = state
        self._row = self._lookup(state["patient_id"], state["history"])
        self._is_ready = True
        return True

    # -------------------------------------------------------------- running
    def process_actions(self, actions: list) -> bool:
        if not self._is_ready:
            return False
        for a in actions:
            if isinstance(a, SESubstanceCompoundInfusion):
                if a.get_compound() != "Saline":
                    raise LookupError(f"fake pulse: compound {a.get_compound()!r} not recorded")
                if not a.get_bag_volume().get_value() > 0:
                    raise ValueError("fake pulse: infusion bag volume must be > 0")
                self._state["saline"] = a.get_rate().get_value(VolumePerTimeUnit.mL_Per_min)
            elif isinstance(a, SESubstanceInfusion):
                if a.get_substance() != "Norepinephrine":
                    raise LookupError(f"fake pulse: substance {a.get_substance()!r} not recorded")
                conc = a.get_concentration().get_value(MassPerVolumeUnit.ug_Per_mL)
                self._state["ne_ug_min"] = conc * a.get_rate().get_value(
                    VolumePerTimeUnit.mL_Per_min)
            elif isinstance(a, SEConsumeNutrients):
                meal = a.get_nutrition().values()
                self._pending.append("meal" if meal.keys() == STANDARD_MEAL.keys() and all(
                    _close(meal[k], v) for k, v in STANDARD_MEAL.items()) else f"meal:{meal}")
            elif isinstance(a, SEUrinate):
                if not a.has_comment():
                    # The real engine logs 'AnyActionData is empty' and segfaults.
                    raise SystemError("fake pulse: SEUrinate without a comment kills the engine")
                self._pending.append("urinate")
            else:
                raise NotImplementedError(f"fake pulse: action {type(a).__name__} not supported")
        return True

    def advance_time_s(self, duration_s: float) -> bool:
        if not self._is_ready or self._state["failed"]:
            return False
        if duration_s != 3600:
            raise NotImplementedError("fake pulse: recordings are hourly; advance 3600 s only")
        CALLS["advance_hours"] += 1
        s = self._state
        fed = sorted(self._pending) == ["meal", "urinate"]
        if self._pending and not fed:
            raise LookupError(f"fake pulse: actions {self._pending} were never recorded together")
        self._pending = []
        fail_at = os.environ.get(IRREVERSIBLE_ENV)
        if fail_at and s["hour"] + 1 == int(fail_at):
            s["failed"] = True
            s["events"] = {"IrreversibleState": 0.0, "CardiacArrest": 1.0}
            return False
        s["history"].append([s["saline"], s["ne_ug_min"], fed])
        s["hour"] += 1
        self._row = self._lookup(s["patient_id"], s["history"])
        return True

    def _lookup(self, pid: str, history: list) -> dict:
        _, runs = _recordings()
        hour = len(history)
        for run_id in sorted(runs):
            rows = runs[run_id]
            if not run_id.startswith(pid + "-") or hour not in rows:
                continue
            if all(all(_close(a, b) for a, b in zip(_settings(rows[h])[:2], history[h - 1][:2],
                                                       strict=True))
                   and _settings(rows[h])[2] == history[h - 1][2] for h in range(1, hour + 1)):
                return rows[hour]
        raise LookupError(f"fake pulse: no recorded run of {pid} with hourly settings "
                          f"(saline mL/min, NE ug/min, fed) = {history}")

    def pull_data(self) -> list[float]:
        row = self._row
        try:
            return [float(row["sim_time_s"])] + [float(row[c]) for c in self._requests]
        except KeyError as exc:
            raise LookupError(f"fake pulse: request {exc} was not recorded") from None

    def pull_active_events(self) -> dict[str, float] | None:
        if self._state and self._state.get("events"):
            return dict(self._state["events"])
        text = self._row.get("active_events", "") if self._row else ""
        if not text:
            return None
        return {k: float(v.rstrip("s")) for k, v in (x.split("=") for x in text.split(";"))}
