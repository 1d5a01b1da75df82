"""The extraction on the whole open MIMIC-III Clinical Database Demo v1.4 (100 patients,
ODbL), when ../shared/data/mimic-iii-demo exists; skipped otherwise."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from helpers.paths import ROOT, shared_dir

from twinfalsify import schema
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.cohort import STEPS
from twinfalsify.sources.mimic3.hourly import LABS
from twinfalsify.sources.mimic3.options import PRESETS


def _shared() -> Path:
    p = ROOT.parent / "shared"
    return shared_dir() or p


DEMO = _shared() / "data" / "mimic-iii-demo"
# two whole-demo extractions: ~8 s on an idle machine, more under load
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                                 reason=f"MIMIC-III demo not present at {DEMO}")]
# documented in docs/how-to/mimic3.md (CONSORT of the demo under each anchor)
COUNTS = {
    "intime": [136, 135, 85, 72, 72, 70, 67, 67, 67, 65, 21, 21, 21],
    "first_vitals": [136, 135, 85, 72, 72, 70, 67, 65, 65, 63, 61, 61, 61],
}
COUNTS_AI_CLINICIAN = {
    "intime": [136, 135, 86, 71, 71, 69, 66, 66, 66, 64, 21, 21, 21],
    "first_vitals": [136, 135, 86, 71, 71, 69, 66, 64, 64, 62, 60, 60, 60],
}


@pytest.fixture(scope="module")
def demo():
    return {a: extract_mimic3(DEMO, anchor=a) for a in COUNTS}


@pytest.mark.parametrize("anchor", list(COUNTS))
def test_whole_demo(demo, anchor):
    res = demo[anchor]
    c = res.consort.set_index("step")["n_stays"]
    # 136 ICU stays of 100 patients in the demo (ICUSTAYS.csv has 136 rows)
    assert c.tolist() == COUNTS[anchor]
    assert (res.consort["n_excluded"] >= 0).all()
    t = schema.validate_trajectories(res.trajectories)
    assert t[schema.STAY_ID].nunique() == c["imputable"] == len(res.anchors)
    assert res.stays["in_cohort"].sum() == c["imputable"] and len(res.stays) == 136
    # plausible clinical ranges (the contract validation checks the wider plausibility ranges)
    assert t["HR"].between(30, 200).all() and t["Temp_C"].between(32, 42).all()
    assert t["age"].min() >= 18 and t["weight"].between(30, 250).all()
    assert t["iv_fluid"].between(0, 5000).all() and t["vasopressor"].between(0, 5).all()
    m = res.missingness
    assert set(m["feature"]) == set(schema.FEATURES) and m["t"].nunique() == schema.T_MAX + 1
    assert m["share_missing_raw"].between(0, 1).all()
    # first_vitals: hour t = 0 is a block with every vital charted or held
    a = res.anchors
    assert a["anchor_h"].between(0, 5).all()
    assert ((a["t0"] - a["intime"]) == pd.to_timedelta(a["anchor_h"], unit="h")).all()


def test_first_vitals_extends_intime(demo):
    """Every stay kept at INTIME has a complete vital set in hour 0, so first_vitals anchors
    it at INTIME too and gives it the same rows, except weight and labs filled by 1-NN
    imputation (donors are drawn from the larger cohort)."""
    i, f = demo["intime"], demo["first_vitals"]
    a = f.anchors.set_index(schema.STAY_ID)["anchor_h"]
    ids = sorted(i.trajectories[schema.STAY_ID].unique())
    assert set(ids) <= set(a.index) and (a.loc[ids] == 0).all()
    assert set(a.index[a == 0]) == set(ids)
    ti = i.trajectories.set_index([schema.STAY_ID, "t"])
    tf = f.trajectories.set_index([schema.STAY_ID, "t"]).loc[ti.index]
    imputable = ["weight", *LABS]
    rest = [c for c in ti.columns if c not in imputable]
    pd.testing.assert_frame_equal(ti[rest], tf[rest])
    # weight and labs differ only where imputed
    imp = i.imputed.set_index([schema.STAY_ID, "t"]).loc[ti.index, imputable].to_numpy()
    diff = (ti[imputable] != tf[imputable]).to_numpy()
    assert not (diff & ~imp).any()


@pytest.mark.parametrize("anchor", list(COUNTS_AI_CLINICIAN))
def test_ai_clinician_preset(anchor):
    res = extract_mimic3(DEMO, anchor=anchor, options=PRESETS["ai_clinician"])
    assert res.consort["n_stays"].tolist() == COUNTS_AI_CLINICIAN[anchor]
    schema.validate_trajectories(res.trajectories)


@pytest.fixture(scope="module")
def preset():
    return extract_mimic3(DEMO, anchor="first_vitals", options=PRESETS["ai_clinician"])


def test_sofa_components_held_only_for_their_hold_time(preset, demo):
    a = preset.stays.set_index(schema.STAY_ID)
    # 239935: a bilirubin of 36 h before scored liver 1 when carried without a limit (10);
    # held 28 h (AI-Clinician's Total_bili hold) it is gone: 9
    assert a.loc[239935, "max_sofa"] == 9
    # 273347: a PaO2 carried 20 h and divided by a later FiO2 scored respiration 3 (8);
    # held 8 h: 7, without respiration
    assert a.loc[273347, "max_sofa"] == 7
    assert "respiration" not in a.loc[273347, "sofa_organs"]
    # the withdrawal rule still reads the last block with every component carried:
    # 228977 stays excluded there
    assert a.loc[228977, "excluded_at"] == "not_withdrawn"
    p = demo["first_vitals"].stays.set_index(schema.STAY_ID)
    # defaults: 239935's maximum block had norepinephrine 0.100053, read to 3 decimals 0.1
    # (cardiovascular 3, not 4): 8
    assert p.loc[239935, "max_sofa"] == 8 and p.loc[273347, "max_sofa"] == 5


def test_own_earlier_weight_before_a_donor(demo):
    res = demo["first_vitals"]
    a = res.stays.set_index(schema.STAY_ID)
    w = res.trajectories.set_index([schema.STAY_ID, "t"])["weight"]
    # 222779: its 234 "kg" charts are deleted (BMI 86 at 165 cm); the patient weighed 96.6 kg
    # 16.5 days before (stay 261764): that, not another patient's 141.5 kg (BMI 52)
    assert w.loc[222779].to_numpy() == pytest.approx([96.6] * 5, abs=1e-3)
    assert a.loc[222779, "n_own_weight_hours"] == 5
    assert a.loc[222779, "n_imputed_weight_hours"] == 0
    # 285750: its own 64.9 kg, not a donor's 81.1 kg
    assert w.loc[285750].to_numpy() == pytest.approx([64.9] * 5, abs=0.05)
    # 210164 keeps its 263 kg: the 157 cm that would make it implausible is charted two
    # months later, in another stay
    assert a.loc[210164, "n_weight_implausible"] == 0
    assert not a["weight_imputed_implausible"].any()


def test_specimens_units_and_semantics(demo, preset):
    res = demo["first_vitals"]
    a = res.stays.set_index(schema.STAY_ID)
    mbp = res.trajectories.set_index([schema.STAY_ID, "t"])["MeanBP"]
    # the MAP check compares a mean only with its own device's pressures of the same
    # minute: over whole stays 30 MAPs in 21 stays (before: 142 in 43, 60 of them < 65
    # mmHg, judged against the other device or readings up to 2 h old)
    assert a["n_map_outside_range"].sum() == 30 and (a["n_map_outside_range"] > 0).sum() == 21
    # 220671: the cuff's MAP of 37 charted alone at 01:00 stays (before: deleted below the
    # cuff's diastolic 42 of 00:23): hour 2 is 61.3, not 85.7
    assert mbp.loc[(220671, 2)] == pytest.approx(61.33, abs=0.01)
    # 221684: a MAP of 142 charted alone, with no pressure of its device that minute, is not
    # judged: hour 2 is (142 + 60.7) / 2
    assert a.loc[221684, "n_map_outside_range"] == 0
    assert mbp.loc[(221684, 2)] == pytest.approx(101.33, abs=0.01)
    # 217992: arterial MAPs of 3 mmHg charted alone (a transducer zeroed) are below 5 mmHg:
    # deleted as outliers, not by the check; hour 0 is 65.2, not 34.1, under either preset
    assert a.loc[217992, "n_map_outside_range"] == 0
    assert mbp.loc[(217992, 0)] == pytest.approx(65.2, abs=0.05)
    pm = preset.trajectories.set_index([schema.STAY_ID, "t"])["MeanBP"]
    assert pm.loc[(217992, 0)] == pytest.approx(68.0)  # before: 24.7 = (68 + 3 + 3) / 3
    # venous and mixed-venous blood gases: their PaO2 / PaCO2 / pH are not arterial;
    # counted over whole stays (the hourly windows alone hold 33 of them); 272047, whose
    # max SOFA they lower from 6 to 4, shows its 3 (before: 0, counted in the hourly window)
    assert a["n_venous_gas_rows"].sum() == 162 and (a["n_venous_gas_rows"] > 0).sum() == 24
    assert a.loc[272047, "n_venous_gas_rows"] == 3 and a.loc[272047, "max_sofa"] == 4
    # 290513's only culture is an MRSA screen: no suspected infection
    assert a.loc[290513, "n_screen_cultures"] == 1
    assert a.loc[290513, "infection_status"] != "onset"
    # the preset applies none of the three rules (AI-Clinician does not): the irrigant is not
    # read (counted 0), the venous gases kept, 290513's MRSA screen a culture
    p = preset.stays.set_index(schema.STAY_ID)
    assert p["n_urine_irrigant_rows"].sum() == 0 and a["n_urine_irrigant_rows"].sum() == 0
    assert p["n_venous_gas_rows"].sum() == 0 and p.loc[272047, "max_sofa"] == 6
    assert p.loc[290513, "infection_status"] == "onset" and p.loc[290513, "in_cohort"]
    # the SOFA reads the vasopressor rate to 3 decimals: 265505's norepinephrine 0.100104 and
    # 298685's dopamine 10.008 (x 0.01) score 3 cardiovascular points, not 4
    assert p.loc[265505, "max_sofa"] == 7 and p.loc[298685, "max_sofa"] == 8
    assert "cardiovascular=3" in p.loc[298685, "sofa_organs"]


def test_preset_irrigant_subtracted_when_switched_on():
    """GU irrigant in (227488) is subtracted from the urine output read by sofa:
    ai_clinician when urine_irrigant is subtract; the tube-feed residual rows are counted
    where they are left out."""
    from dataclasses import replace
    opts = replace(PRESETS["ai_clinician"], urine_irrigant="subtract", tf_residual="exclude")
    a = extract_mimic3(DEMO, options=opts).stays.set_index(schema.STAY_ID)
    assert a["n_urine_irrigant_rows"].sum() == 97
    assert a["n_urine_tf_residual_rows"].sum() == 142  # of 143 rows, one without a stay


def test_docs_consort_table_equals_the_extraction_counts():
    """docs/how-to/mimic3.md's CONSORT table of the demo gives the counts asserted above, per
    anchor and preset (a cohort change that moves them fails here until the page follows)."""
    page = (ROOT / "docs" / "how-to" / "mimic3.md").read_text()
    head = "| step | default, `first_vitals` | default, `intime` | `ai_clinician`, `first_vitals` |"
    lines = page[page.index(head):].split("\n\n")[0].splitlines()[2:]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    n = {col: [int(row[col + 1].replace("*", "").split()[0]) for row in cells]
         for col in range(4)}
    assert [row[0] for row in cells] == list(STEPS)
    assert n[0] == COUNTS["first_vitals"] and n[1] == COUNTS["intime"]
    assert n[2] == COUNTS_AI_CLINICIAN["first_vitals"] and n[3] == COUNTS_AI_CLINICIAN["intime"]
    # excluded in brackets: the drop from the step before
    for col in range(4):
        shown = [int(row[col + 1].split("(")[1].rstrip(")")) if "(" in row[col + 1] else 0
                 for row in cells]
        assert shown == [0] + [a - b for a, b in zip(n[col], n[col][1:], strict=False)]
