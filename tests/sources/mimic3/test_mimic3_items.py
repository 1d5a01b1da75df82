"""The item map: every item list the extraction reads is named once, with its source, and holds
every item id the public MIMIC-IV concept code uses for the same quantity."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pandas as pd
import pytest

from twinfalsify.sources.mimic3 import doses, itemmap
from twinfalsify.sources.mimic3.tables import data_table, read_items


@pytest.mark.parametrize("lst", itemmap.ITEM_LISTS, ids=lambda lst: lst.name)
def test_each_list_holds_the_mimic4_concept_items(lst):
    assert lst.source
    missing = set(lst.mimic4_concept) - set(lst.itemids())
    assert not missing, f"{lst.name}: MIMIC-IV concept item(s) {sorted(missing)} not read"


def test_the_map_names_every_item_the_extraction_can_read():
    # staging keeps exactly the rows of the items some data table names: the map must name
    # every one of them (one place), and name no item no table holds
    staged = set(read_items()["CHARTEVENTS"])
    assert itemmap.all_itemids() == staged
    folder = resources.files("twinfalsify") / "data" / "mimic3"
    with_items = {f.name for f in folder.iterdir()
                  if f.name.endswith(".csv") and "itemid" in data_table(f.name).columns}
    assert with_items == {lst.table for lst in itemmap.ITEM_LISTS}


def test_mimic4_phenylephrine_items_are_read_as_phenylephrine():
    # 229630, 229632 (MIMIC-IV v2.0 on) and 229631 (v3.1): 17.5 % of MIMIC-IV's phenylephrine
    # infusion rows; before, only 221749 was read and these rows were dropped (NaN)
    ev = pd.DataFrame({"itemid": [221749, 229630, 229632, 229631, 229630],
                       "rate": [1.0, 1.0, 2.0, 0.5, 80.0],
                       "rateuom": ["mcg/kg/min"] * 4 + ["mcg/min"]})
    ne = doses.norepinephrine_equivalent(ev, "mv").to_numpy()
    np.testing.assert_allclose(ne, [0.45, 0.45, 0.9, 0.225, 0.45])
    vaso = set(itemmap.ITEM_LISTS[[x.name for x in itemmap.ITEM_LISTS].index(
        "vasopressors")].itemids())
    assert {229630, 229631, 229632} <= vaso


def test_coverage_table_per_release():
    cov = itemmap.coverage().set_index("list")
    assert list(cov.columns[1:1 + len(itemmap.RELEASES)]) == list(itemmap.RELEASES)
    v = cov.loc["vasopressors"]
    # the three MIMIC-IV-only phenylephrine items: none in MIMIC-III, two in v2.0, three in 3.1
    assert v["MIMIC-IV v3.1"] - v["MIMIC-IV v2.0"] == 1
    # ... and the two angiotensin II items (read, not converted)
    assert v["MIMIC-IV only"] == "229630, 229631, 229632, 229709, 229764"
    assert itemmap.releases_of(229709) == itemmap.MIMIC4_RELEASES
    assert itemmap.releases_of(50816) == itemmap.RELEASES  # the blood-gas FiO2: both
    assert itemmap.releases_of(229631) == ("MIMIC-IV v3.1",)
    assert itemmap.releases_of(211) == ("MIMIC-III v1.4",)  # CareVue heart rate
    assert itemmap.releases_of(50821) == itemmap.RELEASES  # labs: both
    # every MIMIC-IV release reads at least the MIMIC-IV concept items of each list
    for lst in itemmap.ITEM_LISTS:
        assert cov.loc[lst.name, "MIMIC-IV v2.0"] >= len(lst.mimic4_concept), lst.name


def test_angiotensin_ii_is_read_not_converted_and_counted():
    """MIMIC-IV's angiotensin II rows (229709, 229764; ng/kg/min) are read by the input reader
    as vasopressor rows, give no norepinephrine equivalent (no factor on AI-Clinician's
    scale), so no dose; the audit counts them (n_vaso_rows_not_converted) by
    ``doses.not_converted_items``, apart from rows in an unknown unit."""
    import duckdb

    from twinfalsify.sources.mimic3.cohort import _inputs
    t = pd.Timestamp("2150-01-01 10:00")
    mv = pd.DataFrame({
        "ICUSTAY_ID": "1", "ITEMID": ["229709", "229764", "221906"],
        "STARTTIME": str(t), "ENDTIME": str(t + pd.Timedelta(hours=2)),
        "AMOUNT": "1", "RATE": ["20", "10", "0.1"],
        "RATEUOM": ["ng/kg/min", "ng/kg/min", "mcg/kg/min"],
        "STATUSDESCRIPTION": "FinishedRunning",
        "PATIENTWEIGHT": "70"})
    cv = pd.DataFrame({c: pd.Series(dtype=str) for c in
                       ("ICUSTAY_ID", "ITEMID", "CHARTTIME", "AMOUNT", "RATE", "RATEUOM")})
    con = duckdb.connect()
    con.register("INPUTEVENTS_MV", mv)
    con.register("INPUTEVENTS_CV", cv)
    win = pd.Series([t], index=[1])
    _, _, mv_v, _ = _inputs(con, [1], win, win + pd.Timedelta(hours=4))
    assert sorted(mv_v["itemid"]) == [221906, 229709, 229764]  # read
    assert doses.not_converted_items() == {229709, 229764}
    ne = doses.norepinephrine_equivalent(mv_v, "mv")
    assert ne[mv_v["itemid"] != 221906].isna().all()
    # the action is the norepinephrine running beside it, not the angiotensin rate
    vaso = doses.hourly_vasopressor(win, mv_v, mv_v.iloc[:0], 1)
    np.testing.assert_allclose(vaso.to_numpy(), [0.1, 0.1])


def test_tf_residual_and_blood_gas_fio2_are_in_the_item_lists():
    lists = {lst.name: set(lst.itemids()) for lst in itemmap.ITEM_LISTS}
    assert 50816 in lists["FiO2"] and 223835 in lists["FiO2"]
    assert {227510, 227488} <= lists["urine output"]
    assert {229709, 229764} <= lists["vasopressors"]
