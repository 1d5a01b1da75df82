"""Pulse conversions, clamp table and physiological limits vs recorded real Pulse 4.2 runs."""

from __future__ import annotations

import filecmp
import json
import math
import re
import sys

import numpy as np
import pandas as pd
import pytest
from helpers.paths import TESTS, shared_dir

from twinfalsify.pulse import units as pu
from twinfalsify.schema import FEATURES, INIT_FEATURES, ContractError

FIXTURE = TESTS / "fixtures" / "pulse-reference"
sys.path.insert(0, str(TESTS / "fakes"))
from pulse.cdm.patient import eSex  # noqa: E402
from pulse.engine.PulseEngine import patient_errors  # noqa: E402  (the fake, a test fixture)

RUNS = pd.read_csv(FIXTURE / "runs.csv")
PATIENTS = pd.read_csv(FIXTURE / "patients.csv")
COLLAPSED = (RUNS.run_id == "P3-S4") & (RUNS.hour == 4)
OK_ROWS = RUNS[~COLLAPSED]


def test_fixture_is_a_copy_of_the_shared_recording():
    src = (shared_dir() or TESTS.parent.parent / "shared") / "data" / "pulse-reference"
    if not src.exists():
        pytest.skip(f"shared recording not found at {src}")
    for name in ("patients.csv", "runs.csv", "README.md"):
        assert filecmp.cmp(src / name, FIXTURE / name, shallow=False), name
    # meta.json: the same facts; the wording of one free-text note (the third example
    # patient's) differs for readers of the fixture, its numbers do not
    shared = json.loads((src / "meta.json").read_text())
    ours = json.loads((FIXTURE / "meta.json").read_text())
    notes_s, notes_o = shared.pop("observations_unusual"), ours.pop("observations_unusual")
    assert shared == ours
    differ = [(a, b) for a, b in zip(notes_s, notes_o, strict=True) if a != b]
    assert len(differ) <= 1
    for a, b in differ:
        assert re.findall(r"[0-9.]+", a) == re.findall(r"[0-9.]+", b)


def test_conversion_table_covers_every_feature_with_recorded_columns():
    conv = pu.load_conversions()
    assert list(conv) == list(FEATURES)
    for c in pu.pulse_conversions(conv):
        assert c.recorded_column in RUNS.columns, c.feature
    assert {c.feature for c in conv.values() if c.source == "x0"} == {"age", "sex"}
    # Core, not skin, temperature; ionised calcium scaled to total.
    assert conv["Temp_C"].property == "CoreTemperature"
    assert conv["Calcium"].scale == 2 and conv["Calcium"].molar_mass == pytest.approx(40.078)


def test_factors_match_independent_arithmetic():
    conv = pu.load_conversions()
    # mg/dL = mmol/L * M / 10: glucose 180.156 g/mol, calcium 40.078 g/mol (x2 ionised->total)
    assert conv["Glucose"].factor == pytest.approx(18.0156)
    assert conv["Calcium"].factor == pytest.approx(8.0156)
    for f in ("Sodium", "Potassium", "Chloride", "HCO3", "HR", "SysBP", "paO2", "Arterial_pH"):
        assert conv[f].factor == 1 and conv[f].offset == 0


@pytest.mark.parametrize("substance,molar_mass,lo,hi", [
    # whole-blood mg/dL (BloodConcentration) vs Aorta molarity via the molar mass: the
    # two requests measure slightly different compartments, so agreement is to ~1 %,
    # except glucose (up to 7 %: glucose control dynamics) and potassium, whose
    # whole-blood value is systematically ~0.797 x the compartment molarity.
    ("Sodium", 22.98977, 1.0, 1.015),
    ("Chloride", 35.453, 1.0, 1.015),
    ("Calcium", 40.078, 1.0, 1.015),
    ("Bicarbonate", 61.0168, 1.0, 1.015),
    ("Glucose", 180.156, 0.99, 1.08),
    ("Potassium", 39.0983, 0.79, 0.80),
])
def test_mg_per_dl_and_mmol_per_l_columns_agree_via_molar_masses(substance, molar_mass, lo, hi):
    conv = {c.substance: c for c in pu.load_conversions().values() if c.substance}
    if conv[substance].molar_mass:  # the table's molar mass is the one checked here
        assert conv[substance].molar_mass == pytest.approx(molar_mass)
    ratio = (OK_ROWS[f"{substance}_BloodConcentration_mg_per_dL"] * 10 / molar_mass
             / OK_ROWS[f"{substance}_Aorta_Molarity_mmol_per_L"])
    assert ratio.between(lo, hi).all(), (ratio.min(), ratio.max())


def test_recorded_values_converted_are_in_the_schema_plausible_ranges():
    from twinfalsify.schema import FEATURE_BY_NAME

    conv = pu.load_conversions()
    for _, r in OK_ROWS.iterrows():
        x0 = {"age": 50, "sex": 0}
        feats = pu.to_study_features(r.to_dict(), x0, conv)
        for f, v in feats.items():
            spec = FEATURE_BY_NAME[f]
            assert spec.lo <= v <= spec.hi, (r.run_id, r.hour, f, v)


# ------------------------------------------------------------------ physiological limits
def test_physiological_limits_pass_every_intact_row_and_fail_the_collapsed_one():
    conv, lim = pu.load_conversions(), pu.load_physiological_limits()
    for _, r in RUNS.iterrows():
        feats = pu.to_study_features(r.to_dict(), {"age": 50, "sex": 0}, conv)
        msg = pu.physiological_violation(feats, lim)
        if r.run_id == "P3-S4" and r.hour == 4:
            assert msg is not None and msg.startswith("HR = 0.001 ")
        else:
            assert msg is None, (r.run_id, r.hour, msg)


def test_collapsed_row_violates_several_limits():
    conv, lim = pu.load_conversions(), pu.load_physiological_limits()
    r = RUNS[COLLAPSED].iloc[0].to_dict()
    feats = pu.to_study_features(r, {"age": 64, "sex": 0}, conv)
    bad = {f for f in lim if not lim[f].lo <= feats[f] <= lim[f].hi}
    assert {"HR", "RR", "Sodium", "Arterial_pH", "paCO2"} <= bad
    assert pu.physiological_violation({**feats, "HR": math.nan}, lim).startswith("HR = nan")


# ------------------------------------------------------------------ clamp table
def _x0(p: pd.Series) -> dict:
    return {"age": p.age_yr, "sex": 1.0 if p.sex == "Female" else 0.0, "weight": p.weight_kg,
            "HR": p.HR_baseline_per_min, "SysBP": p.SBP_baseline_mmHg,
            "DiaBP": p.DBP_baseline_mmHg, "RR": p.RR_baseline_per_min}


def _fake_errors(p: pu.PatientInit) -> list[str]:
    return patient_errors(eSex.Female if p.sex else eSex.Male, p.age, p.weight, p.height_cm,
                          p.HR, p.SysBP, p.DiaBP, p.RR)


def test_init_limits_table_is_pulses():
    lim = pu.load_init_limits()
    assert lim.ranges == {"age": (18, 65), "HR": (50, 110), "SysBP": (90, 120),
                          "DiaBP": (60, 80), "RR": (8, 20)}
    assert lim.dia_sys_ratio_max == 0.75 and lim.bmi == (16, 30)
    assert lim.height_cm == pytest.approx((4.5 * 30.48, 7 * 30.48))


@pytest.mark.parametrize("pid,expected", [
    ("R1_HR130", {"HR": [130, 110]}),
    ("R2_SBP80", {"SysBP": [80, 90]}),
    ("R3_AGE80", {"age": [80, 65]}),
    # BMI 95 / 1.75^2 = 31.02 > 30: height rises to sqrt(95 / 30) m = 177.95 cm
    ("R4_BMI31", {"height_cm": [175, 100 * math.sqrt(95 / 30)]}),
])
def test_recorded_out_of_range_patients_are_clamped_into_range(pid, expected):
    p = PATIENTS.set_index("patient_id").loc[pid]
    assert not p.init_ok  # the real engine refused it
    raw = pu.PatientInit(1 if p.sex == "Female" else 0, p.age_yr, p.weight_kg, p.height_cm,
                         p.HR_baseline_per_min, p.SBP_baseline_mmHg, p.DBP_baseline_mmHg,
                         p.RR_baseline_per_min)
    errs = _fake_errors(raw)  # the fake refuses it with the engine's own words
    assert errs and all(e in p.init_message for e in errs)
    assert pu.init_violations(raw)
    used, clamped = pu.clamp_x0(_x0(p), height_cm=p.height_cm)
    assert clamped.keys() == expected.keys()
    for f, (given, new) in expected.items():
        assert clamped[f][0] == given and clamped[f][1] == pytest.approx(new, rel=1e-5)
    assert pu.init_violations(used) == [] and _fake_errors(used) == []


def test_in_range_recorded_patients_are_not_clamped():
    for _, p in PATIENTS[PATIENTS.kind == "in_range"].iterrows():
        used, clamped = pu.clamp_x0(_x0(p), height_cm=p.height_cm)
        assert clamped == {} and used.height_cm == p.height_cm


def test_clamp_always_gives_an_accepted_patient_and_moves_minimally():
    rng = np.random.default_rng(7)
    for _ in range(2000):
        x0 = {"age": rng.uniform(15, 100), "sex": float(rng.integers(0, 2)),
              "weight": rng.uniform(25, 250), "HR": rng.uniform(30, 180),
              "SysBP": rng.uniform(50, 200), "DiaBP": rng.uniform(20, 140),
              "RR": rng.uniform(2, 45)}
        used, clamped = pu.clamp_x0(x0)
        assert pu.init_violations(used) == [] and _fake_errors(used) == []
        for f in ("age", "HR", "SysBP", "RR"):  # single-feature clip = nearest value in range
            lo, hi = pu.load_init_limits().ranges[f]
            assert getattr(used, f) == min(max(x0[f], lo), hi)
            assert (f in clamped) == (not lo <= x0[f] <= hi)
        # height stays at Pulse's standard unless BMI forced it
        std = pu.STANDARD_HEIGHT_CM[int(x0["sex"])]
        bmi_std = x0["weight"] / (std / 100) ** 2
        assert (used.height_cm == std) == (16 <= bmi_std <= 30)
        assert (used.weight != x0["weight"]) == ("weight" in clamped)


def test_weight_changes_only_beyond_what_height_can_absorb():
    used, clamped = pu.clamp_x0({"age": 40, "sex": 0, "weight": 200, "HR": 80, "SysBP": 100,
                                 "DiaBP": 70, "RR": 12})
    # tallest accepted height 7 ft = 2.1336 m; heaviest at BMI 30: 30 * 2.1336^2 = 136.57 kg
    assert used.height_cm == pytest.approx(213.36)
    assert clamped["weight"][1] == pytest.approx(136.57, abs=0.01)


def test_diastolic_is_capped_at_three_quarters_of_systolic():
    used, clamped = pu.clamp_x0({"age": 40, "sex": 1, "weight": 60, "HR": 80, "SysBP": 95,
                                 "DiaBP": 78, "RR": 12})
    assert used.DiaBP == pytest.approx(71.25) and clamped["DiaBP"] == [78, 71.25]


def test_clamp_rejects_bad_input_clearly():
    good = {"age": 40, "sex": 0, "weight": 70, "HR": 80, "SysBP": 100, "DiaBP": 70, "RR": 12}
    with pytest.raises(ContractError, match="sex"):
        pu.clamp_x0({**good, "sex": 2})
    with pytest.raises(ContractError, match="HR"):
        pu.clamp_x0({**good, "HR": float("nan")})
    with pytest.raises(ContractError, match="RR"):
        pu.clamp_x0({k: v for k, v in good.items() if k != "RR"})


def test_clamp_shares_known_answer():
    x0 = pd.DataFrame([
        {"age": 70, "sex": 0, "weight": 70, "HR": 120, "SysBP": 100, "DiaBP": 70, "RR": 12},
        {"age": 40, "sex": 0, "weight": 70, "HR": 125, "SysBP": 85, "DiaBP": 70, "RR": 12},
        {"age": 40, "sex": 1, "weight": 60, "HR": 80, "SysBP": 100, "DiaBP": 70, "RR": 12},
        {"age": 40, "sex": 1, "weight": 60, "HR": 80, "SysBP": 100, "DiaBP": 70, "RR": 30},
    ])
    s = pu.clamp_shares(x0).set_index("feature")
    assert s.loc["HR", "share"] == 0.5 and s.loc["HR", "mean_abs_change"] == pytest.approx(12.5)
    assert s.loc["age", "n_clamped"] == 1 and s.loc["SysBP", "n_clamped"] == 1
    assert s.loc["RR", "n_clamped"] == 1 and s.loc["any", "share"] == 0.75
    assert set(INIT_FEATURES) <= set(s.index)


def test_bad_tables_raise_errors_naming_file_and_column(tmp_path):
    bad = tmp_path / "conversions.csv"
    text = pu.data_path("conversions.csv").read_text().replace("180.156", "abc")
    bad.write_text(text)
    with pytest.raises(ContractError, match="conversions.csv: row .*molar_mass_g_per_mol"):
        pu.load_conversions(bad)
    lim = tmp_path / "physiological_limits.csv"
    lim.write_text("feature,unit,lo,hi,reason\nHeartRate,/min,1,2,x\n")
    with pytest.raises(ContractError, match="physiological_limits.csv: row 2, column feature"):
        pu.load_physiological_limits(lim)
