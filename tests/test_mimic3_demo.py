"""The extraction on the whole open MIMIC-III Clinical Database Demo v1.4 (100 patients,
ODbL), when ../shared/data/mimic-iii-demo exists; skipped otherwise."""

from __future__ import annotations

from pathlib import Path

import pytest

from twinfalsify import schema
from twinfalsify.sources.mimic3 import extract_mimic3


def _shared() -> Path:
    p = Path(__file__).resolve().parents[1].parent / "shared"
    return p if p.is_dir() else Path("/work/shared")


DEMO = _shared() / "data" / "mimic-iii-demo"


@pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                    reason=f"MIMIC-III demo not present at {DEMO}")
def test_whole_demo():
    res = extract_mimic3(DEMO)
    c = res.consort.set_index("step")["n_stays"]
    # 136 ICU stays of 100 patients in the demo (ICUSTAYS.csv has 136 rows)
    assert c["all_icu_stays"] == 136
    assert (c.diff().dropna() <= 0).all()
    assert (res.consort["n_excluded"] >= 0).all()
    # documented in docs/mimic3.md: 27 stays in the final demo cohort
    assert c["vitals_complete"] == 27
    t = schema.validate_trajectories(res.trajectories)
    assert t[schema.STAY_ID].nunique() == 27
    # plausible clinical ranges (the contract validation checks the wider plausibility ranges)
    assert t["HR"].between(30, 200).all() and t["Temp_C"].between(32, 42).all()
    assert t["age"].min() >= 18 and t["weight"].between(30, 250).all()
    assert t["iv_fluid"].between(0, 5000).all() and t["vasopressor"].between(0, 5).all()
    m = res.missingness
    assert set(m["feature"]) == set(schema.FEATURES) and m["t"].nunique() == schema.T_MAX + 1
    assert m["share_missing_raw"].between(0, 1).all()
