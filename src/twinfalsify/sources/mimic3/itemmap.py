"""Every item list the extraction reads, in one place: the package data table holding it, the
rows of that table, the MIMIC table it is read from, where the list comes from, and the item
ids the public MIMIC-IV concept code (MIT-LCP mimic-code, ``mimic-iv/concepts``) uses for the
same quantity, so that a MIMIC-IV item the extraction would miss is found by a test.

The item ids themselves live only in the data tables (``twinfalsify/data/mimic3/*.csv``);
this module names them. ``MIMIC4_ONLY`` lists the items only MIMIC-IV charts (MIMIC-III's
MetaVision never does) with the first release that has them; ``coverage`` gives the table of
docs/how-to/mimic4.md ("Item coverage per release").
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from .tables import INTUBATED_VERBAL, data_table

RELEASES = ("MIMIC-III v1.4", "MIMIC-IV v2.0", "MIMIC-IV v2.2", "MIMIC-IV v3.0", "MIMIC-IV v3.1")
MIMIC4_RELEASES = RELEASES[1:]


@dataclass(frozen=True)
class ItemList:
    """One list of item ids the extraction reads.

    ``table``: the data table; ``rows``: a pandas query selecting its rows (``None``: all);
    ``read_from``: the MIMIC-III view the ids select rows of; ``source``: where the list comes
    from; ``mimic4_concept``: the item ids of the MIMIC-IV concept code for the same quantity
    (empty where the concept code has none), each of which the list must hold."""

    name: str
    table: str
    rows: str | None
    read_from: str
    source: str
    mimic4_concept: tuple[int, ...] = ()

    def itemids(self) -> tuple[int, ...]:
        """The list's item ids, as the data table holds them."""
        df = data_table(self.table)
        if self.rows is not None:
            df = df.query(self.rows)
        return tuple(sorted(set(pd.to_numeric(df["itemid"]).astype("int64"))))


AIC = "AI-Clinician (Komorowski et al. 2018) reference matrices"
MC4 = "MIT-LCP mimic-code mimic-iv/concepts/"


def _feature(name: str, feature: str, source: str, concept: tuple[int, ...] = (),
             read_from: str = "CHARTEVENTS, LABEVENTS") -> ItemList:
    return ItemList(name, "items.csv", f"feature == '{feature}'", read_from, source, concept)


ITEM_LISTS: tuple[ItemList, ...] = (
    _feature("heart rate", "HR", f"{AIC}; {MC4}measurement/vitalsign.sql", (220045,)),
    _feature("systolic BP", "SysBP", f"{AIC} + 220050; {MC4}measurement/vitalsign.sql",
             (220179, 220050, 225309)),
    _feature("mean BP", "MeanBP", f"{AIC}; {MC4}measurement/vitalsign.sql",
             (220052, 220181, 225312)),
    _feature("diastolic BP", "DiaBP", f"{AIC}; {MC4}measurement/vitalsign.sql",
             (220180, 220051, 225310)),
    _feature("respiratory rate", "RR", f"{AIC}; {MC4}measurement/vitalsign.sql",
             (220210, 224690)),
    _feature("temperature", "Temp_C", f"{AIC}; {MC4}measurement/vitalsign.sql",
             (223761, 223762)),
    _feature("weight", "weight", f"{AIC}; {MC4}demographics/weight_durations.sql",
             (226512, 224639)),
    ItemList("height", "heights.csv", None, "CHARTEVENTS",
             f"project (BMI check); {MC4}measurement/height.sql", (226707, 226730)),
    _feature("glucose", "Glucose", f"{AIC}; {MC4}measurement/vitalsign.sql (fingerstick)",
             (225664, 220621, 226537)),
    *(_feature(f.lower(), f, f"{AIC}; {MC4}measurement/bg.sql, chemistry.sql")
      for f in ("Potassium", "Sodium", "Chloride", "Calcium", "HCO3")),
    _feature("PaO2", "paO2", f"{AIC}; {MC4}measurement/bg.sql", (50821,)),
    _feature("PaCO2", "paCO2", f"{AIC}; {MC4}measurement/bg.sql", (50818,)),
    _feature("arterial pH", "Arterial_pH", f"{AIC}; {MC4}measurement/bg.sql", (50820,)),
    _feature("FiO2", "sofa_fio2", f"{AIC} (chart FiO2); {MC4}measurement/bg.sql (chart FiO2 "
             "223835 and the blood-gas FiO2 50816, switch fio2_lab)", (223835, 50816)),
    _feature("platelets", "sofa_platelets", f"{AIC}; {MC4}measurement/complete_blood_count.sql",
             (51265,)),
    _feature("bilirubin", "sofa_bilirubin", f"{AIC}; {MC4}measurement/enzyme.sql", (50885,)),
    _feature("creatinine", "sofa_creatinine", f"{AIC}; {MC4}measurement/chemistry.sql",
             (50912,)),
    _feature("GCS total (CareVue)", "sofa_gcs", AIC),
    _feature("GCS components", "sofa_gcs_component", f"{MC4}measurement/gcs.sql",
             (220739, 223900, 223901)),
    _feature("RASS", "sofa_rass", "AI-Clinician (GCS estimated from RASS)"),
    ItemList("vasopressors", "vasopressors.csv", None, "INPUTEVENTS_MV, INPUTEVENTS_CV",
             f"AI-Clinician vaso_mv / vaso_cv + MIMIC-IV phenylephrine items + MIMIC-IV "
             f"angiotensin II (read, not converted); {MC4}medication/",
             (221906, 221289, 221749, 222315, 221662)),
    ItemList("IV fluids", "fluids.csv", None, "INPUTEVENTS_MV, INPUTEVENTS_CV",
             "AI-Clinician fluid_mv / fluid_cv"),
    ItemList("urine output", "urine.csv", None, "OUTPUTEVENTS",
             f"AI-Clinician UO query (227510 TF Residual: switch tf_residual); "
             f"{MC4}measurement/urine_output.sql (227488 GU irrigant in: switch "
             "urine_irrigant)",
             (226559, 226560, 226561, 226584, 226563, 226564, 226565, 226567, 226557, 226558,
              227489)),
    ItemList("cultures (chart items)", "cultures.csv", None, "CHARTEVENTS",
             "AI-Clinician culture query"),
    ItemList("blood-pressure devices (MAP check)", "bp_devices.csv", None, "CHARTEVENTS",
             "project: the device of each pressure item (D_ITEMS labels), so that a MAP is "
             "checked against its own device's systolic and diastolic"),
    ItemList("blood-gas specimen", "specimens.csv", None, "LABEVENTS",
             f"{MC4}measurement/bg.sql (52033); MIMIC-III 50800"),
)

# Items only MIMIC-IV charts, with the first release that has them and the rows counted where
# known (MIMIC-IV v2.0 inputevents).
MIMIC4_ONLY: dict[int, tuple[str, str]] = {
    229630: ("MIMIC-IV v2.0", "phenylephrine; 35,766 infusion rows in v2.0"),
    229632: ("MIMIC-IV v2.0", "phenylephrine; 7,347 infusion rows in v2.0"),
    229631: ("MIMIC-IV v3.1", "phenylephrine"),
    229709: ("MIMIC-IV v2.0", "angiotensin II; read, not converted (with 229764: 236 rows "
                              "in v2.0)"),
    229764: ("MIMIC-IV v2.0", "angiotensin II; read, not converted"),
    52033: ("MIMIC-IV v2.0", "blood-gas specimen type (MIMIC-III: 50800)"),
}
# MIMIC-III-only items besides the CareVue ids (< 220000, not labs): its blood-gas specimen
# item (MIMIC-IV charts the specimen type as 52033).
MIMIC3_ONLY: frozenset[int] = frozenset({50800})


def all_itemids() -> set[int]:
    """Every item id any list names, plus the intubated-verbal GCS items of the code."""
    ids = {int(i) for i, _ in INTUBATED_VERBAL}
    for lst in ITEM_LISTS:
        ids |= set(lst.itemids())
    return ids


def releases_of(itemid: int) -> tuple[str, ...]:
    """The releases whose tables can hold ``itemid``: CareVue ids (< 220000, not labs) only
    MIMIC-III; ``MIMIC4_ONLY`` ids from their first release on; the rest all."""
    if itemid in MIMIC3_ONLY:
        return RELEASES[:1]
    if itemid in MIMIC4_ONLY:
        return RELEASES[RELEASES.index(MIMIC4_ONLY[itemid][0]):]
    if itemid < 220000 and not 50000 <= itemid < 60000:
        return RELEASES[:1]
    return RELEASES


def coverage() -> pd.DataFrame:
    """Per item list: how many of its ids each release can chart, and the MIMIC-IV-only ids."""
    rows = []
    for lst in ITEM_LISTS:
        ids = lst.itemids()
        row = {"list": lst.name, "source": lst.source}
        for rel in RELEASES:
            row[rel] = sum(rel in releases_of(i) for i in ids)
        row["MIMIC-IV only"] = ", ".join(str(i) for i in ids if i in MIMIC4_ONLY)
        rows.append(row)
    return pd.DataFrame(rows)
