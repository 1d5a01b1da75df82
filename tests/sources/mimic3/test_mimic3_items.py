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
    assert v["MIMIC-IV only"] == "229630, 229631, 229632"
    assert itemmap.releases_of(229631) == ("MIMIC-IV v3.1",)
    assert itemmap.releases_of(211) == ("MIMIC-III v1.4",)  # CareVue heart rate
    assert itemmap.releases_of(50821) == itemmap.RELEASES  # labs: both
    # every MIMIC-IV release reads at least the MIMIC-IV concept items of each list
    for lst in itemmap.ITEM_LISTS:
        assert cov.loc[lst.name, "MIMIC-IV v2.0"] >= len(lst.mimic4_concept), lst.name
