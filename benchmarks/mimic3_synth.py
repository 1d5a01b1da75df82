"""MIMIC-III v1.4- or MIMIC-IV-shaped tables at any fraction of full size (invented values, no
patient data).

``write_mimic3(folder, scale)`` writes the ten tables the extraction reads (PATIENTS,
ADMISSIONS, ICUSTAYS, CHARTEVENTS, LABEVENTS, INPUTEVENTS_MV, INPUTEVENTS_CV, PRESCRIPTIONS,
MICROBIOLOGYEVENTS, OUTPUTEVENTS) as PhysioNet ships them (upper-case ``TABLE.csv.gz``, upper-
case column names, the v1.4 columns the extraction reads plus the identifier / bookkeeping
columns that give a row its real width), or as Parquet. Every table is generated and written
by DuckDB in one streaming ``COPY`` per table, so memory stays flat whatever the scale.

Proportions of full MIMIC-III v1.4 (PhysioNet's published row counts, ``FULL_ROWS``):
61,532 ICU stays, about 62 % CareVue-era (``CAREVUE_SHARE``), 13 % neonates; length of stay
log-normal with median 50 h and mean about 5 days; ``scale`` times each table's full row count,
reached by spreading filler rows over stay-hours (CHARTEVENTS, INPUTEVENTS_*, OUTPUTEVENTS),
admission-hours (LABEVENTS) or stays (PRESCRIPTIONS, MICROBIOLOGYEVENTS). Filler rows carry
real ITEMIDs the extraction does not read, so the share of rows it keeps is realistic: about
13 % of CHARTEVENTS rows (15 % in the open MIMIC-III demo), a third of LABEVENTS and the input
tables.

What each stay holds, by construction (``expected_cohort`` and ``expected_hr`` state the
results the extraction must give):

- ``sepsis`` stays (``SEPSIS_SHARE``): Vancomycin IV at INTIME - 2 h and a culture at
  INTIME - 4 h (suspected infection, onset = the culture), platelets 80 (SOFA >= 2);
  the others have only non-antibiotic prescriptions and cultures from INTIME + 12 h on;
- vitals charted hourly over the whole stay from INTIME + ``delay`` h (delay 0.25, 0.5, 1.5
  or 2.5 h, so the first-complete-vitals anchor is at floor(delay) h); heart rate
  ``60 + i % 40 + h`` at the h-th charting (stay index i), so hour t of the trajectory has
  HR = 60 + i % 40 + t exactly; temperature (F), GCS and FiO2 every 4 h; a weight at
  INTIME + 10 min;
- labs at INTIME - 1 h, INTIME + 3 h and every 12 h of the stay (25 % of values missing);
- MetaVision: an NaCl and a norepinephrine infusion every 8 h; CareVue: NaCl boluses and
  charted Levophed rates; urine output every 2 h;
- neonates (age 0, excluded as not adult) and deaths within 90 days (withdrawal candidates;
  never withdrawn, as their vasopressor rate stays at 0.1 ug/kg/min).

**MIMIC-IV shape** (``shape=MIMIC4``, ``--shape mimic4``): the tables of MIMIC-IV v2.2 in its
own layout (``hosp/`` and ``icu/``, lower-case files and columns, ``stay_id``, ``anchor_age`` /
``anchor_year`` instead of DOB, ``prescriptions.starttime``, no ERROR column, no CareVue table)
at MIMIC-IV v2.2's row counts per ICU stay (``MIMIC4_ROWS``: 73,181 ICU stays, 313.6 M
chartevents, 118.2 M labevents, 9.0 M inputevents; the counts the MIMIC-IV build scripts
check). Every stay is MetaVision and adult (MIMIC-IV has no CareVue era and no neonatal ICU);
``MIMIC4_LAB_NO_HADM`` of the lab rows carry no admission id (about 2 % of MIMIC-IV's
in-hospital labs), which the extraction links by patient and time. patients and admissions are
padded to their full counts with patients who never reach an ICU; the lab rows all belong to
ICU admissions (in MIMIC-IV most belong to other admissions, which the extraction discards
by item and admission alike). The stays, their values and ``expected_cohort`` /
``expected_hr`` are the MIMIC-III shape's with these shares.

Run:  PYTHONPATH=src python benchmarks/mimic3_synth.py OUT_DIR --scale 0.01 [--format parquet]
      [--shape mimic4]
"""

from __future__ import annotations

import argparse
import fcntl
import json
import time
from dataclasses import dataclass
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd

FULL_STAYS = 61_532
# MIMIC-III v1.4 row counts (PhysioNet's table documentation)
FULL_ROWS = {"PATIENTS": 46_520, "ADMISSIONS": 58_976, "ICUSTAYS": 61_532,
             "CHARTEVENTS": 330_712_483, "LABEVENTS": 27_854_055,
             "INPUTEVENTS_CV": 17_527_935, "INPUTEVENTS_MV": 3_618_991,
             "PRESCRIPTIONS": 4_156_450, "MICROBIOLOGYEVENTS": 631_726,
             "OUTPUTEVENTS": 4_349_218}
TABLES = tuple(FULL_ROWS)
CAREVUE_SHARE = 0.62  # ~38k of the 61.5k stays are from the CareVue era (2001-2008)
NEONATE_SHARE = 0.128  # ~7.9k neonatal ICU stays
SEPSIS_SHARE = 0.22  # stays with antibiotic + culture: the cohort is ~19 % of stays
DEATH_SHARE = 0.12
# MIMIC-IV v2.2 row counts per table (MIMIC-III view names; the counts MIT-LCP's MIMIC-IV
# build scripts validate a load against)
MIMIC4_ROWS = {"PATIENTS": 299_712, "ADMISSIONS": 431_231, "ICUSTAYS": 73_181,
               "CHARTEVENTS": 313_645_063, "LABEVENTS": 118_171_367, "INPUTEVENTS_CV": 0,
               "INPUTEVENTS_MV": 8_978_893, "PRESCRIPTIONS": 15_416_708,
               "MICROBIOLOGYEVENTS": 3_228_713, "OUTPUTEVENTS": 4_234_967}
MIMIC4_LAB_NO_HADM = 0.02  # lab rows without an admission id
LOS_MEDIAN_H, LOS_SIGMA = 50.0, 1.31  # log-normal: mean ~ 118 h (MIMIC: 4.9 days)
ADM_BEFORE_H, ADM_AFTER_H = 6, 72  # the admission around the ICU stay

# CHARTEVENTS items charted by construction: (feature, MetaVision item, CareVue item,
# every k hours, value, text VALUE or None, unit)
CHART_KEPT = [
    ("HR", 220045, 211, 1, 60.0, None, "bpm"),
    ("SysBP", 220179, 51, 1, 115.0, None, "mmHg"),
    ("DiaBP", 220180, 8368, 1, 60.0, None, "mmHg"),
    ("MeanBP", 220181, 52, 1, 78.0, None, "mmHg"),
    ("RR", 220210, 618, 1, 18.0, None, "insp/min"),
    ("Temp_F", 223761, 678, 4, 98.6, None, "?F"),
    ("FiO2", 223835, 3420, 4, 40.0, None, "%"),
    ("GCS", 220739, 198, 4, 4.0, None, "points"),  # CareVue: total (value 15 below)
    ("GCS_verbal", 223900, None, 4, 5.0, "Oriented", None),
    ("GCS_motor", 223901, None, 4, 6.0, "Obeys Commands", None),
]
# real ITEMIDs of frequent items the extraction does not read (SpO2, heart rhythm, ...)
CHART_FILLER = [220277, 220048, 742, 646, 212, 128, 224650, 161, 550, 1125, 159, 1484, 5815,
                8549, 5820, 8554, 5819, 8553, 5817, 227969, 8551, 1703, 113, 224080, 224084,
                224082, 227700, 224086, 224085, 224093, 223753, 5813, 8547]
LAB_KEPT = {50971: 4.0, 50983: 140.0, 50902: 100.0, 50931: 120.0, 50893: 8.5, 50882: 24.0,
            50821: 90.0, 50818: 40.0, 50820: 7.4, 50912: 1.0, 50885: 0.5}
LAB_FILLER = [51221, 51006, 50868, 51222, 51301, 51249, 51279, 51248, 51250, 51277, 50960,
              50970, 51275, 51274, 51237, 50801, 50804, 50802, 50861, 50878, 50863, 50813]
CV_INPUT_FILLER = [30013, 30045, 30131, 30118, 30124, 30032, 30140, 30025]
MV_INPUT_FILLER = [225799, 227536, 226453, 223258, 221744, 221668, 226452, 222168, 221794]
OUTPUT_FILLER = [40050, 40286, 40076, 226588, 226589]
DRUG_FILLER = ["Acetaminophen", "Heparin", "Insulin", "Potassium Chloride", "Furosemide",
               "Docusate Sodium", "Pantoprazole", "Metoprolol Tartrate", "Senna",
               "Magnesium Sulfate"]
SPEC = ["BLOOD CULTURE", "URINE", "SPUTUM", "SWAB", "MRSA SCREEN"]


@dataclass(frozen=True)
class Shape:
    """A release's proportions: ICU stays and rows per table at full size (MIMIC-III view
    names), the CareVue and neonate shares, and how its files are laid out."""

    name: str
    full_stays: int
    full_rows: dict[str, int]
    carevue_share: float
    neonate_share: float

    @property
    def tables(self) -> tuple[str, ...]:
        """The tables the release has (MIMIC-IV: no INPUTEVENTS_CV)."""
        return tuple(t for t, rows in self.full_rows.items() if rows)


MIMIC3 = Shape("mimic3", FULL_STAYS, FULL_ROWS, CAREVUE_SHARE, NEONATE_SHARE)
MIMIC4 = Shape("mimic4", MIMIC4_ROWS["ICUSTAYS"], MIMIC4_ROWS, 0.0, 0.0)
SHAPES = {sh.name: sh for sh in (MIMIC3, MIMIC4)}


def stays_frame(scale: float, seed: int = 0, shape: Shape = MIMIC3) -> pd.DataFrame:
    """One row per ICU stay (one stay per admission and patient): identifiers, era, times
    and the per-stay constants the tables are generated from."""
    n = max(int(round(shape.full_stays * scale)), 20)
    rng = np.random.default_rng(seed)
    i = np.arange(n)
    cv = rng.random(n) < shape.carevue_share
    neo = rng.random(n) < shape.neonate_share
    los = np.clip(LOS_MEDIAN_H * np.exp(rng.normal(0, LOS_SIGMA, n)), 4.0, 2400.0)
    intime = (np.datetime64("2101-01-01T00:00:00")
              + (rng.integers(0, 100 * 365 * 24, n) * 3600).astype("timedelta64[s]"))
    age_y = np.where(neo, 0.0, rng.uniform(20, 85, n))
    died = rng.random(n) < DEATH_SHARE
    return pd.DataFrame({
        "i": i, "subject_id": 1 + i, "hadm_id": 100_000 + i, "icustay_id": 200_000 + i,
        "cv": cv, "neonate": neo, "sepsis": (rng.random(n) < SEPSIS_SHARE) & ~neo,
        "los_h": los, "nh": np.ceil(los).astype("int64"),
        "intime": intime.astype("datetime64[us]"),
        "dob": (intime - (age_y * 365.25 * 86400).astype("timedelta64[s]")
                - np.timedelta64(86400, "s")).astype("datetime64[us]"),
        "died": died, "dod_days": rng.uniform(1, 80, n),
        "delay": rng.choice([0.25, 0.5, 1.5, 2.5], n, p=[.4, .2, .3, .1]),
        "hr_shift": (i % 40).astype("float64"),
        "female": rng.random(n) < 0.44,
    })


def expected_cohort(stays: pd.DataFrame, t_max: int = 4) -> pd.Index:
    """ICU stay ids the extraction (defaults, anchor first_vitals) must keep: adult sepsis
    stays that last at least t_max + 1 hours after their anchor floor(delay) h."""
    ok = stays["sepsis"] & ~stays["neonate"] & (
        stays["los_h"] >= np.floor(stays["delay"]) + t_max + 1)
    return pd.Index(stays.loc[ok, "icustay_id"].to_numpy("int64"))


def expected_hr(stays: pd.DataFrame, t_max: int = 4) -> pd.DataFrame:
    """stay_id, t, HR of the cohort's trajectories by construction: 60 + i % 40 + t."""
    ids = expected_cohort(stays, t_max)
    s = stays.set_index("icustay_id").loc[ids]
    t = np.tile(np.arange(t_max + 1), len(ids))
    return pd.DataFrame({"stay_id": np.repeat(ids.to_numpy(), t_max + 1), "t": t,
                         "HR": 60.0 + np.repeat(s["hr_shift"].to_numpy(), t_max + 1) + t})


def _u(*args: str) -> str:
    """A uniform in [0, 1) hashed from SQL expressions (deterministic, thread-safe)."""
    return f"((hash({', '.join(args)}) % 1000003) / 1000003.0)"


def _ts(expr: str, hours: str) -> str:
    return f"({expr} + to_microseconds(CAST(({hours}) * 3600e6 AS BIGINT)))"


def _rate(target: float, kept: float, units: float) -> tuple[int, float]:
    """Filler rows per unit so that kept + filler ~ target: (whole slots, extra share)."""
    r = max(target - kept, 0.0) / max(units, 1.0)
    return int(np.floor(r)), float(r - np.floor(r))


def _filler(units: str, whole: int, frac: float, salt: int) -> str:
    """``units`` (a SELECT with columns i, h) times filler slots s: every unit gets ``whole``
    slots, and one more with probability ``frac``."""
    n = whole + (1 if frac > 0 else 0)
    return (f"(SELECT u.i, u.h, s.s FROM ({units}) u, range({n}) s(s) "
            f"WHERE s.s < {whole} OR {_u('u.i', 'u.h', str(salt))} < {frac})")


def _in_list(col: str, values: list[int]) -> str:
    vals = ", ".join(map(str, values))
    return f"list_extract([{vals}], 1 + CAST(({col}) AS BIGINT) % {len(values)})"


def table_queries(con: duckdb.DuckDBPyConnection, stays: pd.DataFrame, scale: float,
                  shape: Shape = MIMIC3) -> dict[str, str]:
    """SELECT statement per table (MIMIC-III's columns) over the registered ``st`` (stays)
    relation, with ``shape``'s rows per stay."""
    con.register("st", stays)
    kept = pd.DataFrame(CHART_KEPT, columns=["feature", "item_mv", "item_cv", "every", "base",
                                             "text", "uom"])
    kept["k"] = np.arange(len(kept))
    kept = kept.astype({"item_mv": "Int64", "item_cv": "Int64"})
    con.register("chart_kept", kept)
    stay_hours = "SELECT i, unnest(range(nh)) AS h FROM st"
    n_sh = float(stays["nh"].sum())
    cv = stays["cv"].to_numpy()
    n_sh_cv, n_sh_mv = float(stays.loc[cv, "nh"].sum()), float(stays.loc[~cv, "nh"].sum())
    n = len(stays)
    target = {t: shape.full_rows[t] * n / shape.full_stays for t in TABLES}
    q: dict[str, str] = {}

    q["PATIENTS"] = f"""
        SELECT i + 1 AS ROW_ID, subject_id AS SUBJECT_ID,
               CASE WHEN female THEN 'F' ELSE 'M' END AS GENDER, dob AS DOB,
               CASE WHEN died THEN {_ts('intime', 'los_h + 24 * dod_days')} END AS DOD,
               CASE WHEN died THEN {_ts('intime', 'los_h + 24 * dod_days')} END AS DOD_HOSP,
               NULL::TIMESTAMP AS DOD_SSN, CAST(died AS INTEGER) AS EXPIRE_FLAG
        FROM st"""
    q["ADMISSIONS"] = f"""
        SELECT i + 1 AS ROW_ID, subject_id AS SUBJECT_ID, hadm_id AS HADM_ID,
               {_ts('intime', f'-{ADM_BEFORE_H}')} AS ADMITTIME,
               {_ts('intime', f'nh + {ADM_AFTER_H}')} AS DISCHTIME, NULL::TIMESTAMP AS DEATHTIME,
               'EMERGENCY' AS ADMISSION_TYPE, 'EMERGENCY ROOM ADMIT' AS ADMISSION_LOCATION,
               'HOME' AS DISCHARGE_LOCATION, 'Medicare' AS INSURANCE, 'SEPSIS' AS DIAGNOSIS,
               0 AS HOSPITAL_EXPIRE_FLAG, 1 AS HAS_CHARTEVENTS_DATA
        FROM st"""
    q["ICUSTAYS"] = f"""
        SELECT i + 1 AS ROW_ID, subject_id AS SUBJECT_ID, hadm_id AS HADM_ID,
               icustay_id AS ICUSTAY_ID, CASE WHEN cv THEN 'carevue' ELSE 'metavision' END
               AS DBSOURCE, CASE WHEN neonate THEN 'NICU' ELSE 'MICU' END AS FIRST_CAREUNIT,
               CASE WHEN neonate THEN 'NICU' ELSE 'MICU' END AS LAST_CAREUNIT,
               52 AS FIRST_WARDID, 52 AS LAST_WARDID, intime AS INTIME,
               {_ts('intime', 'los_h')} AS OUTTIME, round(los_h / 24, 4) AS LOS
        FROM st"""

    # CHARTEVENTS: vitals etc. by construction, then filler items over stay-hours
    kept_rows = sum(
        float(((stays["nh"] + k["every"] - 1) // k["every"])[
            stays["cv"] if pd.isna(k["item_mv"]) else
            (~stays["cv"] if pd.isna(k["item_cv"]) else np.ones(n, bool))].sum())
        for _, k in kept.iterrows()) + n
    ce_fill = _filler(stay_hours, *_rate(target["CHARTEVENTS"], kept_rows, n_sh), 11)
    ce_cols = """ROW_ID, SUBJECT_ID, HADM_ID, ICUSTAY_ID, ITEMID, CHARTTIME, STORETIME, CGID,
                 VALUE, VALUENUM, VALUEUOM, WARNING, ERROR, RESULTSTATUS, STOPPED"""

    def ce_row(row_id: str, item: str, t: str, value: str, valuenum: str, uom: str) -> str:
        return f"""SELECT {row_id} AS ROW_ID, s.subject_id AS SUBJECT_ID, s.hadm_id AS HADM_ID,
               s.icustay_id AS ICUSTAY_ID, {item} AS ITEMID, {t} AS CHARTTIME,
               {t} + INTERVAL 20 MINUTE AS STORETIME, 14000 + s.i % 5000 AS CGID,
               {value} AS VALUE, {valuenum} AS VALUENUM, {uom} AS VALUEUOM,
               CASE WHEN s.cv THEN NULL ELSE 0 END AS WARNING,
               CASE WHEN s.cv THEN NULL ELSE 0 END AS ERROR,
               CASE WHEN s.cv THEN 'Manual' END AS RESULTSTATUS,
               CASE WHEN s.cv THEN 'NotStopd' END AS STOPPED"""

    vnum = ("CASE WHEN k.feature = 'HR' THEN k.base + s.hr_shift + sh.h "
            "WHEN k.feature = 'GCS' AND s.cv THEN 15.0 ELSE k.base END")
    vitals = ce_row("(s.i * 4096 + sh.h) * 64 + k.k",
                    "CASE WHEN s.cv THEN k.item_cv ELSE k.item_mv END",
                    _ts("s.intime", "s.delay + sh.h"),
                    f"coalesce(k.text, CAST({vnum} AS VARCHAR))", vnum, "k.uom") + f"""
        FROM ({stay_hours}) sh JOIN st s USING (i) JOIN chart_kept k ON sh.h % k.every = 0
        WHERE s.delay + sh.h < s.los_h
          AND (CASE WHEN s.cv THEN k.item_cv ELSE k.item_mv END) IS NOT NULL"""
    weight = ce_row("s.i * 4096 * 64 + 63", "CASE WHEN s.cv THEN 3581 ELSE 226512 END",
                    "s.intime + INTERVAL 10 MINUTE",
                    "CASE WHEN s.cv THEN '165' ELSE '75' END",
                    "CASE WHEN s.cv THEN 165.0 ELSE 75.0 END",
                    "CASE WHEN s.cv THEN 'lb' ELSE 'kg' END") + " FROM st s"
    u = _u("f.i", "f.h", "f.s", "12")
    filler = ce_row("(s.i * 4096 + f.h) * 64 + 20 + f.s",
                    _in_list(f"hash(f.i, f.h, f.s) % {len(CHART_FILLER)}", CHART_FILLER),
                    _ts("s.intime", f"f.h + {u}"), f"CAST(round(100 * {u}, 1) AS VARCHAR)",
                    f"round(100 * {u}, 1)", "'%'") + f" FROM {ce_fill} f JOIN st s USING (i)"
    q["CHARTEVENTS"] = (f"SELECT {ce_cols} FROM ({vitals} UNION ALL {weight} "
                        f"UNION ALL {filler})")

    # LABEVENTS: draws at INTIME - 1 h, + 3 h and every 12 h of the stay; filler over the
    # admission's hours
    labk = pd.DataFrame({"itemid": list(LAB_KEPT) + [51265],
                         "base": list(LAB_KEPT.values()) + [80.0]})
    con.register("lab_kept", labk)
    draws = ("SELECT i, -1 AS h FROM st UNION ALL SELECT i, 3 AS h FROM st UNION ALL "
             "SELECT i, h FROM (SELECT i, unnest(range(12, nh, 12)) AS h FROM st)")
    n_draws = 2 * n + float((np.maximum(stays["nh"] - 1, 0) // 12).sum())
    lab_kept_rows = n_draws * (0.75 * len(LAB_KEPT) + 1)
    adm_hours = f"SELECT i, unnest(range(-{ADM_BEFORE_H}, nh + {ADM_AFTER_H})) AS h FROM st"
    n_adm_h = n_sh + n * (ADM_BEFORE_H + ADM_AFTER_H)
    lab_fill = _filler(adm_hours, *_rate(target["LABEVENTS"], lab_kept_rows, n_adm_h), 21)
    ul = _u("d.i", "d.h", "l.itemid", "22")
    lab_val = ("CASE WHEN l.itemid = 51265 THEN CASE WHEN s.sepsis THEN 80.0 ELSE 200.0 END "
               f"ELSE round(l.base * (0.97 + 0.06 * {ul}), 3) END")
    uf = _u("f.i", "f.h", "f.s", "23")
    q["LABEVENTS"] = f"""
        SELECT ROW_ID, SUBJECT_ID, HADM_ID, ITEMID, CHARTTIME, VALUE, VALUENUM, VALUEUOM, FLAG
        FROM (
          SELECT (s.i * 8192 + d.h + 16) * 64 + l.itemid % 50 AS ROW_ID, s.subject_id AS SUBJECT_ID,
                 s.hadm_id AS HADM_ID, l.itemid AS ITEMID, {_ts('s.intime', 'd.h')} AS CHARTTIME,
                 CAST({lab_val} AS VARCHAR) AS VALUE, {lab_val} AS VALUENUM,
                 'mEq/L' AS VALUEUOM, NULL AS FLAG
          FROM ({draws}) d JOIN st s USING (i) CROSS JOIN lab_kept l
          WHERE l.itemid = 51265 OR {ul} >= 0.25
          UNION ALL
          SELECT -((s.i * 8192 + f.h + 16) * 64 + f.s) AS ROW_ID, s.subject_id, s.hadm_id,
                 {_in_list(f'hash(f.i, f.h, f.s) % {len(LAB_FILLER)}', LAB_FILLER)},
                 {_ts('s.intime', f'f.h + {uf}')}, CAST(round(10 * {uf}, 2) AS VARCHAR),
                 round(10 * {uf}, 2), 'units', CASE WHEN {uf} > 0.9 THEN 'abnormal' END
          FROM {lab_fill} f JOIN st s USING (i))"""

    # INPUTEVENTS_MV: NaCl 500 mL over 2.5 h and norepinephrine 0.1 ug/kg/min every 8 h
    mv_hours = "SELECT i, unnest(range(nh)) AS h FROM st WHERE NOT cv"
    mv_kept = 2 * float(((stays.loc[~cv, "nh"] + 7) // 8).sum())
    mv_fill = _filler(mv_hours, *_rate(target["INPUTEVENTS_MV"], mv_kept, n_sh_mv), 31)
    um = _u("f.i", "f.h", "f.s", "32")
    mv_cols = """ROW_ID, SUBJECT_ID, HADM_ID, ICUSTAY_ID, STARTTIME, ENDTIME, ITEMID, AMOUNT,
                 AMOUNTUOM, RATE, RATEUOM, STORETIME, CGID, ORDERID, PATIENTWEIGHT,
                 TOTALAMOUNT, STATUSDESCRIPTION"""
    q["INPUTEVENTS_MV"] = f"""
        SELECT {mv_cols} FROM (
          SELECT (s.i * 4096 + h.h) * 64 + x.k AS ROW_ID, s.subject_id AS SUBJECT_ID,
                 s.hadm_id AS HADM_ID, s.icustay_id AS ICUSTAY_ID,
                 {_ts('s.intime', 'h.h + 0.5')} AS STARTTIME,
                 {_ts('s.intime', 'h.h + 3')} AS ENDTIME, x.itemid AS ITEMID,
                 x.amount AS AMOUNT, 'ml' AS AMOUNTUOM, x.rate AS RATE, x.rateuom AS RATEUOM,
                 {_ts('s.intime', 'h.h + 3.2')} AS STORETIME, 14000 + s.i % 5000 AS CGID,
                 s.i * 100 + h.h AS ORDERID, 75.0 AS PATIENTWEIGHT, x.amount AS TOTALAMOUNT,
                 'FinishedRunning' AS STATUSDESCRIPTION
          FROM (SELECT i, unnest(range(0, nh, 8)) AS h FROM st WHERE NOT cv) h
          JOIN st s USING (i)
          CROSS JOIN (VALUES (0, 225158, 500.0, 200.0, 'mL/hour'),
                             (1, 221906, NULL, 0.1, 'mcg/kg/min'))
               x(k, itemid, amount, rate, rateuom)
          UNION ALL
          SELECT -((s.i * 4096 + f.h) * 64 + f.s), s.subject_id, s.hadm_id, s.icustay_id,
                 {_ts('s.intime', f'f.h + {um}')}, {_ts('s.intime', f'f.h + {um} + 1')},
                 {_in_list(f'hash(f.i, f.h, f.s) % {len(MV_INPUT_FILLER)}', MV_INPUT_FILLER)},
                 round(100 * {um}, 2), 'mg', NULL, NULL, {_ts('s.intime', 'f.h + 1.5')},
                 14000 + s.i % 5000, s.i * 100 + f.h, 75.0, 100.0, 'FinishedRunning'
          FROM {mv_fill} f JOIN st s USING (i))"""

    # INPUTEVENTS_CV: an NaCl 250 mL bolus every 6 h, a charted Levophed rate every 3 h
    cv_hours = "SELECT i, unnest(range(nh)) AS h FROM st WHERE cv"
    cv_kept = float(((stays.loc[cv, "nh"] + 4) // 6).sum()
                    + ((stays.loc[cv, "nh"] + 1) // 3).sum())
    cv_fill = _filler(cv_hours, *_rate(target["INPUTEVENTS_CV"], cv_kept, n_sh_cv), 41)
    uc = _u("f.i", "f.h", "f.s", "42")
    cv_cols = """ROW_ID, SUBJECT_ID, HADM_ID, ICUSTAY_ID, CHARTTIME, ITEMID, AMOUNT, AMOUNTUOM,
                 RATE, RATEUOM, STORETIME, CGID, ORDERID, LINKORDERID, STOPPED, NEWBOTTLE,
                 ORIGINALROUTE"""
    q["INPUTEVENTS_CV"] = f"""
        SELECT {cv_cols} FROM (
          SELECT (s.i * 4096 + h.h) * 64 + x.k AS ROW_ID, s.subject_id AS SUBJECT_ID,
                 s.hadm_id AS HADM_ID, s.icustay_id AS ICUSTAY_ID,
                 {_ts('s.intime', 'h.h + 1 + x.k')} AS CHARTTIME, x.itemid AS ITEMID,
                 x.amount AS AMOUNT, 'ml' AS AMOUNTUOM, x.rate AS RATE, x.rateuom AS RATEUOM,
                 {_ts('s.intime', 'h.h + 1.2 + x.k')} AS STORETIME, 14000 + s.i % 5000 AS CGID,
                 s.i * 100 + h.h AS ORDERID, s.i * 100 + h.h AS LINKORDERID,
                 NULL AS STOPPED, NULL AS NEWBOTTLE, 'Intravenous' AS ORIGINALROUTE
          FROM (SELECT i, 0 AS k, unnest(range(0, nh, 6)) AS h FROM st WHERE cv
                UNION ALL SELECT i, 1 AS k, unnest(range(0, nh, 3)) AS h FROM st WHERE cv) h
          JOIN st s USING (i)
          JOIN (VALUES (0, 30018, 250.0, NULL, NULL), (1, 30047, NULL, 8.0, 'mcgmin'))
               x(k, itemid, amount, rate, rateuom) ON x.k = h.k
          WHERE h.h + 1 + x.k < s.los_h
          UNION ALL
          SELECT -((s.i * 4096 + f.h) * 64 + f.s), s.subject_id, s.hadm_id, s.icustay_id,
                 {_ts('s.intime', f'f.h + {uc}')},
                 {_in_list(f'hash(f.i, f.h, f.s) % {len(CV_INPUT_FILLER)}', CV_INPUT_FILLER)},
                 round(50 * {uc}, 2), 'ml', NULL, NULL, {_ts('s.intime', 'f.h + 1')},
                 14000 + s.i % 5000, s.i * 100 + f.h, s.i * 100 + f.h, NULL, NULL, 'Intravenous'
          FROM {cv_fill} f JOIN st s USING (i))"""

    # PRESCRIPTIONS: Vancomycin IV for sepsis stays; filler drugs per stay
    stay_units = "SELECT i, 0 AS h FROM st"
    pr_fill = _filler(stay_units, *_rate(target["PRESCRIPTIONS"], float(stays["sepsis"].sum()),
                                         n), 51)
    up = _u("f.i", "f.s", "52")
    drugs = "[" + ", ".join(f"'{d}'" for d in DRUG_FILLER) + "]"
    q["PRESCRIPTIONS"] = f"""
        SELECT ROW_ID, SUBJECT_ID, HADM_ID, ICUSTAY_ID, STARTDATE, ENDDATE, DRUG_TYPE, DRUG,
               DOSE_VAL_RX, DOSE_UNIT_RX, ROUTE FROM (
          SELECT s.i * 1024 AS ROW_ID, s.subject_id AS SUBJECT_ID, s.hadm_id AS HADM_ID,
                 s.icustay_id AS ICUSTAY_ID, {_ts('s.intime', '-2')} AS STARTDATE,
                 {_ts('s.intime', '70')} AS ENDDATE, 'MAIN' AS DRUG_TYPE,
                 'Vancomycin' AS DRUG, '1000' AS DOSE_VAL_RX, 'mg' AS DOSE_UNIT_RX, 'IV' AS ROUTE
          FROM st s WHERE s.sepsis
          UNION ALL
          SELECT s.i * 1024 + 1 + f.s, s.subject_id, s.hadm_id,
                 CASE WHEN {up} < 0.5 THEN s.icustay_id END,
                 {_ts('s.intime', f'-6 + (s.nh + 78) * {up}')},
                 {_ts('s.intime', f'(s.nh + 78) * {up} + 18')}, 'MAIN',
                 list_extract({drugs}, 1 + CAST(hash(f.i, f.s) % {len(DRUG_FILLER)} AS BIGINT)),
                 '1', 'TAB', 'PO'
          FROM {pr_fill} f JOIN st s USING (i))"""

    # MICROBIOLOGYEVENTS: a blood culture at INTIME - 4 h for sepsis stays (3 rows: specimen,
    # organism, antibiotic tested); filler cultures from INTIME + 12 h on
    mb_fill = _filler(stay_units, *_rate(target["MICROBIOLOGYEVENTS"],
                                         3 * float(stays["sepsis"].sum()), n), 61)
    ub = _u("f.i", "f.s", "62")
    spec = "[" + ", ".join(f"'{d}'" for d in SPEC) + "]"
    q["MICROBIOLOGYEVENTS"] = f"""
        SELECT ROW_ID, SUBJECT_ID, HADM_ID, CHARTDATE, CHARTTIME, SPEC_ITEMID, SPEC_TYPE_DESC,
               ORG_NAME FROM (
          SELECT s.i * 1024 + r AS ROW_ID, s.subject_id AS SUBJECT_ID, s.hadm_id AS HADM_ID,
                 date_trunc('day', {_ts('s.intime', '-4')}) AS CHARTDATE,
                 {_ts('s.intime', '-4')} AS CHARTTIME, 70012 AS SPEC_ITEMID,
                 'BLOOD CULTURE' AS SPEC_TYPE_DESC, 'STAPH AUREUS COAG +' AS ORG_NAME
          FROM st s, range(3) r(r) WHERE s.sepsis
          UNION ALL
          SELECT s.i * 1024 + 3 + f.s, s.subject_id, s.hadm_id,
                 date_trunc('day', {_ts('s.intime', f'12 + (s.nh + 60) * {ub}')}),
                 CASE WHEN {ub} < 0.8 THEN {_ts('s.intime', f'12 + (s.nh + 60) * {ub}')} END,
                 70079, list_extract({spec}, 1 + CAST(hash(f.i, f.s) % {len(SPEC)} AS BIGINT)),
                 NULL
          FROM {mb_fill} f JOIN st s USING (i))"""

    # OUTPUTEVENTS: urine (Foley) every 2 h; filler drains
    out_kept = float(((stays["nh"] + 1) // 2).sum())
    out_fill = _filler(stay_hours, *_rate(target["OUTPUTEVENTS"], out_kept, n_sh), 71)
    uo = _u("f.i", "f.h", "f.s", "72")
    q["OUTPUTEVENTS"] = f"""
        SELECT ROW_ID, SUBJECT_ID, HADM_ID, ICUSTAY_ID, CHARTTIME, ITEMID, VALUE, VALUEUOM,
               STORETIME, CGID, STOPPED, NEWBOTTLE, ISERROR FROM (
          SELECT (s.i * 4096 + h.h) * 64 AS ROW_ID, s.subject_id AS SUBJECT_ID,
                 s.hadm_id AS HADM_ID, s.icustay_id AS ICUSTAY_ID,
                 {_ts('s.intime', 'h.h + 0.5')} AS CHARTTIME,
                 CASE WHEN s.cv THEN 40055 ELSE 226559 END AS ITEMID, 60.0 AS VALUE,
                 'mL' AS VALUEUOM, {_ts('s.intime', 'h.h + 0.7')} AS STORETIME,
                 14000 + s.i % 5000 AS CGID, NULL AS STOPPED, NULL AS NEWBOTTLE, NULL AS ISERROR
          FROM (SELECT i, unnest(range(0, nh, 2)) AS h FROM st) h JOIN st s USING (i)
          UNION ALL
          SELECT -((s.i * 4096 + f.h) * 64 + f.s), s.subject_id, s.hadm_id, s.icustay_id,
                 {_ts('s.intime', f'f.h + {uo}')},
                 {_in_list(f'hash(f.i, f.h, f.s) % {len(OUTPUT_FILLER)}', OUTPUT_FILLER)},
                 round(100 * {uo}, 1), 'mL', {_ts('s.intime', 'f.h + 1')}, 14000 + s.i % 5000,
                 NULL, NULL, NULL
          FROM {out_fill} f JOIN st s USING (i))"""
    return q


# MIMIC-IV file (relative to the folder, without suffix) and columns per MIMIC-III view: the
# real MIMIC-IV v2.2 column names in their order, each given by an expression over the
# MIMIC-III-shaped query's columns (NULL where the generator has nothing to put)
MIMIC4_FILES: dict[str, tuple[str, dict[str, str]]] = {
    "ICUSTAYS": ("icu/icustays", {
        "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID", "stay_id": "ICUSTAY_ID",
        "first_careunit": "'Medical Intensive Care Unit (MICU)'",
        "last_careunit": "'Medical Intensive Care Unit (MICU)'", "intime": "INTIME",
        "outtime": "OUTTIME", "los": "LOS"}),
    "CHARTEVENTS": ("icu/chartevents", {
        "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID", "stay_id": "ICUSTAY_ID",
        "caregiver_id": "CGID", "charttime": "CHARTTIME", "storetime": "STORETIME",
        "itemid": "ITEMID", "value": "VALUE", "valuenum": "VALUENUM", "valueuom": "VALUEUOM",
        "warning": "0"}),
    "LABEVENTS": ("hosp/labevents", {
        "labevent_id": "ROW_ID", "subject_id": "SUBJECT_ID",
        "hadm_id": f"CASE WHEN hash(ROW_ID, 5) % 1000000 < {int(MIMIC4_LAB_NO_HADM * 1e6)} "
                   "THEN NULL ELSE HADM_ID END",
        "specimen_id": "abs(ROW_ID) // 64", "itemid": "ITEMID", "order_provider_id": "NULL",
        "charttime": "CHARTTIME", "storetime": "CHARTTIME + INTERVAL 1 HOUR",
        "value": "VALUE", "valuenum": "VALUENUM", "valueuom": "VALUEUOM",
        "ref_range_lower": "NULL", "ref_range_upper": "NULL", "flag": "FLAG",
        "priority": "'ROUTINE'", "comments": "NULL"}),
    "INPUTEVENTS_MV": ("icu/inputevents", {
        "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID", "stay_id": "ICUSTAY_ID",
        "caregiver_id": "CGID", "starttime": "STARTTIME", "endtime": "ENDTIME",
        "storetime": "STORETIME", "itemid": "ITEMID", "amount": "AMOUNT",
        "amountuom": "AMOUNTUOM", "rate": "RATE", "rateuom": "RATEUOM", "orderid": "ORDERID",
        "linkorderid": "ORDERID", "ordercategoryname": "NULL",
        "secondaryordercategoryname": "NULL", "ordercomponenttypedescription": "NULL",
        "ordercategorydescription": "NULL", "patientweight": "PATIENTWEIGHT",
        "totalamount": "TOTALAMOUNT", "totalamountuom": "'ml'", "isopenbag": "0",
        "continueinnextdept": "0", "statusdescription": "STATUSDESCRIPTION",
        "originalamount": "AMOUNT", "originalrate": "RATE"}),
    "OUTPUTEVENTS": ("icu/outputevents", {
        "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID", "stay_id": "ICUSTAY_ID",
        "caregiver_id": "CGID", "charttime": "CHARTTIME", "storetime": "STORETIME",
        "itemid": "ITEMID", "value": "VALUE", "valueuom": "VALUEUOM"}),
    "PRESCRIPTIONS": ("hosp/prescriptions", {
        "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID", "pharmacy_id": "ROW_ID",
        "poe_id": "NULL", "poe_seq": "NULL", "order_provider_id": "NULL",
        "starttime": "STARTDATE", "stoptime": "ENDDATE", "drug_type": "DRUG_TYPE",
        "drug": "DRUG", "formulary_drug_cd": "NULL", "gsn": "NULL", "ndc": "NULL",
        "prod_strength": "NULL", "form_rx": "NULL", "dose_val_rx": "DOSE_VAL_RX",
        "dose_unit_rx": "DOSE_UNIT_RX", "form_val_disp": "NULL", "form_unit_disp": "NULL",
        "doses_per_24_hrs": "NULL", "route": "ROUTE"}),
    "MICROBIOLOGYEVENTS": ("hosp/microbiologyevents", {
        "microevent_id": "ROW_ID", "subject_id": "SUBJECT_ID", "hadm_id": "HADM_ID",
        "micro_specimen_id": "ROW_ID // 1024", "order_provider_id": "NULL",
        "chartdate": "CHARTDATE", "charttime": "CHARTTIME", "spec_itemid": "SPEC_ITEMID",
        "spec_type_desc": "SPEC_TYPE_DESC", "test_seq": "1", "storedate": "CHARTDATE",
        "storetime": "CHARTTIME", "test_itemid": "NULL", "test_name": "NULL",
        "org_itemid": "NULL", "org_name": "ORG_NAME", "isolate_num": "NULL",
        "quantity": "NULL", "ab_itemid": "NULL", "ab_name": "NULL", "dilution_text": "NULL",
        "dilution_comparison": "NULL", "dilution_value": "NULL", "interpretation": "NULL",
        "comments": "NULL"}),
    "PATIENTS": ("hosp/patients", {}),
    "ADMISSIONS": ("hosp/admissions", {}),
}


def mimic4_queries(q3: dict[str, str], stays: pd.DataFrame, shape: Shape = MIMIC4
                   ) -> dict[str, str]:
    """MIMIC-IV file stem -> SELECT: the MIMIC-III-shaped queries ``q3`` under MIMIC-IV's
    files and columns; patients from the stays (anchor_year = the year of INTIME, anchor_age
    = the age then; dod a date) and, like admissions, padded to ``shape``'s counts with
    patients who never reach an ICU."""
    n = len(stays)
    per_stay = {t: shape.full_rows[t] * n / shape.full_stays for t in ("PATIENTS",
                                                                       "ADMISSIONS")}
    pad_pat = max(int(round(per_stay["PATIENTS"])) - n, 0)
    pad_adm = max(int(round(per_stay["ADMISSIONS"])) - n, 0) if pad_pat else 0
    q: dict[str, str] = {}
    for view, (stem, cols) in MIMIC4_FILES.items():
        if cols:
            sel = ", ".join(f'{expr} AS "{col}"' for col, expr in cols.items())
            q[stem] = f"SELECT {sel} FROM ({q3[view]})"
    q["hosp/patients"] = f"""
        SELECT subject_id, CASE WHEN female THEN 'F' ELSE 'M' END AS gender,
               CAST(floor(date_diff('day', dob, intime) / 365.25) AS INTEGER) AS anchor_age,
               year(intime) AS anchor_year, '2011 - 2013' AS anchor_year_group,
               CASE WHEN died THEN CAST({_ts('intime', 'los_h + 24 * dod_days')} AS DATE)
               END AS dod
        FROM st
        UNION ALL
        SELECT {n + 1} + j, CASE WHEN j % 2 = 0 THEN 'F' ELSE 'M' END, 20 + j % 70,
               2150 + j % 50, '2011 - 2013', NULL::DATE
        FROM range({pad_pat}) r(j)"""
    q["hosp/admissions"] = f"""
        SELECT SUBJECT_ID AS subject_id, HADM_ID AS hadm_id, ADMITTIME AS admittime,
               DISCHTIME AS dischtime, DEATHTIME AS deathtime,
               ADMISSION_TYPE AS admission_type, NULL AS admit_provider_id,
               ADMISSION_LOCATION AS admission_location,
               DISCHARGE_LOCATION AS discharge_location, INSURANCE AS insurance,
               'ENGLISH' AS language, NULL AS marital_status, 'WHITE' AS race,
               NULL::TIMESTAMP AS edregtime, NULL::TIMESTAMP AS edouttime,
               HOSPITAL_EXPIRE_FLAG AS hospital_expire_flag
        FROM ({q3['ADMISSIONS']})
        UNION ALL
        SELECT {n + 1} + j % {max(pad_pat, 1)}, {100_000 + n} + j,
               {_ts("TIMESTAMP '2150-01-01'", '24 * 7 * j')},
               {_ts("TIMESTAMP '2150-01-01'", '24 * 7 * j + 72')}, NULL::TIMESTAMP,
               'EW EMER.', NULL, 'EMERGENCY ROOM', 'HOME', 'Medicare', 'ENGLISH', NULL,
               'WHITE', NULL::TIMESTAMP, NULL::TIMESTAMP, 0
        FROM range({pad_adm}) r(j)"""
    return q


def _check_filler() -> None:
    """Filler ITEMIDs and drugs must be ones the extraction does not read."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from twinfalsify.sources.mimic3.tables import data_table, read_items

    read = set(read_items()["CHARTEVENTS"])  # every itemid of every data table
    clash = read & set(CHART_FILLER + LAB_FILLER + CV_INPUT_FILLER + MV_INPUT_FILLER
                       + OUTPUT_FILLER)
    if clash:
        raise ValueError(f"filler ITEMIDs {sorted(clash)} are read by the extraction")
    ab = data_table("antibiotics.csv")
    inc = ab.loc[ab["kind"] == "name_include", "pattern"].str.lower()
    bad = [d for d in DRUG_FILLER if any(p in d.lower() for p in inc)]
    if bad:
        raise ValueError(f"filler drugs {bad} match antibiotics.csv")


def write_mimic3(folder: Path, scale: float, fmt: str = "csv.gz", seed: int = 0,
                 threads: int = 2, memory_limit: str = "2GB",
                 tables: tuple[str, ...] | None = None, shape: Shape = MIMIC3) -> pd.DataFrame:
    """Write the tables for ``scale`` x full MIMIC-III (``shape=MIMIC4``: full MIMIC-IV, in
    its layout) into ``folder`` (``fmt``: ``csv.gz`` or ``parquet``); returns the stays frame
    (for ``expected_cohort`` / ``expected_hr``). ``rows.json`` next to the tables: the rows
    written per table, by MIMIC-III view name."""
    if fmt not in ("csv.gz", "parquet"):
        raise ValueError(f"fmt must be csv.gz or parquet, got {fmt!r}")
    _check_filler()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stays = stays_frame(scale, seed, shape)
    con = duckdb.connect()
    con.execute(f"SET threads = {int(threads)}")
    con.execute(f"SET memory_limit = '{memory_limit}'")
    con.execute("SET preserve_insertion_order = false")
    con.execute(f"SET temp_directory = '{folder / '.tmp'}'")
    try:
        q = table_queries(con, stays, scale, shape)
        files = {t: (t, q[t]) for t in TABLES}
        if shape.name == "mimic4":
            q4 = mimic4_queries(q, stays, shape)
            files = {t: (MIMIC4_FILES[t][0], q4[MIMIC4_FILES[t][0]]) for t in shape.tables}
        rows = {}
        for t in tables or shape.tables:
            stem, sql = files[t]
            path = folder / f"{stem}.{fmt}"
            path.parent.mkdir(parents=True, exist_ok=True)
            opts = ("FORMAT parquet" if fmt == "parquet" else
                    "FORMAT csv, HEADER, COMPRESSION gzip, TIMESTAMPFORMAT '%Y-%m-%d %H:%M:%S'")
            rows[t] = int(con.execute(f"COPY ({sql}) TO '{path}' ({opts})").fetchone()[0])
    finally:
        con.close()
    # rows written per table, next to the tables (the extraction reads only table files);
    # a run given some tables adds to what another run of the same folder wrote
    rows_file = folder / "rows.json"
    with open(folder / ".rows.lock", "w") as lock:  # two runs may finish at once
        fcntl.flock(lock, fcntl.LOCK_EX)
        if tables and rows_file.exists():
            rows = {**json.loads(rows_file.read_text()), **rows}
        rows_file.write_text(json.dumps(rows, indent=1) + "\n")
    return stays


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path)
    p.add_argument("--scale", type=float, required=True, help="fraction of the full release")
    p.add_argument("--shape", default="mimic3", choices=sorted(SHAPES),
                   help="mimic3: MIMIC-III v1.4; mimic4: MIMIC-IV v2.2 in its layout")
    p.add_argument("--format", default="csv.gz", choices=["csv.gz", "parquet"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--memory-limit", default="2GB")
    p.add_argument("--tables", default=None,
                   help="comma-separated MIMIC-III table names to write (default: all); two "
                   "runs on one folder with complementary lists write the tables in parallel")
    a = p.parse_args()
    shape = SHAPES[a.shape]
    tables = tuple(a.tables.split(",")) if a.tables else None
    if tables and (bad := sorted(set(tables) - set(shape.tables))):
        p.error(f"--tables: unknown table(s) {bad}; choose from {list(shape.tables)}")
    t = time.perf_counter()
    stays = write_mimic3(a.folder, a.scale, a.format, a.seed, a.threads, a.memory_limit,
                         tables=tables, shape=shape)
    rows = json.loads((a.folder / "rows.json").read_text())
    print(f"{len(stays)} stays, expected cohort {len(expected_cohort(stays))}; "
          f"{time.perf_counter() - t:.0f} s")
    for tab in tables or shape.tables:
        stem = MIMIC4_FILES[tab][0] if shape.name == "mimic4" else tab
        f = a.folder / f"{stem}.{a.format}"
        print(f"{tab}: {rows[tab]} rows ({shape.full_rows[tab] * a.scale:.0f} at this scale "
              f"of full), {f.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
