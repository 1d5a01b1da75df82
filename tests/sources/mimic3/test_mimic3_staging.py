"""Staging of the large MIMIC-III tables (``tables.stage``): the extraction gives identical
outputs with and without it (the open demo, both cohort variants; the fixture), the staged
copy keeps exactly the rows some query can read, a bad ITEMID still fails with one line, the
temporary folder is removed, and DuckDB's memory limit / temporary folder come from config
with a clear error for a bad value."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest
from helpers.paths import FIXTURES, SRC

from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.options import PRESETS
from twinfalsify.sources.mimic3.tables import connect, read_items, stage

FIX = FIXTURES / "mimic3"
OUTPUTS = ("trajectories", "consort", "missingness", "anchors", "imputed", "stays")


def _demo() -> Path | None:
    from helpers.paths import shared_dir

    d = shared_dir()
    demo = d / "data" / "mimic-iii-demo" if d else None
    return demo if demo and (demo / "CHARTEVENTS.csv.gz").is_file() else None


def _same(a, b) -> None:
    for f in OUTPUTS:
        pd.testing.assert_frame_equal(getattr(a, f), getattr(b, f), obj=f)


@pytest.mark.parametrize("fixture", [FIX, FIX.with_name("mimic3-patients")])
def test_staged_extraction_equals_unstaged_on_the_fixture(tmp_path, fixture):
    # mimic3-patients: heights (read only for the weights' BMI check) must be staged too
    for variant in PRESETS:
        a = extract_mimic3(fixture, options=PRESETS[variant], stage=False)
        b = extract_mimic3(fixture, options=PRESETS[variant], temp_directory=tmp_path)
        _same(a, b)
    assert list(tmp_path.iterdir()) == []  # the staging folder is removed


@pytest.mark.slow
@pytest.mark.skipif(_demo() is None, reason="MIMIC-III demo not present")
@pytest.mark.parametrize("variant", list(PRESETS))
def test_staged_extraction_equals_unstaged_on_the_demo(variant):
    a = extract_mimic3(_demo(), options=PRESETS[variant], threads=2, stage=False)
    b = extract_mimic3(_demo(), options=PRESETS[variant], threads=2)
    assert len(a.trajectories) > 0
    _same(a, b)


def test_stage_keeps_exactly_the_rows_read(tmp_path):
    d = tmp_path / "in"
    shutil.copytree(FIX, d)
    ce = pd.read_csv(d / "CHARTEVENTS.csv", dtype=str)
    unread = ce.iloc[[0]].assign(ITEMID="220277")  # SpO2: no query reads it
    ce = pd.concat([ce, unread], ignore_index=True)
    ce.to_csv(d / "CHARTEVENTS.csv", index=False)
    con = connect(d)
    rows = stage(con, tmp_path)
    # every itemid of every package data table (a table added later included) is kept
    data = SRC / "twinfalsify" / "data" / "mimic3"
    items = {723, 223900}  # intubated verbal GCS, listed in the code
    for f in data.glob("*.csv"):
        df = pd.read_csv(f, comment="#")
        if "itemid" in df:
            items |= set(pd.to_numeric(df["itemid"], errors="coerce").dropna().astype(int))
    assert set(read_items()["CHARTEVENTS"]) == items
    want = int(ce["ITEMID"].astype(int).isin(items).sum())
    assert rows["CHARTEVENTS"] == want == len(ce) - 1
    staged = con.execute('SELECT * FROM "CHARTEVENTS" LIMIT 0').df().columns
    assert list(staged) == ["SUBJECT_ID", "HADM_ID", "ICUSTAY_ID", "ITEMID", "CHARTTIME",
                            "VALUE", "VALUENUM", "ERROR"]
    con.close()


def test_a_bad_itemid_still_fails_with_one_line(tmp_path):
    d = tmp_path / "in"
    shutil.copytree(FIX, d)
    ce = pd.read_csv(d / "CHARTEVENTS.csv", dtype=str)
    ce.loc[0, "ITEMID"] = "abc"
    ce.to_csv(d / "CHARTEVENTS.csv", index=False)
    for stage_tables in (False, True):
        with pytest.raises(ContractError, match="query failed"):
            extract_mimic3(d, stage=stage_tables)


def test_duckdb_settings_from_config(tmp_path):
    con = connect(FIX, memory_limit="1GB", temp_directory=tmp_path / "spill")
    limit = con.execute("SELECT current_setting('memory_limit')").fetchone()[0]
    assert limit.replace(" ", "").upper() in ("1GB", "953.6MIB", "0.9GIB")
    assert con.execute("SELECT current_setting('temp_directory')").fetchone()[0] == str(
        tmp_path / "spill")
    con.close()
    with pytest.raises(ContractError, match="source.mimic3.memory_limit"):
        connect(FIX, memory_limit="lots")
