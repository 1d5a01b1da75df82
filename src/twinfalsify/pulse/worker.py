"""The Pulse Physiology Engine twin: a protocol-v1 worker driving Pulse's Python API.

    python -m twinfalsify.pulse.worker [--state-cache DIR] [--engine-module NAME]
                                             [--data-root DIR]

Per ``simulate`` request (see runs/protocol.py):

1. X_0 -> Pulse patient with ``pulse.units.clamp_x0`` (Pulse 4.2 refuses baselines
   outside init_limits.csv; every change is returned in ``clamped``).
2. Stabilise (``initialize_engine``, 11-14 s on real Pulse) once per patient and
   save the state to ``--state-cache`` (file name = hash of the init values and the
   engine version); every run then LOADS that state (as the recorded runs did), so
   results do not depend on whether the cache was warm.
3. Hour h = 1..t: send actions only when a setting changes (rate 0 stops an
   infusion): IV fluid as compound infusion ``Saline`` at mL/h / 60 mL/min (bag
   5000 mL); vasopressor as substance infusion ``Norepinephrine`` at 16 ug/mL and
   dose (ug/kg/min) x weight (kg, the configured patient weight) / 16 mL/min. At
   the start of every 3rd hour (t = 3) a Standard meal with 0.5 L water and a
   urination (the paper's Algorithm 2). ``advance_time_s(3600)``, then read the
   requests of conversions.csv and convert them to study units.
4. Failure: ``advance_time_s`` returning False or the active event
   ``IrreversibleState`` -> "irreversible"; a state outside
   physiological_limits.csv -> "irreversible" too, with a message naming the
   feature and value, because real Pulse 4.2 reported success for a collapsed
   state (recorded P3-S4 hour 4: HR 0.001/min, Na 21 mmol/L, pH 9.10).
   ``initialize_engine`` returning False -> "init_failed" with the engine log's
   [ERROR] lines. Hours completed before a failure are returned.

Depth truncation (capability ``truncate``, docs/reference/twin-protocol.md): a request carrying
``continue_while`` box paths stops after the first completed hour on which no path holds any
more (``runs.truncation.hours_needed``) and answers status ok with the hours it has and
``"truncated": true``; a prefix already simulated is returned whole (it costs nothing).

Prefix reuse: within one process, the engine state after every dose prefix of
the current X_0 is saved (binary save/load ~10 ms on real Pulse), so runs
sharing a prefix simulate it once; the runner sends runs with the same X_0
consecutively. Simulated, requested and truncated hours are reported on stderr at shutdown.
Pulse is deterministic: ``seed`` is accepted and ignored.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from twinfalsify.pulse.units import (
    Conversion,
    InitLimits,
    PatientInit,
    PhysLimit,
    clamp_x0,
    load_conversions,
    load_init_limits,
    load_physiological_limits,
    physiological_violation,
    pulse_conversions,
    to_study_features,
)
from twinfalsify.runs import protocol
from twinfalsify.runs.truncation import Box, hours_needed, parse_paths
from twinfalsify.schema import FEATURE_TABLE, T_MAX, ContractError

# Folders of a Pulse data root (the install's bin/). Real Pulse 4.2 started with a data root
# lacking them logs "Unable to find substance directory" and then dies with SIGSEGV inside
# initialize_engine, so the worker checks them before it starts any engine.
DATA_ROOT_DIRS = ("substances", "config", "ecg", "environments", "nutrition")
DATA_ROOT_ENV = "PULSE_DATA_ROOT"
HOUR_S = 3600.0
SALINE_BAG_ML = 5000.0
NE_CONCENTRATION_UG_PER_ML = 16.0
NUTRITION_EVERY_H = 3
# The engine's Standard meal (Pulse data nutrition/Standard.json) as sent in the recording.
STANDARD_MEAL = {"carbohydrate": (130, "g"), "carbohydrate_digestion_rate": (1.083, "g/min"),
                 "fat": (27, "g"), "fat_digestion_rate": (0.055, "g/min"),
                 "protein": (20, "g"), "protein_digestion_rate": (0.071, "g/min"),
                 "calcium": (500, "mg"), "sodium": (1.0, "g"), "water": (0.5, "L")}


def saline_ml_per_min(iv_ml_per_h: float) -> float:
    """IV fluid mL/h -> Pulse infusion rate mL/min (divide by 60)."""
    return iv_ml_per_h / 60.0


def norepinephrine_ml_per_min(dose_ug_per_kg_min: float, weight_kg: float) -> float:
    """ug/kg/min at 16 ug/mL -> pump rate mL/min = dose * weight / 16."""
    return dose_ug_per_kg_min * weight_kg / NE_CONCENTRATION_UG_PER_ML


def is_feeding_hour(h: int) -> bool:
    """Hour h (1-based) starts at t = h - 1; feed at t = 3, 6, ... (never at t = 0)."""
    t = h - 1
    return t > 0 and t % NUTRITION_EVERY_H == 0


@dataclass
class _Node:
    """A simulated dose prefix: its saved state and the study features of hours 1..s."""

    state: Path | None
    hours: list[dict[str, float]]
    failure: tuple[str, str] | None = None  # (status, message) of hour s + 1 when it failed


@dataclass
class _Stats:
    requested_hours: int = 0
    simulated_hours: int = 0
    stabilisations: int = 0
    stable_cache_hits: int = 0
    runs: int = 0
    truncated_runs: int = 0
    truncated_hours: int = 0  # requested hours not simulated because no path needed them
    by_status: dict[str, int] = field(default_factory=dict)


class PulseWorker:
    """Answers hello/simulate for the protocol; owns one Pulse engine at a time."""

    def __init__(self, state_cache: str | Path | None = None, engine_module: str = "pulse",
                 data_root: str = "./", conversions: dict[str, Conversion] | None = None,
                 init_limits: InitLimits | None = None,
                 phys_limits: dict[str, PhysLimit] | None = None):
        self._tmp = Path(tempfile.mkdtemp(prefix="pulse-worker-"))
        self.state_cache = Path(state_cache) if state_cache else self._tmp / "stable"
        self.state_cache.mkdir(parents=True, exist_ok=True)
        self.engine_module = engine_module
        self.data_root = data_root
        self.conversions = conversions or load_conversions()
        self.init_limits = init_limits or load_init_limits()
        self.phys_limits = phys_limits if phys_limits is not None else load_physiological_limits()
        self.stats = _Stats()
        self._api: SimpleNamespace | None = None
        self._key: str | None = None  # init key whose prefixes are cached
        self._nodes: dict[tuple, _Node] = {}
        self._init_failures: dict[str, str] = {}
        self._live: tuple[Any, tuple] | None = None  # (engine, prefix it is at)
        self._n_files = 0
        self._ready = False

    # ------------------------------------------------------------------ Pulse API
    def api(self) -> SimpleNamespace:
        """Import Pulse lazily: the module must import where Pulse is absent."""
        if self._api is None:
            m = self.engine_module
            eng = importlib.import_module(f"{m}.engine.PulseEngine")
            cdm = importlib.import_module(f"{m}.cdm.engine")
            pat = importlib.import_module(f"{m}.cdm.patient")
            act = importlib.import_module(f"{m}.cdm.patient_actions")
            sca = importlib.import_module(f"{m}.cdm.scalars")
            self._api = SimpleNamespace(eng=eng, cdm=cdm, pat=pat, act=act, U=sca)
        return self._api

    def version(self) -> str:
        return str(self.api().eng.version())

    def check_ready(self) -> None:
        """Raise with one line naming the fix when no engine can start here: Pulse's Python
        API does not import, or the data root lacks Pulse's data folders."""
        if self._ready:
            return
        missing_root = data_root_problem(self.data_root)
        if missing_root:
            raise ContractError(missing_root)
        try:
            self.api()
        except ImportError as exc:
            raise ContractError(
                f"cannot import Pulse's Python API (module {self.engine_module!r}): {exc}; put "
                "the Pulse install's bin/ and python/ folders on PYTHONPATH (envs/pulse/build.sh "
                "prints the line)"
            ) from None
        self._ready = True

    def hello(self) -> dict[str, Any]:
        self.check_ready()
        return {"name": "pulse", "version": self.version(),
                "features": [{"name": f.name, "unit": f.unit} for f in FEATURE_TABLE],
                "capabilities": {"save_restore": True, "max_hours": T_MAX, "truncate": True}}

    def _unit(self, text: str):
        U = self.api().U
        known = {"mmHg": U.PressureUnit.mmHg, "1/min": U.FrequencyUnit.Per_min,
                 "degC": U.TemperatureUnit.C, "kg": U.MassUnit.kg, "mL": U.VolumeUnit.mL,
                 "mg/dL": U.MassPerVolumeUnit.mg_Per_dL}
        # Pulse's python cdm has no AmountPerVolumeUnit class: mmol/L is a plain SEScalarUnit.
        return known.get(text) or U.SEScalarUnit(text)

    def _requests(self):
        """One data request per Pulse-sourced row of conversions.csv, in table order."""
        a = self.api()
        R = a.cdm.SEDataRequest
        out = []
        for c in pulse_conversions(self.conversions):
            unit = self._unit(c.pulse_unit) if c.pulse_unit else None
            if c.source == "physiology":
                out.append(R.create_physiology_request(c.property, unit=unit) if unit
                           else R.create_physiology_request(c.property))
            elif c.source == "patient":
                out.append(R.create_patient_request(c.property, unit))
            else:
                out.append(R.create_liquid_compartment_substance_request(
                    c.compartment, c.substance, c.property, unit))
        return a.cdm.SEDataRequestManager(out)

    def _new_engine(self, log_name: str):
        a = self.api()
        e = a.eng.PulseEngine(data_root_dir=self.data_root)
        e.set_log_filename(str(self.state_cache / "logs" / log_name))
        e.log_to_console(False)  # stdout belongs to the protocol
        return e

    def _patient_config(self, p: PatientInit, name: str):
        a = self.api()
        U = a.U
        pc = a.pat.SEPatientConfiguration()
        pt = pc.get_patient()
        pt.set_name(name)
        pt.set_sex(a.pat.eSex.Female if p.sex == 1 else a.pat.eSex.Male)
        pt.get_age().set_value(p.age, U.TimeUnit.yr)
        pt.get_weight().set_value(p.weight, U.MassUnit.kg)
        pt.get_height().set_value(p.height_cm, U.LengthUnit.cm)
        pt.get_heart_rate_baseline().set_value(p.HR, U.FrequencyUnit.Per_min)
        pt.get_systolic_arterial_pressure_baseline().set_value(p.SysBP, U.PressureUnit.mmHg)
        pt.get_diastolic_arterial_pressure_baseline().set_value(p.DiaBP, U.PressureUnit.mmHg)
        pt.get_respiration_rate_baseline().set_value(p.RR, U.FrequencyUnit.Per_min)
        pc.set_data_root_dir(self.data_root)
        # No Sepsis condition: Pulse 4.2 accepts it but it changes nothing (recorded).
        return pc

    def _actions(self, h: int, dose: tuple[float, float], prev: tuple[float, float],
                 weight: float) -> list:
        a = self.api()
        U = a.U
        out = []
        if is_feeding_hour(h):
            c = a.act.SEConsumeNutrients()
            n = c.get_nutrition()
            units = {"g": U.MassUnit.g, "mg": U.MassUnit.mg, "L": U.VolumeUnit.L,
                     "g/min": U.MassPerTimeUnit.g_Per_min}
            for name, (value, unit) in STANDARD_MEAL.items():
                getattr(n, f"get_{name}")().set_value(value, units[unit])
            u = a.act.SEUrinate()
            # An SEUrinate without a comment serialises to an empty action and the
            # real Pulse 4.2 engine segfaults ('AnyActionData is empty'); any comment avoids it.
            u.set_comment("scheduled urination (every 3 h)")
            out += [c, u]
        if dose[0] != prev[0]:
            s = a.act.SESubstanceCompoundInfusion()
            s.set_compound("Saline")
            s.get_rate().set_value(saline_ml_per_min(dose[0]), U.VolumePerTimeUnit.mL_Per_min)
            s.get_bag_volume().set_value(SALINE_BAG_ML, U.VolumeUnit.mL)
            out.append(s)
        if dose[1] != prev[1]:
            ne = a.act.SESubstanceInfusion()
            ne.set_substance("Norepinephrine")
            ne.get_concentration().set_value(NE_CONCENTRATION_UG_PER_ML,
                                             U.MassPerVolumeUnit.ug_Per_mL)
            ne.get_rate().set_value(norepinephrine_ml_per_min(dose[1], weight),
                                    U.VolumePerTimeUnit.mL_Per_min)
            out.append(ne)
        return out

    # ------------------------------------------------------------------ states
    def _state_file(self, stem: str) -> Path:
        self._n_files += 1
        d = self._tmp / "prefix"
        d.mkdir(exist_ok=True)
        return d / f"{stem}-{self._n_files}.pbb"

    def _stable(self, p: PatientInit, key: str) -> tuple[Path | None, str]:
        """Path of the stabilised state (creating it if needed), or (None, init error)."""
        path = self.state_cache / f"pulse-stable-{key}.pbb"
        if path.exists():
            self.stats.stable_cache_hits += 1
            return path, ""
        if key in self._init_failures:
            return None, self._init_failures[key]
        (self.state_cache / "logs").mkdir(exist_ok=True)
        log = self.state_cache / "logs" / f"init-{key}.log"
        log.unlink(missing_ok=True)
        e = self._new_engine(log.name)
        self.stats.stabilisations += 1
        if not e.initialize_engine(self._patient_config(p, key), self._requests()):
            try:
                lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines()
                         if ln.startswith(("[ERROR]", "[FATAL]"))]
            except OSError:
                lines = []
            msg = ("Pulse refused the patient (initialize_engine returned False): "
                   + (" | ".join(lines) if lines else "no [ERROR] line in the engine log"))
            self._init_failures[key] = msg
            return None, msg
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        if not e.serialize_to_file(str(tmp)):
            raise RuntimeError(f"Pulse could not save the stabilised state to {tmp}")
        os.replace(tmp, path)  # atomic: parallel workers may share the cache
        return path, ""

    def _load(self, path: Path):
        (self.state_cache / "logs").mkdir(exist_ok=True)
        e = self._new_engine(f"run-{self._key}.log")
        if not e.serialize_from_file(str(path), self._requests()):
            raise RuntimeError(f"Pulse could not load the state {path}")
        return e

    def _reset_prefixes(self, key: str) -> None:
        for node in self._nodes.values():
            if node.state and node.state.parent == self._tmp / "prefix":
                node.state.unlink(missing_ok=True)
        self._nodes = {}
        self._live = None
        self._key = key

    # ------------------------------------------------------------------ simulate
    def simulate(self, request: dict[str, Any]) -> dict[str, Any]:
        """One protocol ``simulate`` request -> the result fields (see module docstring)."""
        x0, doses, hours, paths = _parse_request(request)
        self.check_ready()  # never start an engine that would crash on a bad data root
        height = x0.get("height_cm")  # optional extension: a known height (recorded patients)
        patient, clamped = clamp_x0(x0, self.init_limits, height_cm=height)
        key = patient.key(f"{self.engine_module}:{self.version()}")
        if key != self._key:
            self._reset_prefixes(key)
        self.stats.requested_hours += hours
        self.stats.runs += 1
        result = self._run(patient, x0, doses[:hours], key, paths)
        result["clamped"] = clamped
        if result.get("truncated"):
            self.stats.truncated_runs += 1
            self.stats.truncated_hours += hours - len(result["hours"])
        self.stats.by_status[result["status"]] = self.stats.by_status.get(result["status"], 0) + 1
        return result

    def _run(self, p: PatientInit, x0: dict, doses: list[tuple[float, float]],
             key: str, paths: list[list[Box]] | None = None) -> dict[str, Any]:
        # Longest simulated prefix of this dose sequence.
        s = len(doses)
        while s > 0 and tuple(doses[:s]) not in self._nodes:
            s -= 1
        node = self._nodes.get(tuple(doses[:s]))
        if node is None:
            stable, msg = self._stable(p, key)
            if stable is None:
                return {"status": "init_failed", "message": msg, "hours": []}
            node = _Node(stable, [])
            self._nodes[()] = node
        if node.failure:
            return {"status": node.failure[0], "message": node.failure[1],
                    "hours": list(node.hours)}
        hours_out = list(node.hours)
        if s == len(doses):
            return {"status": "ok", "message": "", "hours": hours_out}
        if not _still_needed(paths, hours_out, len(doses)):
            return {"status": "ok", "message": "", "hours": hours_out, "truncated": True}
        if self._live and self._live[1] == tuple(doses[:s]):
            engine = self._live[0]
        else:
            engine = self._load(node.state)
        self._live = None
        prev = doses[s - 1] if s else (0.0, 0.0)
        for h in range(s + 1, len(doses) + 1):
            dose = doses[h - 1]
            try:
                engine.process_actions(self._actions(h, dose, prev, p.weight))
                advanced = engine.advance_time_s(HOUR_S)
                events = _event_names(engine.pull_active_events())
            except Exception as exc:  # noqa: BLE001 - engine failure -> "error" with hours so far
                return {"status": "error", "hours": hours_out,
                        "message": f"Pulse failed in hour {h}: {type(exc).__name__}: {exc}"}
            self.stats.simulated_hours += 1
            prefix = tuple(doses[:h])
            failure = None
            if not advanced or "IrreversibleState" in events:
                failure = ("irreversible", f"Pulse reached an irreversible state in hour {h} "
                           f"(advance_time_s returned {advanced}; active events: "
                           f"{', '.join(sorted(events)) or 'none'})")
            else:
                values = engine.pull_data()
                feats = self._features(values, x0)
                bad = physiological_violation(feats, self.phys_limits)
                if bad:
                    failure = ("irreversible", f"collapsed state at the end of hour {h} although "
                               f"Pulse reported success: {bad}")
            if failure:
                self._nodes[prefix] = _Node(None, list(hours_out), failure)
                return {"status": failure[0], "message": failure[1], "hours": hours_out}
            hours_out.append(feats)
            state = self._state_file(key)
            if not engine.serialize_to_file(str(state)):
                raise RuntimeError(f"Pulse could not save the state after hour {h} to {state}")
            self._nodes[prefix] = _Node(state, list(hours_out))
            prev = dose
            if h < len(doses) and not _still_needed(paths, hours_out, len(doses)):
                self._live = (engine, prefix)
                return {"status": "ok", "message": "", "hours": hours_out, "truncated": True}
        self._live = (engine, tuple(doses))
        return {"status": "ok", "message": "", "hours": hours_out}

    def _features(self, values: Sequence[float], x0: dict) -> dict[str, float]:
        rows = pulse_conversions(self.conversions)
        if len(values) != len(rows) + 1:
            raise RuntimeError(f"pull_data() returned {len(values)} values for {len(rows)} "
                               "requests + sim time (a pybind11 < 2.12 build with numpy 2?)")
        pulse = {c.recorded_column: float(v) for c, v in zip(rows, values[1:], strict=True)}
        return to_study_features(pulse, x0, self.conversions)

    def report(self) -> str:
        st = self.stats
        saved = st.requested_hours - st.simulated_hours - st.truncated_hours
        return (f"pulse_worker: {st.runs} runs {st.by_status}; simulated {st.simulated_hours} "
                f"engine-hours for {st.requested_hours} requested hours ({saved} saved by prefix "
                f"reuse, {st.truncated_hours} by depth truncation in {st.truncated_runs} runs); "
                f"{st.stabilisations} stabilisations, {st.stable_cache_hits} "
                "stabilised-state cache hits")

    def close(self) -> None:
        shutil.rmtree(self._tmp, ignore_errors=True)


def data_root_problem(data_root: str | Path) -> str | None:
    """None when ``data_root`` holds Pulse's data folders, else one line naming the fix."""
    root = Path(data_root)
    missing = [d for d in DATA_ROOT_DIRS if not (root / d).is_dir()]
    if not missing:
        return None
    return (f"Pulse data root {str(root.resolve())!r} lacks {', '.join(d + '/' for d in missing)}"
            f": pass --data-root or set {DATA_ROOT_ENV} to the Pulse install's bin/ folder "
            "(envs/pulse/build.sh prints it)")


def _event_names(events: Any) -> set[str]:
    """Active events -> names (real Pulse keys are eEvent enums, the fake's strings)."""
    if not events:
        return set()
    return {getattr(k, "name", str(k)).split(".")[-1] for k in events}


def _still_needed(paths: list[list[Box]] | None, hours_out: list[dict[str, float]],
                  total: int) -> bool:
    """Whether hour len(hours_out) + 1 of a run of ``total`` hours is still needed by some
    ``continue_while`` path (always, without paths)."""
    return paths is None or hours_needed(paths, hours_out, total) > len(hours_out)


def _parse_request(req: dict[str, Any]
                   ) -> tuple[dict, list[tuple[float, float]], int, list[list[Box]] | None]:
    x0 = req.get("x0")
    if not isinstance(x0, dict):
        raise ContractError("simulate request: key x0 must be an object {feature: value}")
    hours = req.get("hours")
    if not isinstance(hours, int) or not 1 <= hours <= T_MAX:
        raise ContractError(f"simulate request: hours = {hours!r} must be an int in 1..{T_MAX}")
    doses = req.get("doses")
    if not isinstance(doses, list) or len(doses) < hours:
        raise ContractError(f"simulate request: doses must list >= {hours} [iv, vaso] pairs")
    out = []
    for i, d in enumerate(doses[:hours]):
        if not (isinstance(d, list | tuple) and len(d) == 2):
            raise ContractError(f"simulate request: doses[{i}] = {d!r} is not [iv, vaso]")
        iv, vaso = float(d[0]), float(d[1])
        if not (math.isfinite(iv) and math.isfinite(vaso) and iv >= 0 and vaso >= 0):
            raise ContractError(f"simulate request: doses[{i}] = {d!r} must be finite and >= 0")
        out.append((iv, vaso))
    paths = req.get("continue_while")
    if paths is not None:
        try:
            paths = parse_paths(paths)
        except ValueError as exc:
            raise ContractError(f"simulate request: {exc}") from None
    return x0, out, hours, paths


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--state-cache", help="directory for stabilised states (kept across runs)")
    ap.add_argument("--engine-module", default="pulse",
                    help="Python package providing Pulse's API (default: pulse)")
    ap.add_argument("--data-root", default=os.environ.get(DATA_ROOT_ENV, "./"),
                    help=f"Pulse's data root: the install's bin/ folder, holding "
                         f"{', '.join(DATA_ROOT_DIRS)} (default: ${DATA_ROOT_ENV}, else ./)")
    args = ap.parse_args(argv)
    # Keep the protocol on the real stdout; anything the engine prints goes to stderr.
    proto_out = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    worker = PulseWorker(args.state_cache, args.engine_module, args.data_root)
    try:
        return protocol.serve_forever(worker.hello, worker.simulate, sys.stdin, proto_out)
    finally:
        print(worker.report(), file=sys.stderr)
        worker.close()


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(main, "twinfalsify.pulse.worker"))  # bad input: one line, exit 2
