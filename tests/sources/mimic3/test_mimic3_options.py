"""The extraction's switches and the cohort_variant presets (options.py), on the fixture:
each switch changes exactly what it names."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.paths import FIXTURES, ROOT

from twinfalsify import schema
from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.cohort import _assign_to_stays
from twinfalsify.sources.mimic3.options import PRESETS, Mimic3Options, options_from_config

FIX = FIXTURES / "mimic3"


@pytest.fixture(scope="module")
def base():
    return extract_mimic3(FIX, anchor="intime")


def _run(**kw):
    return extract_mimic3(FIX, anchor="intime", options=Mimic3Options(**kw))


def _ids(res):
    return set(res.trajectories[schema.STAY_ID])


def _stay(res, sid):
    t = res.trajectories
    return t[t[schema.STAY_ID] == sid].set_index("t")


def test_defaults_are_the_project_preset(base):
    assert options_from_config({}) == PRESETS["project"] == Mimic3Options()
    assert base.options == Mimic3Options().as_dict()


def test_preset_and_override():
    o = options_from_config({"cohort_variant": "ai_clinician", "hold": "last_hour_mean"})
    assert o.sofa == "ai_clinician" and o.gcs_intubated == "verbal_1" and o.event_stay == "last"
    assert o.hold == "last_hour_mean"
    with pytest.raises(ContractError, match="source.mimic3.cohort_variant"):
        options_from_config({"cohort_variant": "mimic"})
    with pytest.raises(ContractError, match=r"source.mimic3.sofa: 'full' is not one of"):
        options_from_config({"sofa": "full"})


def test_sofa_ai_clinician_reads_rass_and_urine(base):
    res = _run(sofa="ai_clinician")
    a = res.stays.set_index(schema.STAY_ID)
    # S6: RASS -4 -> GCS 6 -> CNS 3; S15: 20 mL urine in a 4 h block -> renal 4
    assert a.loc[200006, "sofa_organs"] == "cns=3" and a.loc[200015, "sofa_organs"] == "renal=4"
    # S24's MetaVision GCS components are not read at all
    assert a.loc[200024, "max_sofa"] == 0
    assert _ids(res) == _ids(base) | {200006, 200015}


def test_gcs_intubated_verbal_1_scores_the_charted_1(base):
    a = _run(gcs_intubated="verbal_1").stays.set_index(schema.STAY_ID)
    assert a.loc[200024, "max_sofa"] == 3 and a.loc[200024, "sofa_ge_2"]  # GCS 2 + 1 + 6 = 9


def test_weight_missing_exclude(base):
    res = _run(weight_missing="exclude")
    assert _ids(res) == _ids(base) - {200016}
    assert res.stays.set_index(schema.STAY_ID).loc[200016, "excluded_at"] == "weight_documented"


def test_rewritten_rows_counted_for_fluids_only_under_ai_clinician(base):
    # S1's 'Rewritten' NaCl order, 1000 mL at 1000 mL/h over hour 0
    s = _stay(_run(rewritten="ai_clinician"), 200001)
    np.testing.assert_allclose(s["iv_fluid"], [1125, 250, 125, 500, 0], atol=1e-9)
    np.testing.assert_allclose(s["vasopressor"], _stay(base, 200001)["vasopressor"])


def test_bp_items_ai_clinician_derives_diastolic(base):
    s = _stay(_run(bp_items="ai_clinician"), 200001)  # MetaVision: 220180 not read
    np.testing.assert_allclose(s["DiaBP"], (3 * s["MeanBP"] - s["SysBP"]) / 2)
    assert s["DiaBP"].tolist() != _stay(base, 200001)["DiaBP"].tolist()
    # CareVue diastolic (8368) is read either way
    assert _stay(_run(bp_items="ai_clinician"), 200002)["DiaBP"].tolist() == [60, 55, 58, 61, 62]


def test_hold_last_hour_mean(base):
    # nothing in the fixture is held from an hour with two values, so the cohort is the same
    pd.testing.assert_frame_equal(_run(hold="last_hour_mean").trajectories, base.trajectories)


def test_event_stay_nearest_or_last():
    h = pd.Timedelta(hours=1)
    t = pd.Timestamp("2150-01-10 00:00")
    stays = pd.DataFrame({"icustay_id": [1, 2], "hadm_id": [9, 9],
                          "intime": [t, t + 30 * h], "outtime": [t + 10 * h, t + 50 * h]})
    # 6 h after stay 1 ends, 14 h before stay 2 starts: in both windows
    ev = pd.DataFrame({"hadm_id": [9], "time": [t + 16 * h]})
    assert _assign_to_stays(ev, stays, "nearest")["icustay_id"].tolist() == [1]
    assert _assign_to_stays(ev, stays, "last")["icustay_id"].tolist() == [2]
    # a given ICUSTAY_ID wins; an unknown one drops the event
    ev2 = pd.DataFrame({"hadm_id": [9, 9], "icustay_id": [2, 7], "time": [t, t]})
    assert _assign_to_stays(ev2, stays)["icustay_id"].tolist() == [2]


def test_ai_clinician_preset_end_to_end(base):
    res = extract_mimic3(FIX, anchor="intime", options=PRESETS["ai_clinician"])
    assert res.options == PRESETS["ai_clinician"].as_dict()
    # sofa (+S6, +S15; S24 excluded either way), gcs verbal_1 (S24 needs the components,
    # not read under sofa = ai_clinician), rewritten (S1 fluids), bp (S1 diastolic)
    assert _ids(res) == _ids(base) | {200006, 200015}
    np.testing.assert_allclose(_stay(res, 200001)["iv_fluid"], [1125, 250, 125, 500, 0])


# --- the switches of the rules that depart from AI-Clinician -------------------------

PAT = FIXTURES / "mimic3-patients"
NEW_SWITCHES = {"venous_gas": ("exclude", "keep"), "screens": ("exclude", "count"),
                "urine_irrigant": ("subtract", "ignore"), "tf_residual": ("exclude", "count"),
                "fio2_lab": ("read", "ignore")}


def test_rule_switches_default_on_and_preset_off():
    """Each rule is a switch: the project's value by default, AI-Clinician's in the preset;
    a bad value is refused naming the key, as for every other switch."""
    assert {k: getattr(Mimic3Options(), k) for k in NEW_SWITCHES} == {
        k: v[0] for k, v in NEW_SWITCHES.items()}
    assert {k: getattr(PRESETS["ai_clinician"], k) for k in NEW_SWITCHES} == {
        k: v[1] for k, v in NEW_SWITCHES.items()}
    o = options_from_config({"cohort_variant": "ai_clinician", "venous_gas": "exclude"})
    assert o.venous_gas == "exclude" and o.screens == "count"
    for key in NEW_SWITCHES:
        with pytest.raises(ContractError, match=rf"source.mimic3.{key}: 'on' is not one of"):
            options_from_config({key: "on"})


def test_schema_lists_every_switch_with_its_choices():
    """The config schema (validated when a config is read) offers each switch with exactly
    the values options.CHOICES accepts, the default left to the preset."""
    import yaml

    from twinfalsify.sources.mimic3.options import CHOICES
    sch = yaml.safe_load((ROOT / "workflow" / "schemas" / "config.schema.yaml").read_text())
    props = sch["properties"]["source"]["properties"]["mimic3"]["properties"]
    for key, values in CHOICES.items():
        assert props[key]["enum"] == list(values), key
        assert "default" not in props[key] and props[key]["description"], key


def test_screens_count_makes_a_screening_swab_a_culture(tmp_path):
    """300013 has an antibiotic and no culture; an MRSA screen 6 h after the antibiotic is no
    culture by default (no_culture) and AI-Clinician's culture under screens: count."""
    import shutil

    from twinfalsify.sources.mimic3.cohort import _stays, suspected_infection
    from twinfalsify.sources.mimic3.tables import connect
    shutil.copytree(PAT, tmp_path / "m")
    mic = pd.read_csv(tmp_path / "m" / "MICROBIOLOGYEVENTS.csv", dtype=str)
    row = {c: "" for c in mic.columns} | {
        "ROW_ID": "999", "SUBJECT_ID": "13", "HADM_ID": "113", "CHARTDATE": "2150-01-03",
        "CHARTTIME": "2150-01-03 06:00:00", "SPEC_ITEMID": "70091",
        "SPEC_TYPE_DESC": "MRSA SCREEN"}
    pd.concat([mic, pd.DataFrame([row])]).to_csv(tmp_path / "m" / "MICROBIOLOGYEVENTS.csv",
                                                 index=False)
    con = connect(tmp_path / "m")
    stays = _stays(con)
    ev_default, ev_count = {}, {}
    default = suspected_infection(con, stays, evidence=ev_default)
    count = suspected_infection(con, stays, evidence=ev_count, screens="count")
    assert 300013 not in default.index
    assert count.loc[300013, "onset"] == pd.Timestamp("2150-01-03 00:00:00")
    assert count.loc[300013, "culture_time"] == pd.Timestamp("2150-01-03 06:00:00")
    # counted either way; every other stay's onset is the same
    assert ev_default["screens"][300013] == ev_count["screens"][300013] == 1
    pd.testing.assert_frame_equal(count.drop(300013), default)


def _gas_con(fio2_lab_value: float = 50.0, specimen: str = "VEN"):
    """A DuckDB connection with one stay's chart FiO2 (40 % at 10:00) and, at 11:00, a blood
    gas: PaO2 35 with its specimen row (50800) and its FiO2 (50816)."""
    import duckdb

    con = duckdb.connect()
    t = "2150-01-01 "
    con.register("CHARTEVENTS", pd.DataFrame({
        "ICUSTAY_ID": ["1"], "ITEMID": ["223835"], "CHARTTIME": [t + "10:00:00"],
        "VALUENUM": ["40"], "VALUE": ["40"], "ERROR": ["0"]}))
    con.register("LABEVENTS", pd.DataFrame({
        "SUBJECT_ID": "1", "HADM_ID": "10", "ITEMID": ["50821", "50800", "50816"],
        "CHARTTIME": t + "11:00:00", "VALUENUM": ["35", None, str(fio2_lab_value)],
        "VALUE": ["35", specimen, str(fio2_lab_value)]}))
    stays = pd.DataFrame({"hadm_id": [10], "subject_id": [1],
                          "admittime": [pd.Timestamp(t + "00:00")],
                          "dischtime": [pd.Timestamp("2150-01-05")],
                          "intime": [pd.Timestamp(t + "08:00")],
                          "outtime": [pd.Timestamp("2150-01-03")]}, index=pd.Index([1]))
    lo = pd.Series(pd.Timestamp(t + "08:00"), index=[1])
    return con, stays, lo, lo + pd.Timedelta(hours=8)


def test_fio2_lab_50816_is_read_for_pf_unless_ignored():
    from twinfalsify.sources.mimic3.cohort import _events
    con, stays, lo, hi = _gas_con(fio2_lab_value=0.6)  # a fraction: read as 60 %
    ev = _events(con, stays, lo, hi, ("sofa_fio2",), Mimic3Options())
    assert sorted(ev["value"]) == [40.0, 60.0]
    ev = _events(con, stays, lo, hi, ("sofa_fio2",), Mimic3Options(fio2_lab="ignore"))
    assert ev["value"].tolist() == [40.0]  # AI-Clinician: the chart FiO2 only


def test_venous_gas_keep_reads_the_venous_pao2():
    from twinfalsify.sources.mimic3.cohort import _events
    con, stays, lo, hi = _gas_con(specimen="VEN")
    counts: dict = {}
    ev = _events(con, stays, lo, hi, ("paO2",), Mimic3Options(), counts=counts)
    assert ev.empty and counts["venous_gas"][1] == 1
    counts = {}
    ev = _events(con, stays, lo, hi, ("paO2",), Mimic3Options(venous_gas="keep"), counts=counts)
    assert ev["value"].tolist() == [35.0] and "venous_gas" not in counts
    con, stays, lo, hi = _gas_con(specimen="ART")  # an arterial gas is kept either way
    assert _events(con, stays, lo, hi, ("paO2",), Mimic3Options())["value"].tolist() == [35.0]


def test_urine_irrigant_and_tube_feed_residual_switches():
    """Through the urine reader: 227489 500 mL with 227488 200 mL in at 10:30 and a tube-feed
    residual 227510 of 150 mL at 11:00 (block 0), 40055 60 mL at 14:30 (block 1)."""
    import duckdb

    from twinfalsify.sources.mimic3.cohort import _urine, urine_items
    t = pd.Timestamp("2150-01-01 10:00")
    rows = [(0.5, 227489, 500), (0.5, 227488, 200), (1.0, 227510, 150), (4.5, 40055, 60)]
    con = duckdb.connect()
    con.register("OUTPUTEVENTS", pd.DataFrame({
        "ICUSTAY_ID": "1", "ITEMID": [str(r[1]) for r in rows],
        "CHARTTIME": [str(t + pd.Timedelta(hours=r[0])) for r in rows],
        "VALUE": [str(r[2]) for r in rows]}))
    lo = pd.Series([t], index=[1])

    def uo(**kw):
        return _urine(con, [1], lo, 2, Mimic3Options(**kw)).to_dict()
    assert uo() == {(1, 0): 300.0, (1, 1): 60.0}  # 500 - 200, residual left out
    assert uo(tf_residual="count") == {(1, 0): 450.0, (1, 1): 60.0}
    assert uo(urine_irrigant="ignore") == {(1, 0): 500.0, (1, 1): 60.0}
    assert uo(urine_irrigant="ignore", tf_residual="count") == {(1, 0): 650.0, (1, 1): 60.0}
    read = set(urine_items(PRESETS["ai_clinician"])["itemid"])
    assert 227510 in read and 227488 not in read  # AI-Clinician's list, as it has it
    read = set(urine_items()["itemid"])
    assert 227510 not in read and 227488 in read
