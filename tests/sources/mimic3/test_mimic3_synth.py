"""The MIMIC-III-shaped table generator of the benchmarks, at its smallest scale: its tables
have full MIMIC-III's proportions, and the extraction gives the cohort and hourly values the
generator puts in by construction (from gzip CSV and from Parquet alike)."""

from __future__ import annotations

import importlib.util
import sys

import duckdb
import numpy as np
import pandas as pd
import pytest
from helpers.paths import ROOT

from twinfalsify.sources.mimic3 import extract_mimic3

SCALE = 0.001  # 62 ICU stays


def _synth():
    spec = importlib.util.spec_from_file_location("mimic3_synth",
                                                  ROOT / "benchmarks" / "mimic3_synth.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["mimic3_synth"] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def synth():
    return _synth()


def _written(synth, tmp_path_factory, shape: str):
    """(folder, stays) of the tables of ``shape`` at SCALE."""
    folder = tmp_path_factory.mktemp(f"{shape}-synth")
    return folder, synth.write_mimic3(folder, SCALE, threads=1, shape=synth.SHAPES[shape])


@pytest.fixture(scope="module")
def tables(synth, tmp_path_factory):
    return _written(synth, tmp_path_factory, "mimic3")


def test_tables_have_full_mimic_proportions(synth, tables):
    folder, stays = tables
    n = len(stays)
    assert n == round(synth.FULL_STAYS * SCALE)
    names = sorted(p.name for p in folder.glob("*.csv.gz"))
    assert names == sorted(f"{t}.csv.gz" for t in synth.TABLES)  # as PhysioNet ships them
    con = duckdb.connect()
    for t in synth.TABLES:
        if t in ("PATIENTS", "ADMISSIONS"):  # one patient and admission per stay
            continue
        rd = f"read_csv('{folder / (t + '.csv.gz')}', header = true, all_varchar = true)"
        cols = [r[0] for r in con.execute(f"DESCRIBE SELECT * FROM {rd}").fetchall()]
        assert cols == [c.upper() for c in cols], t
        rows = con.execute(f"SELECT count(*) FROM {rd}").fetchone()[0]
        want = synth.FULL_ROWS[t] * n / synth.FULL_STAYS
        assert abs(rows - want) <= 0.02 * want + 5, (t, rows, want)
    # most CHARTEVENTS rows are items the extraction does not read (~ 15 % in MIMIC-III)
    from twinfalsify.sources.mimic3 import hourly

    items = hourly.item_map()
    kept = tuple(items.loc[items["source"] == "chartevents", "itemid"])
    share = con.execute(
        f"SELECT avg(CAST(CAST(ITEMID AS BIGINT) IN {kept} AS DOUBLE)) FROM "
        f"read_csv('{folder / 'CHARTEVENTS.csv.gz'}', header = true, all_varchar = true)"
    ).fetchone()[0]
    assert 0.08 < share < 0.2
    assert 0.45 < (stays["cv"]).mean() < 0.8  # CareVue-era majority


def test_extraction_gives_the_cohort_and_values_built_in(synth, tables):
    folder, stays = tables
    res = extract_mimic3(folder, threads=1)
    want = synth.expected_cohort(stays)
    assert 0 < len(want) < len(stays)
    traj = res.trajectories
    assert sorted(traj["stay_id"].unique()) == sorted(want)
    c = res.consort.set_index("step")["n_stays"]
    assert c["adult"] == int((~stays["neonate"]).sum())
    assert c["suspected_infection"] == int(stays["sepsis"].sum())
    hr = traj[["stay_id", "t", "HR"]].merge(synth.expected_hr(stays), on=["stay_id", "t"],
                                            suffixes=("", "_built"))
    assert len(hr) == len(traj)
    np.testing.assert_array_equal(hr["HR"], hr["HR_built"])
    assert (traj["Temp_C"].round(6) == 37.0).all()  # 98.6 F charted every 4 h, held


def test_parquet_extracts_like_csv(synth, tables, tmp_path):
    folder, stays = tables
    synth.write_mimic3(tmp_path, SCALE, fmt="parquet", threads=1)
    assert sorted(p.name for p in tmp_path.glob("*.parquet")) == sorted(
        f"{t}.parquet" for t in synth.TABLES)
    a = extract_mimic3(folder, threads=1).trajectories
    b = extract_mimic3(tmp_path, threads=1).trajectories
    pd.testing.assert_frame_equal(a, b)


@pytest.fixture(scope="module")
def tables4(synth, tmp_path_factory):
    return _written(synth, tmp_path_factory, "mimic4")


def test_mimic4_shape_has_mimic4s_layout_and_proportions(synth, tables4):
    """Files where MIMIC-IV keeps them, with every column the MIMIC-IV layout reads, at
    MIMIC-IV v2.2's rows per ICU stay; no CareVue, no neonates; some labs lack hadm_id."""
    from twinfalsify.sources.mimic4 import FILES, MIMIC4

    folder, stays = tables4
    n = len(stays)
    assert n == round(synth.MIMIC4_ROWS["ICUSTAYS"] * SCALE)
    assert not stays["cv"].any() and not stays["neonate"].any()
    con = duckdb.connect()
    for view, stems in FILES.items():
        if not stems:  # INPUTEVENTS_CV: no MIMIC-IV table
            assert not list(folder.rglob("*inputevents_cv*"))
            continue
        path = folder / f"{stems[0]}.csv.gz"
        rd = f"read_csv('{path}', header = true, all_varchar = true)"
        cols = [r[0] for r in con.execute(f"DESCRIBE SELECT * FROM {rd}").fetchall()]
        assert cols == [c.lower() for c in cols] and set(MIMIC4.columns[view]) <= set(cols)
        rows = con.execute(f"SELECT count(*) FROM {rd}").fetchone()[0]
        want = synth.MIMIC4_ROWS[view] * n / synth.MIMIC4_ROWS["ICUSTAYS"]
        assert abs(rows - want) <= 0.02 * want + 5, (view, rows, want)
    no_hadm = con.execute(
        "SELECT avg(CAST(hadm_id IS NULL AS DOUBLE)) FROM "
        f"read_csv('{folder / 'hosp' / 'labevents.csv.gz'}', header = true)").fetchone()[0]
    assert 0.01 < no_hadm < 0.03


def test_mimic4_extraction_gives_the_cohort_and_values_built_in(synth, tables4):
    """The MIMIC-IV source on the MIMIC-IV-shaped tables: exactly the built-in cohort and
    hourly heart rates (lab rows without hadm_id linked by patient and time)."""
    from twinfalsify.sources.mimic4 import extract_mimic4

    folder, stays = tables4
    res = extract_mimic4(folder, threads=1)
    want = synth.expected_cohort(stays)
    traj = res.trajectories
    assert 0 < len(want) < len(stays)
    assert sorted(traj["stay_id"].unique()) == sorted(want)
    assert res.stays["n_labs_linked_by_time"].sum() > 0  # the labs without hadm_id
    hr = traj[["stay_id", "t", "HR"]].merge(synth.expected_hr(stays), on=["stay_id", "t"],
                                            suffixes=("", "_built"))
    assert len(hr) == len(traj)
    np.testing.assert_array_equal(hr["HR"], hr["HR_built"])
