"""Pulse <-> study units, Pulse's accepted patient baselines (the clamp table) and
the physiological limits that mark a collapsed engine state. All three are data
files in ``twinfalsify/pulse/data/``; this module only loads and applies them.

Conversion (one row of ``conversions.csv`` per study feature)::

    study_value = scale * pulse_value * (M / 10 if M else 1) + offset

where M is the molar mass in g/mol (mmol/L -> mg/dL: 1 mmol/L = M mg/L = M/10 mg/dL)
and ``scale`` is a dimensionless model surrogate factor (only calcium uses one:
ionised -> total, see the table's ``decision`` column). Rows with source ``x0``
echo the given X_0 value (age, sex are demographics the engine does not change).

Clamp (``init_limits.csv``; Pulse 4.2's patient-initialisation checks, whose
[ERROR] messages the recorded runs quote): age, HR, SysBP, DiaBP, RR are clipped
into their closed ranges; then DiaBP <= 0.75 SysBP. Height is not in the data:
it starts at Pulse's own sex-specific standard height (177 cm male, 163 cm female,
the value Pulse itself uses when no height is set) and is moved, within
Pulse's 4.5-7 ft, just far enough to bring BMI = weight / height^2 into [16, 30];
only if that is impossible is the weight changed. Every change is recorded as
{feature: [given, used]} (height as "height_cm": [standard, used]).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import pandas as pd

from twinfalsify.schema import FEATURES, INIT_FEATURES, ContractError

STANDARD_HEIGHT_CM = {0: 177.0, 1: 163.0}  # Pulse 4.2 defaults (CDC 50th percentile at 20 y)
# Relative margin kept inside the BMI limits so that Pulse's own float BMI never
# lands a rounding error beyond the limit (Pulse errors on BMI > 30 and BMI < 16).
_BMI_MARGIN = 1e-6

CONVERSION_COLUMNS = (
    "feature", "study_unit", "source", "compartment", "substance", "property",
    "pulse_unit", "recorded_column", "scale", "molar_mass_g_per_mol", "offset", "meaning",
    "decision",
)
SOURCES = ("x0", "physiology", "patient", "liquid_compartment_substance")


def data_path(name: str) -> Path:
    """Path of a packaged table in twinfalsify/pulse/data/."""
    return Path(str(resources.files("twinfalsify.pulse") / "data" / name))


def _read_csv(path: Path, required: Iterable[str]) -> list[dict[str, str]]:
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            header = reader.fieldnames or []
    except FileNotFoundError:
        raise ContractError(f"{path}: file not found") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise ContractError(f"{path}: missing column(s) {', '.join(missing)}")
    return rows


def _num(path: Path, row: int, col: str, text: str, default: float | None = None) -> float:
    if text.strip() == "" and default is not None:
        return default
    try:
        value = float(text)
    except ValueError:
        raise ContractError(f"{path}: row {row}, column {col}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ContractError(f"{path}: row {row}, column {col}: {text!r} is not finite")
    return value


# ----------------------------------------------------------------------------- conversions
@dataclass(frozen=True)
class Conversion:
    """One study feature: where it comes from in Pulse and how it is converted."""

    feature: str
    study_unit: str
    source: str  # x0 | physiology | patient | liquid_compartment_substance
    compartment: str
    substance: str
    property: str
    pulse_unit: str  # '' = dimensionless
    recorded_column: str  # column of the recorded runs (runs.csv) holding this request
    scale: float
    molar_mass: float | None
    offset: float
    meaning: str
    decision: str

    @property
    def factor(self) -> float:
        """Multiplier from Pulse's unit to the study's: scale * (M/10 if molar)."""
        return self.scale * (self.molar_mass / 10.0 if self.molar_mass else 1.0)

    def to_study(self, pulse_value: float) -> float:
        return self.factor * float(pulse_value) + self.offset


def load_conversions(path: str | Path | None = None) -> dict[str, Conversion]:
    """Read the conversions table; one row per schema.FEATURES entry, in that order."""
    p = Path(path) if path else data_path("conversions.csv")
    rows = _read_csv(p, CONVERSION_COLUMNS)
    out: dict[str, Conversion] = {}
    for i, r in enumerate(rows, start=2):
        name = r["feature"]
        if name not in FEATURES:
            raise ContractError(f"{p}: row {i}, column feature: {name!r} is not a study feature")
        if name in out:
            raise ContractError(f"{p}: row {i}, column feature: {name!r} appears twice")
        if r["source"] not in SOURCES:
            raise ContractError(
                f"{p}: row {i}, column source: {r['source']!r} not one of {', '.join(SOURCES)}"
            )
        if r["source"] != "x0" and not (r["property"] and r["recorded_column"]):
            raise ContractError(f"{p}: row {i}: a Pulse feature needs property and recorded_column")
        molar = _num(p, i, "molar_mass_g_per_mol", r["molar_mass_g_per_mol"], default=0.0)
        out[name] = Conversion(
            feature=name, study_unit=r["study_unit"], source=r["source"],
            compartment=r["compartment"], substance=r["substance"], property=r["property"],
            pulse_unit=r["pulse_unit"], recorded_column=r["recorded_column"],
            scale=_num(p, i, "scale", r["scale"]), molar_mass=molar or None,
            offset=_num(p, i, "offset", r["offset"], default=0.0),
            meaning=r["meaning"], decision=r["decision"],
        )
    missing = [f for f in FEATURES if f not in out]
    if missing:
        raise ContractError(f"{p}: no row for feature(s) {', '.join(missing)}")
    return {f: out[f] for f in FEATURES}


def pulse_conversions(conversions: Mapping[str, Conversion]) -> list[Conversion]:
    """The rows the engine must be asked for, in a fixed (table) order = request order."""
    return [c for c in conversions.values() if c.source != "x0"]


def to_study_features(
    pulse_values: Mapping[str, float], x0: Mapping[str, float],
    conversions: Mapping[str, Conversion],
) -> dict[str, float]:
    """Pulse values keyed by recorded_column (+ X_0 for echoed rows) -> study features."""
    out: dict[str, float] = {}
    for name, c in conversions.items():
        if c.source == "x0":
            out[name] = float(x0[name])
        else:
            out[name] = c.to_study(pulse_values[c.recorded_column])
    return out


# ----------------------------------------------------------------------------- init limits
@dataclass(frozen=True)
class InitLimits:
    """Pulse 4.2's accepted patient baselines (closed intervals)."""

    ranges: Mapping[str, tuple[float, float]]  # study feature -> (lo, hi)
    dia_sys_ratio_max: float
    bmi: tuple[float, float]
    height_cm: tuple[float, float]


def load_init_limits(path: str | Path | None = None) -> InitLimits:
    p = Path(path) if path else data_path("init_limits.csv")
    rows = _read_csv(p, ("quantity", "study_feature", "unit", "lo", "hi"))
    by_q: dict[str, tuple[str, float, float]] = {}
    for i, r in enumerate(rows, start=2):
        lo, hi = _num(p, i, "lo", r["lo"]), _num(p, i, "hi", r["hi"])
        if lo > hi:
            raise ContractError(f"{p}: row {i} ({r['quantity']}): lo {lo} > hi {hi}")
        by_q[r["quantity"]] = (r["study_feature"], lo, hi)
    need = ("age", "heart_rate_baseline", "systolic_pressure_baseline",
            "diastolic_pressure_baseline", "respiration_rate_baseline",
            "diastolic_to_systolic_ratio", "body_mass_index", "height")
    missing = [q for q in need if q not in by_q]
    if missing:
        raise ContractError(f"{p}: column quantity: missing row(s) {', '.join(missing)}")
    ranges = {f: (lo, hi) for f, lo, hi in by_q.values() if f}
    for f in ("age", "HR", "SysBP", "DiaBP", "RR"):
        if f not in ranges:
            raise ContractError(f"{p}: column study_feature: no range for {f}")
    return InitLimits(
        ranges=ranges, dia_sys_ratio_max=by_q["diastolic_to_systolic_ratio"][2],
        bmi=by_q["body_mass_index"][1:], height_cm=by_q["height"][1:],
    )


@dataclass(frozen=True)
class PatientInit:
    """The values a Pulse patient is configured with (Pulse units: y, kg, cm, /min, mmHg)."""

    sex: int  # 1 = female
    age: float
    weight: float
    height_cm: float
    HR: float
    SysBP: float
    DiaBP: float
    RR: float

    def key(self, engine_version: str = "") -> str:
        """Stable hash of the init values (cache key of the stabilised state)."""
        payload = {k: (round(v, 9) if isinstance(v, float) else v) for k, v in asdict(self).items()}
        payload["engine"] = engine_version
        text = json.dumps(payload, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:24]


def clamp_x0(
    x0: Mapping[str, float], limits: InitLimits | None = None, height_cm: float | None = None,
) -> tuple[PatientInit, dict[str, list[float]]]:
    """X_0 (study features) -> (Pulse-acceptable patient, {feature: [given, used]}).

    Rule (see module docstring): clip each baseline into Pulse's closed range, then
    cap DiaBP at ratio_max * SysBP; start height at Pulse's sex standard (or
    ``height_cm`` if the caller knows it) inside [4.5, 7] ft and move it to the
    nearest height giving BMI in [16, 30] (BMI = kg / m^2); change weight only if
    no height in range can. Assumes the limits are consistent (0.75 * 90 >= 60).
    """
    lim = limits or load_init_limits()
    missing = [f for f in INIT_FEATURES if f not in x0]
    if missing:
        raise ContractError(f"x0: missing init feature(s) {', '.join(missing)}")
    vals: dict[str, float] = {}
    for f in INIT_FEATURES:
        try:
            v = float(x0[f])
        except (TypeError, ValueError):
            raise ContractError(f"x0: feature {f} = {x0[f]!r} is not a number") from None
        if not math.isfinite(v):
            raise ContractError(f"x0: feature {f} = {v} is not finite")
        vals[f] = v
    if vals["sex"] not in (0.0, 1.0):
        raise ContractError(f"x0: feature sex = {vals['sex']} must be 0 (male) or 1 (female)")
    if vals["weight"] <= 0:
        raise ContractError(f"x0: feature weight = {vals['weight']} kg must be > 0")
    sex = int(vals["sex"])
    clamped: dict[str, list[float]] = {}
    used = dict(vals)
    for f, (lo, hi) in lim.ranges.items():
        if f in used:
            used[f] = min(max(used[f], lo), hi)
    used["DiaBP"] = min(used["DiaBP"], lim.dia_sys_ratio_max * used["SysBP"])

    h_lo, h_hi = lim.height_cm
    start = STANDARD_HEIGHT_CM[sex] if height_cm is None else float(height_cm)
    height = min(max(start, h_lo), h_hi)
    bmi_lo = lim.bmi[0] * (1 + _BMI_MARGIN)
    bmi_hi = lim.bmi[1] * (1 - _BMI_MARGIN)
    w = used["weight"]
    bmi = w / (height / 100) ** 2
    if bmi > bmi_hi:  # too heavy for this height: taller, up to 7 ft, then lighter
        height = min(100 * math.sqrt(w / bmi_hi), h_hi)
        if height == h_hi:  # only then can no height absorb the weight
            w = min(w, bmi_hi * (height / 100) ** 2)
    elif bmi < bmi_lo:  # too light: shorter, down to 4.5 ft, then heavier
        height = max(100 * math.sqrt(w / bmi_lo), h_lo)
        if height == h_lo:
            w = max(w, bmi_lo * (height / 100) ** 2)
    used["weight"] = w
    for f in INIT_FEATURES:
        if used[f] != vals[f]:
            clamped[f] = [vals[f], used[f]]
    if height != start:
        clamped["height_cm"] = [start, height]
    patient = PatientInit(
        sex=sex, age=used["age"], weight=used["weight"], height_cm=height, HR=used["HR"],
        SysBP=used["SysBP"], DiaBP=used["DiaBP"], RR=used["RR"],
    )
    return patient, clamped


def init_violations(p: PatientInit, limits: InitLimits | None = None) -> list[str]:
    """Which of Pulse's initialisation checks a patient fails (empty = accepted)."""
    lim = limits or load_init_limits()
    out = []
    for f, (lo, hi) in lim.ranges.items():
        v = getattr(p, f)
        if not lo <= v <= hi:
            out.append(f"{f} {v:g} outside [{lo:g}, {hi:g}]")
    if p.DiaBP > lim.dia_sys_ratio_max * p.SysBP:
        out.append(f"DiaBP/SysBP {p.DiaBP / p.SysBP:.4f} > {lim.dia_sys_ratio_max:g}")
    bmi = p.weight / (p.height_cm / 100) ** 2
    if not lim.bmi[0] <= bmi <= lim.bmi[1]:
        out.append(f"BMI {bmi:.4f} outside [{lim.bmi[0]:g}, {lim.bmi[1]:g}]")
    if not lim.height_cm[0] <= p.height_cm <= lim.height_cm[1]:
        lo, hi = lim.height_cm
        out.append(f"height {p.height_cm:g} cm outside [{lo:g}, {hi:g}]")
    return out


def clamp_shares(x0: pd.DataFrame, limits: InitLimits | None = None) -> pd.DataFrame:
    """Share of X_0 rows whose value the Pulse clamp changes, per feature.

    Columns: feature, n, n_clamped, share, mean_abs_change (over clamped rows),
    plus a row "any" (rows with at least one clamped init feature; height_cm
    counted separately because it is not a data feature).
    """
    lim = limits or load_init_limits()
    counts: dict[str, list[float]] = {f: [] for f in (*INIT_FEATURES, "height_cm")}
    n_any = 0
    records = x0.to_dict("records")
    for rec in records:
        _, cl = clamp_x0(rec, lim)
        if any(f in cl for f in INIT_FEATURES):
            n_any += 1
        for f, (given, used) in cl.items():
            counts[f].append(abs(used - given))
    n = len(records)
    rows = [
        {"feature": f, "n": n, "n_clamped": len(d), "share": len(d) / n if n else float("nan"),
         "mean_abs_change": sum(d) / len(d) if d else 0.0}
        for f, d in counts.items()
    ]
    rows.append({"feature": "any", "n": n, "n_clamped": n_any,
                 "share": n_any / n if n else float("nan"), "mean_abs_change": float("nan")})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------- collapse
@dataclass(frozen=True)
class PhysLimit:
    feature: str
    unit: str
    lo: float
    hi: float
    reason: str


def load_physiological_limits(path: str | Path | None = None) -> dict[str, PhysLimit]:
    p = Path(path) if path else data_path("physiological_limits.csv")
    rows = _read_csv(p, ("feature", "unit", "lo", "hi", "reason"))
    out = {}
    for i, r in enumerate(rows, start=2):
        if r["feature"] not in FEATURES:
            raise ContractError(f"{p}: row {i}, column feature: {r['feature']!r} unknown")
        lo, hi = _num(p, i, "lo", r["lo"]), _num(p, i, "hi", r["hi"])
        if lo >= hi:
            raise ContractError(f"{p}: row {i} ({r['feature']}): lo {lo} >= hi {hi}")
        out[r["feature"]] = PhysLimit(r["feature"], r["unit"], lo, hi, r["reason"])
    return out


def physiological_violation(
    features: Mapping[str, float], limits: Mapping[str, PhysLimit],
) -> str | None:
    """Message naming the first feature (schema order) outside its limits, else None.

    A value that is NaN counts as a violation: an engine that returns NaN has failed.
    """
    for f in FEATURES:
        lim = limits.get(f)
        if lim is None or f not in features:
            continue
        v = features[f]
        if not (lim.lo <= v <= lim.hi):  # also catches NaN
            return (f"{f} = {v:.6g} {lim.unit} outside the physiological limits "
                    f"[{lim.lo:g}, {lim.hi:g}] ({lim.reason})")
    return None
