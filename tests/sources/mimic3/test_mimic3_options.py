"""The extraction's switches and the cohort_variant presets (options.py), on the fixture:
each switch changes exactly what it names."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.paths import FIXTURES

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
