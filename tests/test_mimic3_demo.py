"""The extraction on the whole open MIMIC-III Clinical Database Demo v1.4 (100 patients,
ODbL), when ../shared/data/mimic-iii-demo exists; skipped otherwise."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from conftest import shared_dir

from twinfalsify import schema
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.hourly import LABS
from twinfalsify.sources.mimic3.options import PRESETS


def _shared() -> Path:
    p = Path(__file__).resolve().parents[1].parent / "shared"
    return shared_dir() or p


DEMO = _shared() / "data" / "mimic-iii-demo"
# two whole-demo extractions: ~8 s on an idle machine, more under load
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                                 reason=f"MIMIC-III demo not present at {DEMO}")]
# documented in docs/how-to/mimic3.md (CONSORT of the demo under each anchor)
COUNTS = {
    "intime": [136, 135, 86, 73, 73, 71, 68, 68, 68, 66, 21, 21, 21],
    "first_vitals": [136, 135, 86, 73, 73, 71, 68, 66, 66, 64, 62, 62, 62],
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
