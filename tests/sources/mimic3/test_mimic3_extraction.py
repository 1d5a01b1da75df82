"""End-to-end tests of the MIMIC-III extraction on the hand-made v1.4-schema fixture
(tests/fixtures/mimic3, see its README), against values worked out by hand."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers.paths import FIXTURES

from twinfalsify import schema
from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3 import extract_mimic3, resolve_mimic3_dir
from twinfalsify.sources.mimic3.cohort import STEPS, _stays, suspected_infection
from twinfalsify.sources.mimic3.tables import connect, find_table

FIX = FIXTURES / "mimic3"
S1, S2, S12 = 200001, 200002, 200012
# the cohort under anchor=intime: S1, S2 (hand-computed values), S9 (weaned, not a
# withdrawal), and the stays of the fixed extraction bugs that the old code got wrong
COHORT_INTIME = [200001, 200002, 200009, 200016, 200017, 200019, 200020, 200022, 200023]


@pytest.fixture(scope="module")
def cohort():
    return extract_mimic3(FIX, anchor="intime")


@pytest.fixture(scope="module")
def cohort_fv():
    return extract_mimic3(FIX, anchor="first_vitals")


def test_consort_counts_each_step(cohort):
    c = cohort.consort
    assert list(c["step"]) == list(STEPS)
    # 24 stays (README); under anchor=intime the anchor step excludes nothing, and S12/S13
    # (vitals 1 h / 6 h late) join S4 at vitals_complete: [INTIME, INTIME + 1 h) has none
    assert list(c["n_stays"]) == [24, 23, 20, 17, 16, 15, 14, 14, 13, 12, 9, 9, 9]
    assert list(c["n_excluded"]) == [0, 1, 3, 3, 1, 1, 1, 0, 1, 1, 3, 0, 0]
    assert sorted(cohort.trajectories[schema.STAY_ID].unique()) == COHORT_INTIME
    assert (cohort.anchors["anchor_h"] == 0).all()
    assert (cohort.anchors["t0"] == cohort.anchors["intime"]).all()


def test_first_vitals_consort(cohort_fv):
    c = cohort_fv.consort
    assert list(c["step"]) == list(STEPS)
    # S13 has no complete vital set in the first 6 ICU hours (anchor step); S12 is kept
    assert list(c["n_stays"]) == [24, 23, 20, 17, 16, 15, 14, 13, 12, 11, 10, 10, 10]
    assert list(c["n_excluded"]) == [0, 1, 3, 3, 1, 1, 1, 1, 1, 1, 1, 0, 0]
    assert sorted(cohort_fv.trajectories[schema.STAY_ID].unique()) == sorted(
        [*COHORT_INTIME, S12])
    a = cohort_fv.anchors.set_index(schema.STAY_ID)
    assert a["anchor_h"].to_dict() == {**dict.fromkeys(COHORT_INTIME, 0), S12: 1}
    assert a.loc[S12, "t0"] == pd.Timestamp("2150-01-03 11:00:00")  # INTIME 10:00 + 1 h


def test_first_vitals_late_stay_aligned_to_anchor(cohort_fv):
    s = _stay(cohort_fv, S12)
    # vitals charted at INTIME + 1:30, 2:30, ..., 5:30: anchor block [INTIME + 1 h, + 2 h),
    # so t = 0..4 hold the values of hours 1..5 = the fixture's hour-0..4 values
    assert s["HR"].tolist() == [80, 100, 90, 85, 95]
    assert s["MeanBP"].tolist() == [80, 73, 77, 80, 82]
    # 100.4 F at INTIME + 1:00 (t = 0) -> 38.0 C held 6 h; 37.0 C at INTIME + 4:30 (t = 3)
    np.testing.assert_allclose(s["Temp_C"], [38.0, 38.0, 38.0, 37.0, 37.0], atol=1e-9)
    # labs at INTIME - 1 h: blood gas held 8 h, still valid at the last block start (+5 h)
    assert (s["Arterial_pH"] == 7.4).all() and (s["Potassium"] == 4.0).all()
    # doses by hand, INTIME-relative hours -> anchor-relative t = hour - 1:
    # NaCl bolus 100 mL at INTIME + 0:20 is in hour 0, before t = 0: not in the trajectory;
    # NaCl 500 mL at 250 mL/h over INTIME + 0:30..2:30: hour 0 125 (dropped), hour 1 250
    # (t = 0), hour 2 125 (t = 1); norepinephrine 0.2 ug/kg/min over 4:15..4:45: hour 4 (t = 3)
    np.testing.assert_allclose(s["iv_fluid"], [250, 125, 0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(s["vasopressor"], [0, 0, 0, 0.2, 0], atol=1e-9)


def test_first_vitals_leaves_intime_anchored_stays_unchanged(cohort, cohort_fv):
    # the intime cohort's stays have vitals in hour 0: anchor 0, so both anchors give
    # identical rows, except imputed cells (1-NN donors come from the cohort, which differs)
    a = cohort.trajectories.set_index([schema.STAY_ID, "t"])
    b = cohort_fv.trajectories.set_index([schema.STAY_ID, "t"]).loc[a.index]
    imp = cohort.imputed.set_index([schema.STAY_ID, "t"]).loc[a.index]
    keep = [c for c in a.columns if c not in imp.columns]
    pd.testing.assert_frame_equal(a[keep], b[keep])
    for col in imp.columns:
        own = ~imp[col].to_numpy()
        np.testing.assert_array_equal(a[col].to_numpy()[own], b[col].to_numpy()[own])


def test_anchor_window_bounds_the_search():
    # S13's vitals start at INTIME + 6:30, in hour 6: outside the default 6 h window (hours
    # 0..5), inside a 7 h window, where it is kept with t = 0 at INTIME + 6 h
    res = extract_mimic3(FIX, anchor="first_vitals", anchor_window_h=7)
    a = res.anchors.set_index(schema.STAY_ID)["anchor_h"]
    assert a.to_dict() == {**dict.fromkeys(COHORT_INTIME, 0), S12: 1, 200013: 6}
    assert res.consort.set_index("step").loc["anchor", "n_excluded"] == 0
    s = _stay(res, 200013)
    assert s["HR"].tolist() == [80, 100, 90, 85, 95]
    # its only fluid is the 100 mL bolus at INTIME + 0:20, long before t = 0
    assert (s["iv_fluid"] == 0).all()


def test_default_anchor_is_first_vitals(cohort_fv):
    res = extract_mimic3(FIX)
    pd.testing.assert_frame_equal(res.trajectories, cohort_fv.trajectories)


def test_bad_anchor_is_named():
    with pytest.raises(ContractError, match="anchor must be one of"):
        extract_mimic3(FIX, anchor="first_hr")
    with pytest.raises(ContractError, match="anchor_window_h"):
        extract_mimic3(FIX, anchor="first_vitals", anchor_window_h=0)


def test_onset_rules():
    con = connect(FIX)
    stays = _stays(con)
    inf = suspected_infection(con, stays)
    onset = inf["onset"]
    # S1: antibiotic 2150-01-03 00:00, culture 08:00 (8 h later) -> onset = antibiotic
    assert onset[S1] == pd.Timestamp("2150-01-03 00:00:00")
    assert inf.loc[S1, "onset_source"] == "antibiotic"
    # S2: culture 2160-05-04 12:00, antibiotic 2160-05-05 00:00 (12 h later) -> onset = culture
    assert onset[S2] == pd.Timestamp("2160-05-04 12:00:00")
    assert inf.loc[S2, "onset_source"] == "culture"
    # S3: antibiotic 4 days after the culture: outside both windows
    assert 200003 not in onset.index
    assert 200005 in onset.index  # the minor has an infection; excluded for age, not here


def test_trajectories_pass_contract(cohort):
    t = schema.validate_trajectories(cohort.trajectories)
    assert list(t.columns) == [*schema.TRAJECTORY_COLUMNS, schema.SUBJECT_ID]
    # the patient of each stay (S21 and S22 are one admission of subject 21)
    subj = t.groupby(schema.STAY_ID)[schema.SUBJECT_ID].first()
    assert subj[S1] == 1 and subj[200022] == 21
    assert all(v == [0, 1, 2, 3, 4] for v in t.groupby(schema.STAY_ID)["t"].apply(list))


def _stay(cohort, sid):
    return cohort.trajectories[cohort.trajectories[schema.STAY_ID] == sid].set_index("t")


def test_metavision_stay_hourly_values(cohort):
    s = _stay(cohort, S1)
    # vitals charted at INTIME + h + 30 min, one per hour
    assert s["HR"].tolist() == [80, 100, 90, 85, 95]
    assert s["MeanBP"].tolist() == [80, 73, 77, 80, 82]
    # 100.4 F at 0:30 -> (100.4 - 32) * 5/9 = 38.0 C, held 6 h over t = 1, 2; 37.0 C at 3:30
    np.testing.assert_allclose(s["Temp_C"], [38.0, 38.0, 38.0, 37.0, 37.0], atol=1e-9)
    # labs drawn 1 h before ICU admission, held (K 14 h, blood gas 8 h)
    assert (s["Potassium"] == 4.0).all() and (s["Arterial_pH"] == 7.4).all()
    assert (s["weight"] == 70.0).all() and (s["sex"] == 1).all()
    np.testing.assert_allclose(s["age"], 60.0, atol=1e-9)
    # NaCl 0.9 % 500 mL at 250 mL/h over 0:30-2:30 -> 125, 250, 125 mL; albumin 25 % 100 mL
    # bolus at 3:15 -> 100 x 5 = 500 mL NS-equivalent; the 'Rewritten' 1000 mL row ignored
    np.testing.assert_allclose(s["iv_fluid"], [125, 250, 125, 500, 0], atol=1e-9)
    # norepinephrine 0.1 ug/kg/min 0:30-2:30; vasopressin 2.4 U/h 1:00-3:00 -> 2.4 * 5/60 =
    # 0.2; phenylephrine 80 ug/min 3:00-4:00 -> 80 * 0.45 / 80 = 0.45; max per hour
    np.testing.assert_allclose(s["vasopressor"], [0.1, 0.2, 0.2, 0.45, 0.0], atol=1e-9)


def test_carevue_stay_hourly_values(cohort):
    s = _stay(cohort, S2)
    # 176 lb -> 176 * 0.45359237 kg
    np.testing.assert_allclose(s["weight"], 176 * 0.45359237, rtol=1e-12)
    # 98.6 F at 0:30 -> 37.0 C (held to t = 1); 38.5 C (item 676) at 2:30 -> t = 2..4
    np.testing.assert_allclose(s["Temp_C"], [37.0, 37.0, 38.5, 38.5, 38.5], atol=1e-9)
    assert (s["sex"] == 0).all()
    # CareVue amounts are boluses at CHARTTIME: NaCl 250 mL at 1:20; 3 % saline 100 mL x 3
    np.testing.assert_allclose(s["iv_fluid"], [0, 250, 0, 300, 0], atol=1e-9)
    # Levophed 8 ug/min / 80 = 0.1 at 0:30; dopamine 5 ug/kg/min x 0.01 = 0.05 at 2:10;
    # vasopressin 0.04 U/min x 5 = 0.2 at 3:20 (charted rates count in their hour)
    np.testing.assert_allclose(s["vasopressor"], [0.1, 0.0, 0.05, 0.2, 0.0], atol=1e-9)


def test_missingness_report(cohort):
    m = cohort.missingness.set_index(["feature", "t"])
    assert set(m.columns) >= {"n_missing_raw", "share_missing_raw"}
    # temperatures: S2 raw at t = 0, 2; the 8 other stays raw at t = 0, 3
    assert [m.loc[("Temp_C", t), "n_missing_raw"] for t in range(5)] == [0, 9, 8, 1, 9]
    # labs drawn before ICU admission: raw-missing in every hour, except S17's sodium
    # (drawn at INTIME + 3:30: raw at t = 3, held at t = 4, imputed at t = 0..2)
    na = m.xs("Sodium", level="feature")
    assert na["n_missing_raw"].tolist() == [9, 9, 9, 8, 9]
    assert na["n_imputed"].tolist() == [1, 1, 1, 0, 0]
    # S16's weight, charted at INTIME + 2:10, is imputed at t = 0, 1
    assert m.xs("weight", level="feature")["n_imputed"].tolist() == [1, 1, 0, 0, 0]
    assert m.loc[("HR", 0), "share_missing_raw"] == 0.0


def _copy_as(tmp: Path, lower: bool, gz: bool) -> Path:
    for f in FIX.glob("*.csv"):
        name = f.stem.lower() if lower else f.stem
        if gz:
            with open(f, "rb") as src, gzip.open(tmp / f"{name}.csv.gz", "wb") as dst:
                shutil.copyfileobj(src, dst)
        else:
            shutil.copy(f, tmp / f"{name}.csv")
    return tmp


def test_lower_case_gz_and_parquet_give_same_result(tmp_path, cohort):
    d = _copy_as(tmp_path, lower=True, gz=True)
    # one table as Parquet (upper-case name), with the CSV removed
    pd.read_csv(FIX / "ICUSTAYS.csv", dtype=str).to_parquet(d / "ICUSTAYS.parquet")
    (d / "icustays.csv.gz").unlink()
    res = extract_mimic3(d, anchor="intime")
    pd.testing.assert_frame_equal(res.trajectories, cohort.trajectories)
    pd.testing.assert_frame_equal(res.consort, cohort.consort)


def test_missing_table_error_names_folder_and_files(tmp_path):
    d = _copy_as(tmp_path, lower=False, gz=False)
    (d / "LABEVENTS.csv").unlink()
    with pytest.raises(ContractError) as e:
        extract_mimic3(d)
    msg = str(e.value)
    assert str(d) in msg and "LABEVENTS.csv.gz" in msg and "labevents.parquet" in msg
    with pytest.raises(ContractError, match="LABEVENTS"):
        find_table(d, "LABEVENTS")


def test_wrong_columns_error(tmp_path):
    d = _copy_as(tmp_path, lower=False, gz=False)
    pd.read_csv(d / "PATIENTS.csv").drop(columns=["DOB"]).to_csv(d / "PATIENTS.csv", index=False)
    with pytest.raises(ContractError, match=r"PATIENTS\.csv: missing .* column\(s\) DOB"):
        extract_mimic3(d)


def test_resolve_dir_env_override(tmp_path, monkeypatch):
    monkeypatch.delenv("TWINFALSIFY_MIMIC3_DIR", raising=False)
    assert resolve_mimic3_dir(str(tmp_path)) == tmp_path
    monkeypatch.setenv("TWINFALSIFY_MIMIC3_DIR", str(FIX))
    assert resolve_mimic3_dir("/nonexistent") == FIX
    monkeypatch.setenv("TWINFALSIFY_MIMIC3_DIR", str(tmp_path / "nope"))
    with pytest.raises(ContractError, match="TWINFALSIFY_MIMIC3_DIR") as e:
        resolve_mimic3_dir(str(tmp_path))
    assert "nope" in str(e.value)
    monkeypatch.delenv("TWINFALSIFY_MIMIC3_DIR")
    with pytest.raises(ContractError, match="TWINFALSIFY_MIMIC3_DIR"):
        resolve_mimic3_dir(None)


# --- one fixture stay per extraction bug; the old code got each wrong (tests/fixtures/mimic3
# README: the old extraction kept S14, S15, S21, S24, excluded S9, S19, S20, S23 and gave
# S16 / S17 values from later hours)

def _audit(cohort):
    return cohort.stays.set_index(schema.STAY_ID)


def test_onset_outside_the_stay_window_is_dropped(cohort):
    # S14: the admission's only stay; antibiotic 86 h after OUTTIME
    a = _audit(cohort).loc[200014]
    assert a["onset"] == pd.Timestamp("2150-01-08 00:00:00")
    assert not a["onset_in_window"] and a["excluded_at"] == "suspected_infection"


def test_labs_before_the_lab_window_do_not_count(cohort):
    # S15: platelets 80 drawn 40 h before INTIME (inside the SOFA window around the onset,
    # outside [INTIME - 1 d, OUTTIME + 1 d]): SOFA 0
    a = _audit(cohort).loc[200015]
    assert a["max_sofa"] == 0 and a["excluded_at"] == "sofa_ge_2"


def test_weight_never_comes_from_a_later_hour(cohort):
    # S16: weight 95 kg charted at INTIME + 2:10 only. Hours 0, 1 are imputed from other
    # stays' rows of hours <= t: the nearest are the template stays (identical vitals and
    # labs, distance 0), the first of which is S1 (70 kg)
    s = _stay(cohort, 200016)
    assert s["weight"].tolist() == [70.0, 70.0, 95.0, 95.0, 95.0]
    imp = cohort.imputed.set_index([schema.STAY_ID, "t"]).loc[200016, "weight"]
    assert imp.tolist() == [True, True, False, False, False]


def test_imputation_never_uses_the_stays_own_later_hours(cohort):
    # S17: vitals 30 above every other stay's, so its own rows are its nearest neighbours;
    # sodium 150 drawn at INTIME + 3:30 only. Hours 0..2 take 140 from other stays (the
    # old 1-NN over all rows took 150 from S17's own hour 3)
    assert _stay(cohort, 200017)["Sodium"].tolist() == [140.0, 140.0, 140.0, 150.0, 150.0]


def test_withdrawal_needs_the_last_sofa_condition(cohort):
    a = _audit(cohort)
    # S9: vasopressor stopped, then recovered (last SOFA 2 < 6 / 2): kept
    assert a.loc[200009, "in_cohort"] and a.loc[200009, "not_withdrawn"]
    # S18: same, but bilirubin 7 at 38 h keeps the last SOFA at 5 >= 6 / 2: withdrawal
    assert a.loc[200018, "excluded_at"] == "not_withdrawn"


def test_smaller_items(cohort):
    a = _audit(cohort)
    # S19: cefpodoxime is an antibiotic
    assert a.loc[200019, "suspected_infection"] and a.loc[200019, "in_cohort"]
    # S20: a culture charted in CHARTEVENTS (225401) counts
    assert a.loc[200020, "culture_time"] == a.loc[200020, "intime"] - pd.Timedelta(hours=2)
    assert a.loc[200020, "in_cohort"]
    # S21 / S22: an antibiotic with PRESCRIPTIONS.ICUSTAY_ID = S22 belongs to S22 only
    assert pd.isna(a.loc[200021, "onset"]) and a.loc[200021, "excluded_at"] == (
        "suspected_infection")
    assert a.loc[200022, "onset"] == pd.Timestamp("2150-01-06 00:00:00")
    # S23: weight charted as CareVue 581 (kg)
    assert (_stay(cohort, 200023)["weight"] == 82.0).all()
    # S24: GCS 8 with an intubated verbal score is not assessable: SOFA 0
    assert a.loc[200024, "max_sofa"] == 0 and a.loc[200024, "excluded_at"] == "sofa_ge_2"


def test_audit_table_one_row_per_stay_every_reason(cohort):
    a = _audit(cohort)
    assert len(a) == 24 and a.index.is_unique
    assert set(a.index[a["in_cohort"]]) == set(COHORT_INTIME)
    assert (a.loc[a["in_cohort"], "excluded_at"].fillna("") == "").all()
    # every failed criterion is listed, not only the first: the minor S5 also fails nothing
    # else; S11 (no weight) fails only weight_documented
    assert a.loc[200005, "reasons"] == "adult"
    assert a.loc[200011, "reasons"] == "weight_documented"
    # the first failed step is the CONSORT step that excluded the stay
    excl = a.loc[~a["in_cohort"], "excluded_at"].value_counts()
    c = cohort.consort.set_index("step")["n_excluded"]
    assert all(excl.get(step, 0) == c[step] for step in STEPS[1:])
    # organs behind the SOFA: S1 coagulation 2 + cardiovascular 4
    assert a.loc[S1, "sofa_organs"] == "coagulation=2;cardiovascular=4"
    assert a.loc[S1, "n_imputed_weight_hours"] == 0 and a.loc[S1, "n_imputed_lab_cells"] == 0
    assert a.loc[200016, "n_imputed_weight_hours"] == 2
    assert a.loc[200016, "n_imputed_lab_cells"] == 0
