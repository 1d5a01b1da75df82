"""The MEDS generator of the size benchmark (benchmarks/meds_synth.py) at a tiny scale: its
folder is a MEDS dataset the ``meds`` source opens, every code the generator writes for a
trajectory feature is read in its unit, and the extraction gives exactly the cohort, hourly
heart rates and doses the generator builds in."""

from __future__ import annotations

import importlib.util
import json
import sys

import duckdb
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from helpers.paths import ROOT  # noqa: E402

from twinfalsify.sources.meds import extract_meds, open_dataset

SCALE = 0.0005  # 37 ICU stays, about 240,000 events


@pytest.fixture(scope="module")
def synth():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("meds_synth",
                                                  ROOT / "benchmarks" / "meds_synth.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["meds_synth"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def written(synth, tmp_path_factory):
    folder = tmp_path_factory.mktemp("meds-synth")
    # 20 stays a shard: two shards of stays and one of the patients without an ICU stay
    return folder, synth.write_meds(folder, SCALE, stays_per_shard=20, threads=1)


def test_the_folder_is_a_meds_dataset_with_mimic4_proportions(synth, written):
    folder, stays = written
    ds = open_dataset(folder)
    assert len(ds.shards) == 3 and {"text_value", "unit"} <= ds.columns
    rows = json.loads((folder / "rows.json").read_text())
    assert ds.n_rows == rows["total"]
    n = len(stays)
    per_stay = rows["chartevents"] / n  # MIMIC-IV v2.2: 313.6 M chartevents / 73,181 stays
    full = synth.SHAPE.full_rows["CHARTEVENTS"] / synth.SHAPE.full_stays
    assert 0.7 * full < per_stay < 1.3 * full
    con = duckdb.connect()
    for shard in ds.shards:  # sorted by subject and time, a subject in one shard
        t = con.execute(f"SELECT subject_id, time FROM read_parquet('{shard}')").df()
        assert t.equals(t.sort_values(["subject_id", "time"], na_position="first",
                                      kind="stable").reset_index(drop=True))
    subj = [set(pq.read_table(s, columns=["subject_id"])["subject_id"].to_pylist())
            for s in ds.shards]
    assert not (subj[0] & subj[1]) and not (subj[0] & subj[2]) and not (subj[1] & subj[2])
    splits = pd.read_parquet(folder / "metadata" / "subject_splits.parquet")
    assert set(splits["subject_id"]) == set().union(*subj)
    codes = pd.read_parquet(folder / "metadata" / "codes.parquet")
    assert {"LAB//220045//bpm", "LAB//223761//°F", "LAB//50931//mg/dL",
            "INFUSION_START//221906", "INFUSION_END//225158",
            "SUBJECT_WEIGHT_AT_INFUSION//KG", "ICU_ADMISSION//Medical Intensive Care Unit "
            "(MICU)", "MEDS_BIRTH", "GENDER//F"} <= set(codes["code"])


def test_the_meds_source_gives_the_cohort_and_values_built_in(synth, written):
    folder, stays = written
    c = extract_meds(folder, "mimic4", cohort="icu_admission")
    assert c.consort["n_stays"].iloc[0] == len(stays)
    assert c.units["read"].all()  # every mapped code in a unit the preset accepts
    want = synth.expected_hr(stays).set_index(["stay_id", "t"]).sort_index()
    got = c.trajectories.set_index(["stay_id", "t"]).sort_index()
    assert len(want) > 0 and got.index.equals(want.index)  # the cohort, stay by stay
    np.testing.assert_allclose(got["HR"], want["HR"], rtol=0, atol=1e-9)
    t = want.index.get_level_values("t").to_numpy()
    # NaCl 500 mL from 0.5 h to 3 h; norepinephrine 0.1 ug/kg/min over the same span
    np.testing.assert_allclose(got["iv_fluid"], np.array([100, 200, 200, 0, 0.0])[t],
                               atol=1e-6)
    np.testing.assert_allclose(got["vasopressor"], np.array([0.1, 0.1, 0.1, 0, 0])[t],
                               atol=1e-6)
    assert (got["weight"] == 75.0).all()
