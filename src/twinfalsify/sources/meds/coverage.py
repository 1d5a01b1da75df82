"""The MIMIC-IV item map against a MIMIC-IV dataset in MEDS: per concept (trajectory feature,
IV fluid, vasopressor), the rows the ``mimic4`` preset reads, the map's items the dataset never
charts, and the items the public MIMIC-IV concept code uses for the concept (``itemmap``'s
``mimic4_concept``) that the dataset charts and the map does not read."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from twinfalsify.sources.mimic3.itemmap import ITEM_LISTS

from .codemap import mimic4_code_map, split_unit
from .cohort import code_counts
from .dataset import connect, open_dataset


def _item(code: str) -> int | None:
    parts = code.split("//")
    return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else None


def coverage(path: str | Path) -> pd.DataFrame:
    """One row per concept: concept, map_items, rows_read, rows_unit_rejected,
    map_items_not_charted, concept_items_not_read (``itemid (rows)``, from the MIMIC-IV
    concept code)."""
    ds = open_dataset(path)
    con = connect(ds)
    try:
        counts = code_counts(con)
    finally:
        con.close()
    counts["item"] = counts["code"].map(_item)
    counts["prefix"] = counts["code"].str.split("//").str[0]
    cmap = mimic4_code_map()
    concept = {lst.name: lst for lst in ITEM_LISTS}
    rows = []
    feats = cmap.features.assign(item=cmap.features["code"].map(_item))
    for feature, g in feats.groupby("feature", sort=False):
        lab = counts[counts["prefix"] == "LAB"]
        units = {int(i): set(u) for i, u in zip(g["item"], g["units"], strict=True)}
        hit = lab[lab["item"].isin(units)]
        ok = [split_unit(c)[1] in units[int(i)] for c, i in zip(hit["code"], hit["item"],
                                                                strict=True)]
        lst = next((x for x in ITEM_LISTS if x.rows == f"feature == '{feature}'"), None)
        rows.append(_row(feature, set(units), hit, ok, lst, lab))
    for action, lst_name in (("fluid", "IV fluids"), ("vasopressor", "vasopressors")):
        items = set(cmap.infusions.loc[cmap.infusions["action"] == action, "item"])
        starts = counts[counts["prefix"] == "INFUSION_START"]
        hit = starts[starts["item"].isin(items)]
        rows.append(_row(action, items, hit, [True] * len(hit), concept[lst_name], starts))
    return pd.DataFrame(rows)


def _row(name: str, items: set[int], hit: pd.DataFrame, ok: list[bool], lst, pool
         ) -> dict:
    ok_s = pd.Series(ok, index=hit.index, dtype=bool)
    charted = set(hit["item"].astype(int))
    extra = [] if lst is None else [i for i in lst.mimic4_concept if i not in items]
    extra_rows = pool[pool["item"].isin(extra)].groupby("item")["n"].sum()
    return {"concept": name, "map_items": len(items),
            "rows_read": int(hit.loc[ok_s, "n"].sum()),
            "rows_unit_rejected": int(hit.loc[~ok_s, "n"].sum()),
            "map_items_not_charted": ", ".join(str(i) for i in sorted(items - charted)),
            "concept_items_not_read": ", ".join(f"{int(i)} ({int(n)})"
                                                for i, n in extra_rows.items())}
