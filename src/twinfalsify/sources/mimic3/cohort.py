"""MIMIC-III v1.4 sepsis-3 cohort (AI-Clinician criteria with the paper's changes) as hourly
trajectories over ``t_max`` + 1 hours from a time anchor t0 (ICU admission, or the first
complete vital set), plus a CONSORT table, missingness, the anchor of each stay and a
per-stay audit table. No value of hour t depends on anything charted after the end of
hour t (tests/sources/mimic3/test_mimic3_causality.py).

Steps (each a row of the CONSORT table, ``STEPS``; every criterion is evaluated for every
stay where it is defined; docs/how-to/mimic3.md explains each and how it differs from the
AI-Clinician code; the switches are in ``options``):
 1. all ICU stays;
 2. adults: age >= 18 at ICU admission (INTIME - DOB; MIMIC's shifted ages > 89 set to 91.4);
 3. suspected infection: a systemic antibiotic and a culture, culture <= 24 h after the
    antibiotic or antibiotic <= 72 h after the culture (Seymour et al. 2016; onset = the
    earlier of the pair, AI-Clinician's loop over antibiotics in time order), onset within
    [INTIME - 48 h, OUTTIME + 48 h] (``suspected_infection``);
 4. SOFA >= 2: the maximum over 4 h blocks of [onset - 48 h, onset + 24 h] of a SOFA score
    from the components measurable in the raw tables (see ``max_sofa``), baseline 0; labs
    only in [INTIME - 1 d, OUTTIME + 1 d];
 5. mortality documented (ADMISSIONS.HOSPITAL_EXPIRE_FLAG present; the project's own);
 6. IV fluid / vasopressor intake documented (an INPUTEVENTS_MV/CV row; the project's own);
 7. treatment withdrawal excluded (AI-Clinician's rule in full: ``withdrawn``);
 8. anchor: t = 0 is fixed. ``intime``: t = 0 at INTIME (excludes nothing).
    ``first_vitals`` (default): t = 0 at INTIME + k h for the first whole hour k within the
    first ``anchor_window_h`` ICU hours whose block has every vital (HR, SysBP, DiaBP,
    MeanBP, RR, Temp_C) after BP completion and sample-and-hold; stays without one excluded;
 9. ICU stay covers hours 0..t_max after the anchor (OUTTIME >= t0 + (t_max + 1) h);
10. weight documented (charted in [INTIME - 72 h, OUTTIME]; hours without a weight charted
    at or before their end imputed from other stays, or, ``weight_missing="exclude"``, a
    weight charted or held in every hour);
11. the paper's change: every vital (HR, SysBP, DiaBP, MeanBP, RR, Temp_C) present in each
    hour t = 0..t_max after sample-and-hold;
12. imputable: weight and labs still missing after sample-and-hold have a 1-NN donor among
    other stays' rows of the same or an earlier hour.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd

from twinfalsify import schema
from twinfalsify.schema import ContractError
from twinfalsify.sources.consort import Consort

from . import doses, hourly
from .options import Mimic3Options
from .tables import (
    INTUBATED_VERBAL,
    MIMIC3,
    REQUIRED_COLUMNS,
    Layout,
    connect,
    data_table,
    diagnose,
    staged,
)

HOUR = pd.Timedelta(hours=1)
AGE_SHIFTED = 91.4  # MIMIC shifts DOB of patients > 89 y; AI-Clinician sets their age to 91.4


@dataclass
class Mimic3Cohort:
    trajectories: pd.DataFrame  # schema.TRAJECTORY_COLUMNS + schema.SUBJECT_ID
    consort: pd.DataFrame  # step, description, n_stays, n_excluded
    missingness: pd.DataFrame  # feature, t, n_missing_raw, share_missing_raw, n_imputed
    anchors: pd.DataFrame  # stay_id, intime, t0 (time of t = 0), anchor_h (t0 - INTIME, h)
    imputed: pd.DataFrame | None = None  # stay_id, t, weight + labs: True = imputed cell
    stays: pd.DataFrame | None = None  # per ICU stay: onset, SOFA, every criterion (_audit)
    options: dict | None = None  # the switches used (options.Mimic3Options)


def _ts(col: str) -> str:
    return f"TRY_CAST({col} AS TIMESTAMP)"


def _stays(con, layout: Layout = MIMIC3) -> pd.DataFrame:
    """Every ICU stay with its patient's age at INTIME (``age``), sex and the admission's
    mortality flag. Age: MIMIC-III ``(INTIME - DOB) / 365.25 d``, its shifted ages over 89
    (DOB about 300 years before) set to 91.4; MIMIC-IV (``layout.age == "anchor"``), where
    only the year is known, ``anchor_age + year(INTIME) - anchor_year``, its ages over 89
    (anchor_age 91) set to 91.4 likewise."""
    born = ("TRY_CAST(p.ANCHOR_AGE AS DOUBLE) AS anchor_age, "
            "TRY_CAST(p.ANCHOR_YEAR AS INTEGER) AS anchor_year" if layout.age == "anchor"
            else f"{_ts('p.DOB')} AS dob")
    df = con.execute(f"""
        SELECT CAST(i.ICUSTAY_ID AS BIGINT) AS icustay_id,
               CAST(i.SUBJECT_ID AS BIGINT) AS subject_id,
               CAST(i.HADM_ID AS BIGINT) AS hadm_id, i.DBSOURCE AS dbsource,
               {_ts('i.INTIME')} AS intime, {_ts('i.OUTTIME')} AS outtime,
               {born}, {_ts('p.DOD')} AS dod, p.GENDER AS gender,
               TRY_CAST(a.HOSPITAL_EXPIRE_FLAG AS INTEGER) AS hospital_expire_flag,
               {_ts('a.ADMITTIME')} AS admittime, {_ts('a.DISCHTIME')} AS dischtime
        FROM ICUSTAYS i
        JOIN PATIENTS p ON CAST(i.SUBJECT_ID AS BIGINT) = CAST(p.SUBJECT_ID AS BIGINT)
        LEFT JOIN ADMISSIONS a ON CAST(i.HADM_ID AS BIGINT) = CAST(a.HADM_ID AS BIGINT)
        ORDER BY icustay_id""").df()
    if layout.age == "anchor":
        birth_cols, birth_name = ["anchor_age", "anchor_year"], "anchor_age or anchor_year"
    else:
        birth_cols, birth_name = ["dob"], "DOB"
    bad = df["intime"].isna() | df[birth_cols].isna().any(axis=1)
    if bad.any():
        raise ContractError(f"ICUSTAYS/PATIENTS: {int(bad.sum())} stay(s) without INTIME or "
                            f"{birth_name}, e.g. ICUSTAY_ID {df.loc[bad, 'icustay_id'].iloc[0]}")
    if layout.age == "anchor":
        age = df["anchor_age"] + (df["intime"].dt.year - df["anchor_year"])
        df["age"] = np.where(df["anchor_age"] > 89, AGE_SHIFTED, age)
    else:
        age = (df["intime"] - df["dob"]).dt.total_seconds() / (365.25 * 86400)
        df["age"] = np.where(age > 150, AGE_SHIFTED, age)
    g = df["gender"].astype("string").str.upper().str.strip()
    df["sex"] = np.where(g == "F", 1.0, np.where(g == "M", 0.0, np.nan))
    return df.set_index("icustay_id", drop=False)


ONSET_WINDOW = pd.Timedelta(hours=48)  # AI-Clinician: events and onset in [in - 48 h, out + 48 h]
LAB_WINDOW = pd.Timedelta(days=1)  # AI-Clinician: labs kept in [INTIME - 1 d, OUTTIME + 1 d]


EVENT_STAY = ("nearest", "last")


def _assign_to_stays(events: pd.DataFrame, stays: pd.DataFrame, rule: str = "nearest"
                     ) -> pd.DataFrame:
    """Give each event (hadm_id, icustay_id or NaN, time) one ICU stay, as AI-Clinician
    fills icustay ids of antibiotics and cultures (sepsis-3 onset code):

    - an event with an ICUSTAY_ID keeps it (dropped if that stay is not among ``stays``);
    - otherwise a stay of the same admission with INTIME - 48 h <= time <= OUTTIME + 48 h;
      when several qualify, ``rule="nearest"`` takes the one whose [INTIME, OUTTIME] is
      nearest to the event (0 inside; ties: earlier INTIME), ``"last"`` the last by INTIME
      (AI-Clinician's loop, where a later match overwrites an earlier one);
    - when none qualifies, the admission's only stay, if it has one.

    Returns icustay_id, time (plus the other columns of ``events``)."""
    s = stays[["icustay_id", "hadm_id", "intime", "outtime"]].reset_index(drop=True)
    ev = events.reset_index(drop=True).assign(_row=lambda d: np.arange(len(d)))
    if "icustay_id" not in ev:
        ev["icustay_id"] = np.nan
    has = ev["icustay_id"].notna()
    direct = ev[has].astype({"icustay_id": "int64"})
    direct = direct[direct["icustay_id"].isin(s["icustay_id"])]
    rest = ev[~has].drop(columns="icustay_id")
    m = rest.merge(s, on="hadm_id")
    inwin = (m["time"] >= m["intime"] - ONSET_WINDOW) & (m["time"] <= m["outtime"] + ONSET_WINDOW)
    win = m[inwin]
    if rule == "last":
        win = win.sort_values(["_row", "intime"], kind="stable").drop_duplicates(
            "_row", keep="last")
    else:
        dist = np.maximum(np.maximum((win["intime"] - win["time"]) / HOUR,
                                     (win["time"] - win["outtime"]) / HOUR), 0.0)
        win = win.assign(_d=dist).sort_values(["_row", "_d", "intime"], kind="stable")
        win = win.drop_duplicates("_row", keep="first")
    n_per_adm = s.groupby("hadm_id")["icustay_id"].transform("count")
    only_ids = set(s.loc[n_per_adm == 1, "icustay_id"])
    only = m[~m["_row"].isin(win["_row"]) & m["icustay_id"].isin(only_ids)]
    keep = [c for c in events.columns if c not in ("icustay_id", "hadm_id")]
    out = pd.concat([direct[["icustay_id", *keep]], win[["icustay_id", *keep]],
                     only[["icustay_id", *keep]]], ignore_index=True)
    return out.astype({"icustay_id": "int64"})


def _link_by_time(ev: pd.DataFrame, stays: pd.DataFrame) -> tuple[pd.DataFrame, np.ndarray]:
    """Give each row of ``ev`` (hadm_id or NaN, subject_id, time) without an admission the
    admission of its patient whose [ADMITTIME, DISCHTIME] holds its time (the earliest such,
    if admissions overlap). Returns ``ev`` with hadm_id filled and a mask of the rows filled."""
    ev = ev.reset_index(drop=True)
    need = ev["hadm_id"].isna() & ev["time"].notna()
    filled = np.zeros(len(ev), dtype=bool)
    if not need.any():
        return ev, filled
    adm = (stays[["subject_id", "hadm_id", "admittime", "dischtime"]].dropna()
           .drop_duplicates("hadm_id").sort_values("admittime", kind="stable"))
    q = ev.loc[need, ["subject_id", "time"]].reset_index()
    m = q.merge(adm, on="subject_id")
    m = m[(m["time"] >= m["admittime"]) & (m["time"] <= m["dischtime"])]
    m = m.drop_duplicates("index", keep="first")
    ev.loc[m["index"].to_numpy(), "hadm_id"] = m["hadm_id"].to_numpy()
    filled[m["index"].to_numpy()] = True
    return ev, filled


def suspected_infection(con, stays: pd.DataFrame, event_stay: str = "nearest",
                        evidence: dict | None = None, screens: str = "exclude"
                        ) -> pd.DataFrame:
    """Onset of suspected infection per ICU stay (AI-Clinician's sepsis-3 onset rule).

    Antibiotics: PRESCRIPTIONS rows matching antibiotics.csv, time = STARTDATE, stay =
    PRESCRIPTIONS.ICUSTAY_ID when given. Cultures: MICROBIOLOGYEVENTS rows (time =
    CHARTTIME, else CHARTDATE) and CHARTEVENTS rows of the culture items of cultures.csv
    (AI-Clinician's culture query). Events without a stay get one by ``_assign_to_stays``
    (``event_stay``: the rule when several stays of the admission qualify). Screening swabs
    (screens.csv) are no cultures (``screens="exclude"``) or count as cultures
    (``"count"``, AI-Clinician); ``evidence["screens"]`` counts them per stay either way.
    Per stay, antibiotics are scanned in time order; for each, the nearest culture in time
    decides: culture within 24 h after (or at) the antibiotic -> onset = antibiotic time;
    culture within 72 h before -> onset = culture time (AI-Clinician sepsis3_def). An onset
    outside [INTIME - 48 h, OUTTIME + 48 h] is dropped (AI-Clinician keeps onsets only in
    that window; an admission's only stay can otherwise receive events from any time): such
    stays come back with ``in_window`` False.

    Returns a frame indexed by icustay_id: onset, onset_source ('antibiotic' | 'culture'),
    antibiotic_time, culture_time, in_window. ``evidence`` (a dict), when given, receives the
    stays with any antibiotic (``"antibiotic"``) and any culture (``"culture"``) assigned.
    """
    ab = data_table("antibiotics.csv")
    inc = ab.loc[ab["kind"] == "name_include", "pattern"].str.lower().tolist()
    exc = ab.loc[ab["kind"] == "name_exclude", "pattern"].str.lower().tolist()
    routes = ab.loc[ab["kind"] == "route_exclude", "pattern"].str.upper().tolist()
    con.register("abx_inc", pd.DataFrame({"p": inc}))
    con.register("abx_exc", pd.DataFrame({"p": exc}))
    con.register("abx_routes", pd.DataFrame({"r": routes}))
    abx = con.execute(f"""
        SELECT CAST(HADM_ID AS BIGINT) AS hadm_id, TRY_CAST(ICUSTAY_ID AS BIGINT) AS icustay_id,
               {_ts('STARTDATE')} AS time
        FROM PRESCRIPTIONS pr
        WHERE EXISTS (SELECT 1 FROM abx_inc WHERE contains(lower(pr.DRUG), abx_inc.p))
          AND NOT EXISTS (SELECT 1 FROM abx_exc WHERE contains(lower(pr.DRUG), abx_exc.p))
          AND upper(trim(coalesce(pr.ROUTE, ''))) NOT IN (SELECT r FROM abx_routes)
          AND HADM_ID IS NOT NULL AND STARTDATE IS NOT NULL""").df()
    # surveillance screens (MRSA, VRE, ...) are not cultures for a suspected infection
    scr = data_table("screens.csv")
    mcols = {x.upper() for x in con.execute("SELECT * FROM MICROBIOLOGYEVENTS LIMIT 0").df()}
    conds = [f"upper(trim(coalesce({col}, ''))) IN ("
             + ", ".join("'" + v.replace("'", "''") + "'" for v in g["value"].str.upper())
             + ")" for col, g in scr.groupby("column") if col in mcols]
    screen = " OR ".join(conds) or "FALSE"
    micro_all = con.execute(f"""
        SELECT TRY_CAST(HADM_ID AS BIGINT) AS hadm_id, CAST(NULL AS BIGINT) AS icustay_id,
               CAST(SUBJECT_ID AS BIGINT) AS subject_id,
               coalesce({_ts('CHARTTIME')}, {_ts('CHARTDATE')}) AS time,
               ({screen}) AS screen
        FROM MICROBIOLOGYEVENTS""").df()
    # a culture without HADM_ID (MIMIC-IV: outpatient and ED specimens among them) is linked
    # by patient and time to the admission whose [ADMITTIME, DISCHTIME] holds it (before:
    # dropped); one outside every admission stays unlinked
    micro_all, by_time = _link_by_time(micro_all, stays)
    micro_all = micro_all.assign(_by_time=by_time).drop(columns="subject_id")
    micro_all = micro_all[micro_all["hadm_id"].notna()]
    is_screen = micro_all["screen"].astype(bool)
    micro = (micro_all[~is_screen] if screens == "exclude" else micro_all).drop(columns="screen")
    screen_rows = micro_all[is_screen].drop(columns=["screen", "_by_time"])
    con.register("cult_items", data_table("cultures.csv")[["itemid"]].astype("int64"))
    chart = con.execute(f"""
        SELECT TRY_CAST(HADM_ID AS BIGINT) AS hadm_id, TRY_CAST(ICUSTAY_ID AS BIGINT) AS icustay_id,
               {_ts('CHARTTIME')} AS time
        FROM CHARTEVENTS
        WHERE TRY_CAST(ITEMID AS BIGINT) IN (SELECT itemid FROM cult_items)""").df()
    cult = pd.concat([micro.drop(columns="_by_time"), chart], ignore_index=True)
    cult = cult[cult["time"].notna() & (cult["hadm_id"].notna() | cult["icustay_id"].notna())]
    abx = abx[abx["time"].notna()]
    a = _assign_to_stays(abx, stays, event_stay).drop_duplicates()
    c = _assign_to_stays(cult, stays, event_stay).drop_duplicates()
    if evidence is not None:
        evidence["antibiotic"] = pd.Index(a["icustay_id"].unique())
        evidence["culture"] = pd.Index(c["icustay_id"].unique())
        linked = micro[micro["_by_time"].astype(bool)] if "_by_time" in micro else micro[:0]
        evidence["culture_by_time"] = (
            _assign_to_stays(linked.drop(columns="_by_time"), stays, event_stay)["icustay_id"]
            .value_counts() if len(linked) else pd.Series(dtype="int64"))
        scr_rows = screen_rows[screen_rows["time"].notna()]
        evidence["screens"] = (_assign_to_stays(scr_rows, stays, event_stay)["icustay_id"]
                               .value_counts() if len(scr_rows) else pd.Series(dtype="int64"))
    rows = {}
    cgroups = {k: np.sort(v["time"].to_numpy("datetime64[ns]")) for k, v in c.groupby("icustay_id")}
    for sid, g in a.groupby("icustay_id"):
        cs = cgroups.get(sid)
        if cs is None:
            continue
        for t_ab in np.sort(g["time"].to_numpy("datetime64[ns]")):
            d = np.abs(cs - t_ab)
            k = int(np.argmin(d))  # nearest culture (first one on ties, as MATLAB's min)
            gap_h = d[k] / np.timedelta64(1, "h")
            if gap_h <= 24 and t_ab <= cs[k]:
                rows[sid] = (pd.Timestamp(t_ab), "antibiotic", t_ab, cs[k])
                break
            if gap_h <= 72 and t_ab >= cs[k]:
                rows[sid] = (pd.Timestamp(cs[k]), "culture", t_ab, cs[k])
                break
    out = pd.DataFrame.from_dict(rows, orient="index",
                                 columns=["onset", "onset_source", "antibiotic_time",
                                          "culture_time"])
    out.index = out.index.astype("int64")
    out.index.name = "icustay_id"
    for col in ("onset", "antibiotic_time", "culture_time"):
        out[col] = pd.to_datetime(out[col])
    st = stays.reindex(out.index)
    out["in_window"] = ((out["onset"] >= st["intime"] - ONSET_WINDOW)
                        & (out["onset"] <= st["outtime"] + ONSET_WINDOW)).to_numpy()
    return out.sort_index()


# Verbal GCS charted as "intubated" (CareVue 723 '1.0 ET/Trach', MetaVision 223900
# 'No Response-ETT'): the verbal response cannot be assessed, so the charted 1 is not a
# measured verbal score (Teasdale & Jennett 1974; the MIMIC Code Repository's GCS concept
# treats such charting as not assessable). gcs_intubated = "not_assessable" drops the GCS
# total charted at that instant (CNS SOFA then has no value there); "verbal_1" keeps it.
# The items are tables.INTUBATED_VERBAL (staging keeps them too).
BLOOD_GAS = ("paO2", "paCO2", "Arterial_pH")  # arterial only: specimens.csv
MEASURED_DIASTOLIC = (220051, 220180)  # MetaVision ABPd / NBPd: bp_items = "measured" only
# GCS from RASS where no GCS is charted (AI-Clinician, after Wesley et al., JAMA 2003):
# RASS >= 0 -> 15, -1 -> 14, -2 -> 12, -3 -> 11, -4 -> 6, -5 -> 3
RASS_TO_GCS = {0: 15.0, -1: 14.0, -2: 12.0, -3: 11.0, -4: 6.0, -5: 3.0}


INCH = 2.54  # cm


def _heights(con, subjects) -> pd.DataFrame:
    """Body heights (cm) charted for ``subjects`` in any of their ICU stays: subject_id,
    time, height_cm (heights.csv items; a value in the other unit's adult range is taken in
    that unit; outside outlier_limits.csv ``height_cm`` deleted)."""
    items = data_table("heights.csv")[["itemid", "unit"]].astype({"itemid": "int64"})
    con.register("height_items", items)
    con.register("height_subj", pd.DataFrame({"subject_id": np.asarray(subjects, "int64")}))
    h = con.execute(f"""
        SELECT CAST(c.SUBJECT_ID AS BIGINT) AS subject_id, {_ts('c.CHARTTIME')} AS time,
               TRY_CAST(c.VALUENUM AS DOUBLE) AS value, i.unit
        FROM CHARTEVENTS c JOIN height_items i ON CAST(c.ITEMID AS BIGINT) = i.itemid
        WHERE CAST(c.SUBJECT_ID AS BIGINT) IN (SELECT subject_id FROM height_subj)
          AND coalesce(TRY_CAST(c.ERROR AS INTEGER), 0) = 0""").df()
    h = h.dropna(subset=["time", "value"])
    v, inch = h["value"].to_numpy(float), (h["unit"] == "in").to_numpy()
    as_cm = np.where(inch, v * INCH, v)
    as_cm = np.where(inch & (v >= 120) & (v <= 230), v, as_cm)  # cm in an inch item
    as_cm = np.where(~inch & (v >= 47) & (v <= 91), v * INCH, as_cm)  # inches in a cm item
    h = h.assign(height_cm=as_cm)
    h = h[hourly.within_limits("height_cm", h["height_cm"]).to_numpy()]
    return h[["subject_id", "time", "height_cm"]].sort_values("time", kind="stable")


def _bmi_implausible(con, subject: np.ndarray, time: np.ndarray, kg: np.ndarray) -> np.ndarray:
    """True where weight ``kg`` of patient ``subject`` at ``time`` has a BMI outside
    outlier_limits.csv ``bmi`` with the patient's last height charted at or before ``time``
    (``_heights``; never a later one); False where no height is known by then."""
    out = np.zeros(len(kg), dtype=bool)
    if not len(kg):
        return out
    q = pd.DataFrame({"row": np.arange(len(kg)), "time": pd.to_datetime(time),
                      "value": np.asarray(kg, float),
                      "subject_id": np.asarray(subject, "int64")})
    h = _heights(con, q["subject_id"].unique())
    if h.empty:
        return out
    q = pd.merge_asof(q.sort_values("time", kind="stable"), h, on="time", by="subject_id",
                      direction="backward")
    bmi = q["value"] / (q["height_cm"] / 100) ** 2
    bad = q["height_cm"].notna() & ~hourly.within_limits("bmi", bmi)
    out[q.loc[bad, "row"].to_numpy()] = True
    return out


def patient_weights(con, stays: pd.DataFrame, subjects) -> pd.DataFrame:
    """Every weight charted for ``subjects`` (any ICU stay, any time; items.csv ``weight``),
    in kg, outliers and weights implausible for the patient's height deleted, values of one
    instant averaged: subject_id, time, weight."""
    items = hourly.item_map()
    items = items[(items["feature"] == "weight") & (items["source"] == "chartevents")]
    con.register("wt_items", items[["itemid"]])
    con.register("wt_subj", pd.DataFrame({"subject_id": np.asarray(subjects, "int64")}))
    w = con.execute(f"""
        SELECT CAST(c.SUBJECT_ID AS BIGINT) AS icustay_id, {_ts('c.CHARTTIME')} AS time,
               CAST(c.ITEMID AS BIGINT) AS itemid, 'chartevents' AS source,
               TRY_CAST(c.VALUENUM AS DOUBLE) AS value
        FROM CHARTEVENTS c
        WHERE CAST(c.ITEMID AS BIGINT) IN (SELECT itemid FROM wt_items)
          AND CAST(c.SUBJECT_ID AS BIGINT) IN (SELECT subject_id FROM wt_subj)
          AND coalesce(TRY_CAST(c.ERROR AS INTEGER), 0) = 0""").df()
    w = hourly.delete_outliers(hourly.convert_values(w.dropna(subset=["time", "value"])))
    w = w.rename(columns={"icustay_id": "subject_id"})
    bad = _bmi_implausible(con, w["subject_id"].to_numpy(), w["time"].to_numpy(),
                           w["value"].to_numpy(float))
    w = w[~bad]
    return (w.groupby(["subject_id", "time"], as_index=False)["value"].mean()
            .rename(columns={"value": "weight"}))


OWN_WEIGHT_MAX_AGE = pd.Timedelta(days=90)  # see own_earlier_weight


def own_earlier_weight(con, stays: pd.DataFrame, held: pd.DataFrame, t0: pd.Series
                       ) -> pd.Series:
    """For each (icustay_id, t) of ``held`` without a weight: the lower median of the
    patient's last three plausible weights (``patient_weights``: outliers and weights
    implausible for the height already deleted, each instant averaged) charted strictly
    before the hour's start t0 + t h and at most ``OWN_WEIGHT_MAX_AGE`` (90 days) before it,
    in this stay or an earlier one (a body weight changes slowly; the patient's own is a
    better estimate than another patient's).

    The median of three, not the last value, so that one mis-charted weight is not carried:
    210164 charts 64.6 kg, then 263.2 kg the next day (no height known by then to reject it);
    its patient's next stay, 281609, starts from 64.6 kg, not 263.2. The *lower* median, so
    that the result is always a charted weight, never the mean of two disagreeing ones (70 kg
    and a mis-charted 234 "kg" give 70, not 152): a unit error (pounds in a kg item) makes a
    weight too high, not too low. At most 90 days old: critical illness and the months
    around it change the weight by more than the imputation's error (a patient loses muscle
    mass by the week in the ICU), and 90 days is the horizon of the outcome the project
    reads (90-day mortality); an older weight leaves the hour to the donor imputation.
    Returns the filled cells only."""
    miss = held.index[held["weight"].isna().to_numpy()]
    if not len(miss):
        return pd.Series(dtype=float, name="weight")
    k = miss.to_frame(index=False)
    k["start"] = t0.reindex(k["icustay_id"]).to_numpy() + k["t"].to_numpy() * HOUR
    k["subject_id"] = stays["subject_id"].reindex(k["icustay_id"]).to_numpy("int64")
    w = patient_weights(con, stays, k["subject_id"].unique())
    if w.empty:
        return pd.Series(dtype=float, name="weight")
    w = w.sort_values(["subject_id", "time"], kind="stable").reset_index(drop=True)
    w["pos"] = np.arange(len(w))
    hit = pd.merge_asof(k.sort_values("start", kind="stable"),
                        w.rename(columns={"time": "start"})[["subject_id", "start", "pos"]]
                        .sort_values("start", kind="stable"),
                        on="start", by="subject_id", allow_exact_matches=False,
                        direction="backward").dropna(subset=["pos"])
    last = hit["pos"].to_numpy("int64")
    subj, times, kg = (w["subject_id"].to_numpy(), w["time"].to_numpy("datetime64[ns]"),
                       w["weight"].to_numpy(float))
    oldest = hit["start"].to_numpy("datetime64[ns]") - OWN_WEIGHT_MAX_AGE.to_timedelta64()
    cand = np.full((len(hit), 3), np.nan)
    for j in range(3):  # the last three, same patient, within the age bound
        p = last - j
        ok = p >= 0
        ok[ok] &= (subj[p[ok]] == hit["subject_id"].to_numpy()[ok]) & (times[p[ok]] >= oldest[ok])
        cand[ok, j] = kg[p[ok]]
    n = np.isfinite(cand).sum(axis=1)
    srt = np.sort(cand, axis=1)  # NaN last
    val = np.where(n > 0, srt[np.arange(len(hit)), np.maximum(n - 1, 0) // 2], np.nan)
    hit = hit.assign(weight=val).dropna(subset=["weight"])
    return pd.Series(hit["weight"].to_numpy(), name="weight",
                     index=pd.MultiIndex.from_frame(hit[["icustay_id", "t"]])).sort_index()


def implausible_weight(con, stays: pd.DataFrame, ev: pd.DataFrame) -> np.ndarray:
    """True for each weight row of ``ev`` (icustay_id, time, feature, value in kg) whose BMI
    with the patient's last height charted at or before it (``_heights``, any of the
    patient's ICU stays, so never a later one) is outside outlier_limits.csv ``bmi``.
    Weights without a height known by then pass (the kg outlier limits still apply): e.g.
    234 'kg' (pounds in a kg item) at a height of 165 cm is BMI 86, deleted."""
    out = np.zeros(len(ev), dtype=bool)
    w = ev["feature"].to_numpy() == "weight"
    if not w.any():
        return out
    subj = stays["subject_id"].reindex(ev["icustay_id"].to_numpy()[w]).to_numpy("int64")
    out[np.flatnonzero(w)] = _bmi_implausible(con, subj, ev["time"].to_numpy()[w],
                                              ev["value"].to_numpy(float)[w])
    return out


def _events(con, stays: pd.DataFrame, lo: pd.Series, hi: pd.Series, features,
            opts: Mimic3Options | None = None, dropped: list | None = None,
            counts: dict | None = None) -> pd.DataFrame:
    """Charted and lab values of ``features`` for ``stays`` between lo and hi (per stay),
    converted to contract units, outliers deleted. Filtering happens in DuckDB. Lab values
    only in [INTIME - 1 d, OUTTIME + 1 d] (AI-Clinician's lab window). Weights implausible
    for the patient's height are deleted (``implausible_weight``; appended to ``dropped``
    when given). A charted mean pressure above the systolic or below the diastolic of the
    same device charted at the same time is deleted (``hourly.map_outside_range``, references
    from ``_bp_references``; ``counts["map_outside"]`` receives the rows per stay when
    ``counts`` is given). ``opts``: the item switches
    (bp_items, gcs_intubated, sofa: which GCS items make ``sofa_gcs``; fio2_lab: the
    blood-gas FiO2 read or not; venous_gas: venous blood gases deleted or kept)."""
    opts = opts or Mimic3Options()
    wanted = tuple(features)
    items = hourly.item_map()
    items = items[items["feature"].isin(features)]
    if opts.bp_items == "ai_clinician":
        items = items[~items["itemid"].isin(MEASURED_DIASTOLIC)]
    if opts.fio2_lab == "ignore":  # AI-Clinician: the charted FiO2 only, no blood-gas FiO2
        items = items[~((items["feature"] == "sofa_fio2") & (items["source"] == "labevents"))]
    win = pd.DataFrame({"icustay_id": stays.index.to_numpy(),
                        "hadm_id": stays["hadm_id"].to_numpy(),
                        "subject_id": stays["subject_id"].to_numpy(),
                        "admittime": stays["admittime"].to_numpy(),
                        "dischtime": stays["dischtime"].to_numpy(),
                        "lo": lo.reindex(stays.index).to_numpy(),
                        "hi": hi.reindex(stays.index).to_numpy(),
                        "lab_lo": (stays["intime"] - LAB_WINDOW).to_numpy(),
                        "lab_hi": (stays["outtime"] + LAB_WINDOW).to_numpy()})
    con.register("win", win)
    con.register("items_chart", items.loc[items["source"] == "chartevents", ["itemid"]])
    con.register("items_lab", items.loc[items["source"] == "labevents", ["itemid"]])
    ce = con.execute(f"""
        SELECT w.icustay_id, {_ts('c.CHARTTIME')} AS time, CAST(c.ITEMID AS BIGINT) AS itemid,
               'chartevents' AS source, TRY_CAST(c.VALUENUM AS DOUBLE) AS value
        FROM CHARTEVENTS c JOIN win w ON CAST(c.ICUSTAY_ID AS BIGINT) = w.icustay_id
        WHERE CAST(c.ITEMID AS BIGINT) IN (SELECT itemid FROM items_chart)
          AND coalesce(TRY_CAST(c.ERROR AS INTEGER), 0) = 0
          AND {_ts('c.CHARTTIME')} BETWEEN w.lo AND w.hi""").df()
    # a lab row without HADM_ID (about 2 % of MIMIC-IV's in-hospital labs) is linked by
    # patient and time: charted within [ADMITTIME, DISCHTIME] of the stay's admission
    le = con.execute(f"""
        SELECT w.icustay_id, {_ts('l.CHARTTIME')} AS time, CAST(l.ITEMID AS BIGINT) AS itemid,
               'labevents' AS source, TRY_CAST(l.VALUENUM AS DOUBLE) AS value,
               FALSE AS by_time
        FROM LABEVENTS l JOIN win w ON TRY_CAST(l.HADM_ID AS BIGINT) = w.hadm_id
        WHERE CAST(l.ITEMID AS BIGINT) IN (SELECT itemid FROM items_lab)
          AND {_ts('l.CHARTTIME')} BETWEEN w.lo AND w.hi
          AND {_ts('l.CHARTTIME')} BETWEEN w.lab_lo AND w.lab_hi
        UNION ALL
        SELECT w.icustay_id, {_ts('l.CHARTTIME')} AS time, CAST(l.ITEMID AS BIGINT) AS itemid,
               'labevents' AS source, TRY_CAST(l.VALUENUM AS DOUBLE) AS value,
               TRUE AS by_time
        FROM LABEVENTS l JOIN win w ON CAST(l.SUBJECT_ID AS BIGINT) = w.subject_id
        WHERE TRY_CAST(l.HADM_ID AS BIGINT) IS NULL
          AND CAST(l.ITEMID AS BIGINT) IN (SELECT itemid FROM items_lab)
          AND {_ts('l.CHARTTIME')} BETWEEN w.admittime AND w.dischtime
          AND {_ts('l.CHARTTIME')} BETWEEN w.lo AND w.hi
          AND {_ts('l.CHARTTIME')} BETWEEN w.lab_lo AND w.lab_hi""").df()
    if counts is not None:
        counts["lab_by_time"] = le.loc[le["by_time"].astype(bool), "icustay_id"].value_counts()
    le = le.drop(columns="by_time")
    gas = set(items.loc[(items["source"] == "labevents")
                        & items["feature"].isin(BLOOD_GAS), "itemid"].astype("int64"))
    if gas and len(le) and opts.venous_gas == "exclude":
        # a blood gas drawn from venous blood is not an arterial one (specimens.csv)
        con.register("spec_rules", data_table("specimens.csv")[["itemid", "value", "arterial"]])
        ven = con.execute(f"""
            SELECT DISTINCT w.icustay_id, {_ts('l.CHARTTIME')} AS time
            FROM LABEVENTS l JOIN win w ON CAST(l.HADM_ID AS BIGINT) = w.hadm_id
            JOIN spec_rules r ON CAST(l.ITEMID AS BIGINT) = r.itemid
                             AND upper(trim(l.VALUE)) = r.value
            WHERE r.arterial = 0
              AND {_ts('l.CHARTTIME')} BETWEEN w.lo AND w.hi""").df()
        hit = le["itemid"].isin(gas).to_numpy() & pd.MultiIndex.from_frame(
            le[["icustay_id", "time"]]).isin(pd.MultiIndex.from_frame(ven)) if len(ven) else (
            np.zeros(len(le), dtype=bool))
        if counts is not None:
            counts["venous_gas"] = le.loc[hit, "icustay_id"].value_counts()
        le = le[~hit]
    ev = pd.concat([ce, le], ignore_index=True).dropna(subset=["value", "time"])
    ev = hourly.delete_outliers(hourly.convert_values(ev))
    if "MeanBP" in wanted:
        is_map = (ev["feature"] == "MeanBP").to_numpy()
        bad_map = np.zeros(len(ev), dtype=bool)
        bad_map[is_map] = hourly.map_outside_range(ev[is_map], _bp_references(con))
        if counts is not None:
            counts["map_outside"] = ev.loc[bad_map, "icustay_id"].value_counts()
        ev = ev[~bad_map].reset_index(drop=True)
    if "weight" in features:
        bad = implausible_weight(con, stays, ev)
        if dropped is not None:
            dropped.append(ev[bad])
        ev = ev[~bad].reset_index(drop=True)
    gcs = ev["feature"].isin(["sofa_gcs", "sofa_gcs_component"])
    if gcs.any() and opts.gcs_intubated == "not_assessable":
        cond = " OR ".join(f"(CAST(c.ITEMID AS BIGINT) = {i} AND c.VALUE LIKE '{v}')"
                           for i, v in INTUBATED_VERBAL)
        ett = con.execute(f"""
            SELECT DISTINCT w.icustay_id, {_ts('c.CHARTTIME')} AS time
            FROM CHARTEVENTS c JOIN win w ON CAST(c.ICUSTAY_ID AS BIGINT) = w.icustay_id
            WHERE ({cond}) AND {_ts('c.CHARTTIME')} BETWEEN w.lo AND w.hi""").df()
        key = pd.MultiIndex.from_frame(ev[["icustay_id", "time"]])
        hit = key.isin(pd.MultiIndex.from_frame(ett[["icustay_id", "time"]])) if len(ett) else (
            np.zeros(len(ev), bool))
        ev = ev[~(gcs.to_numpy() & hit)].reset_index(drop=True)
    if opts.sofa == "ai_clinician":
        # AI-Clinician: CareVue GCS total only; RASS-estimated GCS where none is charted
        ev = ev[ev["feature"] != "sofa_gcs_component"]
        rass = ev[ev["feature"] == "sofa_rass"]
        ev = ev[ev["feature"] != "sofa_rass"]
        if len(rass):
            est = rass["value"].round().clip(upper=0).map(RASS_TO_GCS)
            rass = rass.assign(feature="sofa_gcs", value=est.to_numpy())
            have = pd.MultiIndex.from_frame(ev.loc[ev["feature"] == "sofa_gcs",
                                                   ["icustay_id", "time"]])
            rass = rass[~pd.MultiIndex.from_frame(rass[["icustay_id", "time"]]).isin(have)]
            ev = pd.concat([ev, rass.dropna(subset=["value"])], ignore_index=True)
    else:
        ev = ev[ev["feature"] != "sofa_rass"]
    # GCS (MetaVision): eye + verbal + motor charted together -> total
    comp = ev[ev["feature"] == "sofa_gcs_component"]
    if len(comp):
        g = comp.groupby(["icustay_id", "time"])["value"].agg(["sum", "count"]).reset_index()
        g = g[g["count"] == 3]
        ev = pd.concat([ev[ev["feature"] != "sofa_gcs_component"],
                        pd.DataFrame({"icustay_id": g["icustay_id"], "time": g["time"],
                                      "feature": "sofa_gcs", "value": g["sum"]})],
                       ignore_index=True)
    return ev[["icustay_id", "time", "feature", "value"]]


def _bp_references(con) -> pd.DataFrame:
    """The systolic and diastolic pressures of bp_devices.csv charted in the stays and
    window of the table ``win`` (registered by ``_events``), outliers deleted as their
    feature's: the MAP check's references (``hourly.map_outside_range``). Read whatever
    ``bp_items`` says, so that the check has the same-device diastolic either way."""
    dev = hourly.bp_devices()
    dev = dev[dev["role"].isin(["sys", "dia"])]
    con.register("bp_ref_items", dev[["itemid"]])
    r = con.execute(f"""
        SELECT w.icustay_id, {_ts('c.CHARTTIME')} AS time, CAST(c.ITEMID AS BIGINT) AS itemid,
               TRY_CAST(c.VALUENUM AS DOUBLE) AS value
        FROM CHARTEVENTS c JOIN win w ON CAST(c.ICUSTAY_ID AS BIGINT) = w.icustay_id
        WHERE CAST(c.ITEMID AS BIGINT) IN (SELECT itemid FROM bp_ref_items)
          AND coalesce(TRY_CAST(c.ERROR AS INTEGER), 0) = 0
          AND {_ts('c.CHARTTIME')} BETWEEN w.lo AND w.hi""").df().dropna(subset=["time", "value"])
    feat = r["itemid"].map(dev.set_index("itemid")["role"].map(hourly.BP_ROLES))
    ok = pd.Series(False, index=r.index)
    for f in ("SysBP", "DiaBP"):
        m = feat == f
        ok[m] = hourly.within_limits(f, r.loc[m, "value"])
    return r[ok.to_numpy()]


def _inputs(con, ids, lo: pd.Series, hi: pd.Series, rewritten: str = "exclude",
            implausible: list | None = None) -> tuple[pd.DataFrame, ...]:
    """Fluid and vasopressor rows (MetaVision, CareVue) of stays ``ids`` overlapping [lo, hi].
    MetaVision 'Rewritten' rows are dropped (``rewritten="exclude"``) or, as AI-Clinician,
    dropped for vasopressors only (``"ai_clinician"``). A row whose dose is outside
    dose_limits.csv (``doses.dose_plausible``) is dropped; ``implausible`` (a list), when
    given, receives the stay ids of the dropped rows. PATIENTWEIGHT is read for
    norepinephrine charted in the wrong unit (vasopressors.csv)."""
    win = pd.DataFrame({"icustay_id": np.asarray(ids, dtype="int64"),
                        "lo": lo.reindex(ids).to_numpy(), "hi": hi.reindex(ids).to_numpy()})
    con.register("win_in", win)
    fl = data_table("fluids.csv")[["itemid"]].astype("int64")
    va = data_table("vasopressors.csv")[["itemid"]].drop_duplicates().astype("int64")
    con.register("fl_items", fl)
    con.register("va_items", va)
    mv_sel = f"""SELECT w.icustay_id, CAST(m.ITEMID AS BIGINT) AS itemid,
               {_ts('m.STARTTIME')} AS starttime, {_ts('m.ENDTIME')} AS endtime,
               TRY_CAST(m.AMOUNT AS DOUBLE) AS amount, TRY_CAST(m.RATE AS DOUBLE) AS rate,
               m.RATEUOM AS rateuom, coalesce(m.STATUSDESCRIPTION, '') AS status,
               TRY_CAST(m.PATIENTWEIGHT AS DOUBLE) AS patientweight
        FROM INPUTEVENTS_MV m JOIN win_in w ON CAST(m.ICUSTAY_ID AS BIGINT) = w.icustay_id
        WHERE {_ts('m.STARTTIME')} <= w.hi AND {_ts('m.ENDTIME')} >= w.lo"""
    cv_sel = f"""SELECT w.icustay_id, CAST(c.ITEMID AS BIGINT) AS itemid,
               {_ts('c.CHARTTIME')} AS charttime, TRY_CAST(c.AMOUNT AS DOUBLE) AS amount,
               TRY_CAST(c.RATE AS DOUBLE) AS rate, c.RATEUOM AS rateuom
        FROM INPUTEVENTS_CV c JOIN win_in w ON CAST(c.ICUSTAY_ID AS BIGINT) = w.icustay_id
        WHERE {_ts('c.CHARTTIME')} BETWEEN w.lo AND w.hi"""
    def q(sel: str, items: str, notnull: str, cond: str = "TRUE") -> pd.DataFrame:
        return con.execute(f"SELECT * FROM ({sel}) WHERE itemid IN (SELECT itemid FROM {items})"
                           f" AND {notnull} IS NOT NULL AND {cond}").df()
    not_rewritten = "status <> 'Rewritten'"
    mv_f = q(mv_sel, "fl_items", "amount",
             "TRUE" if rewritten == "ai_clinician" else not_rewritten)
    mv_v = q(mv_sel, "va_items", "rate", not_rewritten)
    cv_f, cv_v = q(cv_sel, "fl_items", "amount"), q(cv_sel, "va_items", "rate")
    out = []
    for frame, action, system in ((mv_f, "iv_fluid", "mv"), (cv_f, "iv_fluid", "cv"),
                                  (mv_v, "vasopressor", "mv"), (cv_v, "vasopressor", "cv")):
        dose = (frame["amount"] if action == "iv_fluid"
                else doses.norepinephrine_equivalent(frame, system)) if len(frame) else (
            pd.Series(dtype=float))
        ok = doses.dose_plausible(dose, action).to_numpy(bool)
        if implausible is not None:
            implausible.append(frame.loc[~ok, "icustay_id"])
        out.append(frame[ok].reset_index(drop=True))
    return tuple(out)


VASO_DECIMALS = 3  # SOFA reads the norepinephrine-equivalent rate to 3 decimals (sofa_components)


def round_half_up(x: pd.Series, decimals: int) -> pd.Series:
    """``x`` rounded as PostgreSQL's ``round(cast(x as numeric), decimals)`` rounds it (the
    rounding of AI-Clinician's vasopressor queries): the double read as its 15 significant
    digits, then halves away from zero (0.1005 -> 0.101, where binary rounding gives 0.1)."""
    step = Decimal(1).scaleb(-decimals)

    def one(v: float) -> float:
        if not np.isfinite(v):
            return v
        return float(Decimal(format(v, ".15g")).quantize(step, rounding=ROUND_HALF_UP))

    uniq = pd.unique(x.to_numpy(float))  # few distinct rates among many rows
    return x.map(dict(zip(uniq, map(one, uniq), strict=True))).astype(float)


SOFA_ORGANS = ("respiration", "coagulation", "liver", "cardiovascular", "cns", "renal")


def sofa_components(b: pd.DataFrame) -> pd.DataFrame:
    """SOFA points per organ (Vincent et al. 1996) per row from block means, AI-Clinician's
    thresholds; columns ``SOFA_ORGANS``.

    Columns used (NaN component -> 0 points): pf (PaO2/FiO2 mmHg), sofa_platelets (10^3/uL),
    sofa_bilirubin (mg/dL), MeanBP (mmHg), vaso (NE-eq ug/kg/min, max; read to 3 decimals),
    sofa_gcs, sofa_creatinine (mg/dL), optionally uo (urine output of the 4 h block, mL; NaN = not
    charted, no points). Ventilation is not used.
    """
    def pts(conds):
        out = np.zeros(len(b))
        for p, c in enumerate(conds):
            out = np.where(np.asarray(c, dtype=bool), p, out)  # later (worse) wins
        return out
    pf, plt, bil = b["pf"], b["sofa_platelets"], b["sofa_bilirubin"]
    # the rate compared with the 0.1 ug/kg/min threshold to 3 decimals, as AI-Clinician's
    # vasopressor queries standardise it (round(rate_std, 3)): MetaVision charts the rate its
    # pump computed, e.g. norepinephrine 0.100104 or dopamine 10.008 (x 0.01 = 0.10008) for an
    # ordered 0.1 / 10, which scored 4 points instead of SOFA's 3 (dopamine 5-15: 3 points)
    mapp, gcs, cr = b["MeanBP"], b["sofa_gcs"], b["sofa_creatinine"]
    vaso = round_half_up(b["vaso"].fillna(0), VASO_DECIMALS)
    uo = b["uo"] if "uo" in b else pd.Series(np.nan, index=b.index)
    return pd.DataFrame({
        "respiration": pts([pf > 400, pf < 400, pf < 300, pf < 200, pf < 100]),
        "coagulation": pts([plt > 150, plt < 150, plt < 100, plt < 50, plt < 20]),
        "liver": pts([bil < 1.2, bil >= 1.2, bil >= 2, bil >= 6, bil > 12]),
        "cardiovascular": pts([mapp >= 70, mapp < 70, mapp < 65, (vaso > 0) & (vaso <= 0.1),
                               vaso > 0.1]),
        "cns": pts([gcs > 14, gcs <= 14, gcs <= 12, gcs <= 9, gcs <= 5]),
        # urine output of the 4 h block (sofa=ai_clinician only): < 84 mL (500 mL/day) 3,
        # < 34 mL (200 mL/day) 4 points, AI-Clinician's thresholds
        "renal": pts([cr < 1.2, cr >= 1.2, cr >= 2, (cr >= 3.5) | (uo < 84), (cr > 5) | (uo < 34)]),
    }, index=b.index)


SOFA_FEATURES = ("MeanBP", "paO2", "sofa_fio2", "sofa_platelets", "sofa_bilirubin", "sofa_gcs",
                 "sofa_gcs_component", "sofa_rass", "sofa_creatinine")
BLOCK_FEATURES = ("MeanBP", "paO2", "sofa_fio2", "sofa_platelets", "sofa_bilirubin", "sofa_gcs",
                  "sofa_creatinine")


def urine_items(opts: Mimic3Options | None = None) -> pd.DataFrame:
    """The rows of urine.csv read under ``opts``: a row whose ``read_when`` names a switch
    and a value (``urine_irrigant=subtract``, ``tf_residual=count``) only when that switch
    has that value."""
    opts = opts or Mimic3Options()
    u = data_table("urine.csv")
    cond = u["read_when"].fillna("").astype(str).str.strip()
    keep = [not c or getattr(opts, c.split("=")[0]) == c.split("=")[1] for c in cond]
    return u[np.asarray(keep, dtype=bool)]


def _urine(con, ids, lo: pd.Series, n_blocks: int,
           opts: Mimic3Options | None = None) -> pd.Series:
    """Urine output (mL) per 4 h block of [lo, lo + 4 n_blocks h): the sum of OUTPUTEVENTS
    rows of the items of urine.csv charted in the block (AI-Clinician's output_4hourly), the
    GU irrigant put in (sign -1) subtracted within its own charting time (the irrigant
    charted at a time comes back out in the urine charted then; mimic-code's
    urine_output.sql sums per charting time too), never below 0 mL there: a charting time
    with only irrigant is no urine row;
    blocks without a row are missing (AI-Clinician's nansum would make them 0 mL, i.e.
    4 renal points for any block where no urine was charted). ``opts``: which items
    (``urine_items``: the irrigant and the tube-feed residual are switches)."""
    win = pd.DataFrame({"icustay_id": np.asarray(ids, dtype="int64"),
                        "lo": lo.reindex(ids).to_numpy(),
                        "hi": (lo + 4 * n_blocks * HOUR).reindex(ids).to_numpy()})
    con.register("win_uo", win)
    con.register("uo_items", urine_items(opts)[["itemid", "sign"]].astype("int64"))
    # sign -1: GU irrigant volume in, subtracted (only a positive volume, as the MIMIC-IV
    # concept code), so that irrigation returned through the catheter is not urine
    u = con.execute(f"""
        SELECT icustay_id, time, greatest(sum(value), 0) AS value FROM (
            SELECT w.icustay_id, {_ts('o.CHARTTIME')} AS time, i.sign,
                   CASE WHEN i.sign < 0 THEN -greatest(TRY_CAST(o.VALUE AS DOUBLE), 0)
                        ELSE TRY_CAST(o.VALUE AS DOUBLE) END AS value
            FROM OUTPUTEVENTS o JOIN win_uo w ON CAST(o.ICUSTAY_ID AS BIGINT) = w.icustay_id
            JOIN uo_items i ON CAST(o.ITEMID AS BIGINT) = i.itemid
            WHERE {_ts('o.CHARTTIME')} >= w.lo AND {_ts('o.CHARTTIME')} < w.hi)
        WHERE value IS NOT NULL AND time IS NOT NULL
        GROUP BY icustay_id, time HAVING max(sign) > 0""").df()
    u = u.dropna()
    blk = ((u["time"].to_numpy() - lo.reindex(u["icustay_id"]).to_numpy()) // (4 * HOUR))
    return u.assign(blk=blk.astype("int64")).groupby(["icustay_id", "blk"])["value"].sum()


def hold_blocks(b: pd.DataFrame, width_h: float) -> pd.DataFrame:
    """Carry each SOFA component of ``BLOCK_FEATURES`` into later blocks of its stay that lack
    it, for at most its AI-Clinician hold time (sample_and_hold.csv: MAP 2 h, GCS 6 h, PaO2
    8 h, FiO2 12 h, platelets / bilirubin / creatinine 28 h): block b takes the value of the
    stay's last earlier block b' with one when (b - b') x ``width_h`` <= hold, the distance
    AI-Clinician's SAH.m measures between its 4 h records. Other columns (urine output: not
    in AI-Clinician's matrix) are not carried. ``b`` is indexed by (icustay_id, blk)."""
    hold = data_table("sample_and_hold.csv").set_index("feature")["hold_hours"]
    out = b.copy()
    blk = pd.Series(b.index.get_level_values(1).to_numpy("float64"), index=b.index)
    for c in BLOCK_FEATURES:
        if c not in out or c not in hold.index:
            continue
        seen = blk.where(out[c].notna()).groupby(level=0).ffill()
        filled = out[c].groupby(level=0).ffill()
        ok = out[c].isna() & ((blk - seen) * width_h <= float(hold[c]))
        out[c] = out[c].where(~ok, filled)
    return out


CARRY = ("none", "hold", "unlimited")


def block_sofa(con, stays: pd.DataFrame, start: pd.Series, n_blocks: int, *,
               carry: str = "none", opts: Mimic3Options | None = None) -> pd.DataFrame:
    """SOFA points per organ in 4 h blocks [start + 4 b h, start + 4 (b + 1) h),
    b = 0..n_blocks - 1, for the stays of ``start`` (index icustay_id).

    Block means of the charted / lab values (no imputation); vasopressor = max
    NE-equivalent rate running in the block. ``carry`` (``CARRY``): a component missing in a
    block takes the stay's last earlier block value for at most its AI-Clinician hold time
    (``"hold"``: ``hold_blocks``; AI-Clinician's SOFA is computed after sample-and-hold),
    without a limit (``"unlimited"``: the withdrawal rule's stand-in for AI-Clinician's
    imputed record) or not at all (``"none"``). ``opts.sofa``: which GCS items, and whether
    the block's urine output counts (``_urine``). Returns a frame indexed by
    (icustay_id, blk) with ``SOFA_ORGANS``, ``sofa`` and ``vaso``."""
    opts = opts or Mimic3Options()
    ids = start.index
    lo, hi = start, start + 4 * n_blocks * HOUR
    ev = _events(con, stays.loc[ids], lo, hi, SOFA_FEATURES, opts)
    ev = ev.assign(blk=((ev["time"].to_numpy() - start.reindex(ev["icustay_id"]).to_numpy())
                        // (4 * HOUR)).astype("int64"))
    ev = ev[(ev["blk"] >= 0) & (ev["blk"] < n_blocks)]
    b = ev.pivot_table(index=["icustay_id", "blk"], columns="feature", values="value",
                       aggfunc="mean")
    idx = pd.MultiIndex.from_product([ids, range(n_blocks)], names=["icustay_id", "blk"])
    b = b.reindex(idx)
    for c in BLOCK_FEATURES:
        if c not in b:
            b[c] = np.nan
    if opts.sofa == "ai_clinician":
        b["uo"] = _urine(con, ids, lo, n_blocks, opts).reindex(idx).to_numpy()
    if carry not in CARRY:
        raise ValueError(f"block_sofa: carry must be one of {CARRY}, got {carry!r}")
    if carry == "hold":
        b = hold_blocks(b, 4)
    elif carry == "unlimited":
        b = b.groupby(level=0).ffill()
    b["pf"] = b["paO2"] / (b["sofa_fio2"] / 100)
    _, _, mv_v, cv_v = _inputs(con, ids, lo, hi, opts.rewritten)
    vaso = doses.hourly_vasopressor(lo, mv_v, cv_v, n_blocks - 1, width=4 * HOUR)
    vaso.index.names = idx.names
    b["vaso"] = vaso.reindex(idx).to_numpy()
    out = sofa_components(b)
    out["sofa"] = out[list(SOFA_ORGANS)].sum(axis=1)
    out["vaso"] = b["vaso"].to_numpy()
    return out


def max_sofa(con, stays: pd.DataFrame, onset: pd.Series,
             opts: Mimic3Options | None = None) -> pd.DataFrame:
    """Max over the eighteen 4 h blocks of [onset - 48 h, onset + 24 h) of the block SOFA
    (``block_sofa``), each component carried forward from the last earlier block of the
    window that has it for at most its hold time (``hold_blocks``: AI-Clinician scores SOFA on
    values sample-and-held that long; without carrying,
    ``opts.sofa_carry = "none"``, a block scores only what was charted in those 4 h, and the
    maximum understates).
    Returns, per stay, ``max_sofa`` and ``sofa_organs``: the organs scoring >= 1 point in the
    first block reaching the maximum (';'-joined)."""
    opts = opts or Mimic3Options()
    blocks = block_sofa(con, stays, onset - 48 * HOUR, 18,
                        carry="hold" if opts.sofa_carry == "carry" else "none", opts=opts)
    first = blocks["sofa"].groupby(level=0).idxmax()  # first block with the maximum
    best = blocks.loc[first.to_numpy()]
    organs = best[list(SOFA_ORGANS)].apply(
        lambda r: ";".join(f"{o}={int(r[o])}" for o in SOFA_ORGANS if r[o] > 0), axis=1)
    return pd.DataFrame({"max_sofa": best["sofa"].to_numpy(),
                         "sofa_organs": organs.to_numpy()},
                        index=pd.Index(best.index.get_level_values(0), name="icustay_id"))


WITHDRAWAL_INPUTS = ("died_within_90d", "stay_blocks_4h", "max_block_vaso", "last_block_vaso",
                     "max_block_sofa", "last_block_sofa")


def withdrawn(con, stays: pd.DataFrame, opts: Mimic3Options | None = None,
              inputs: dict | None = None) -> pd.Index:
    """Stays flagged as treatment withdrawal, AI-Clinician's 'exclude early deaths from
    possible withdrawals' (source and parameters: data/mimic3/withdrawal.csv) on 4 h blocks
    of the whole ICU stay from INTIME: all of

    - died within 90 days of ICU admission (mortality_90d);
    - the stay has fewer than 20 blocks of 4 h (OUTTIME - INTIME < 80 h);
    - the maximum block vasopressor (max NE-equivalent rate, ug/kg/min) > 0.3;
    - no vasopressor in the last block (max_dose_vaso == 0);
    - SOFA of the last block >= half the maximum block SOFA over the stay.

    AI-Clinician's record is [onset - 24 h, onset + 48 h] in 4 h blocks of sample-and-held,
    imputed values; here it is the ICU stay, and SOFA components are carried forward over
    blocks without a time limit (``block_sofa(carry="unlimited")``), the nearest equivalent
    without imputation (the SOFA >= 2 criterion holds each only for its hold time).
    ``inputs`` (a dict), when given, receives a frame of the rule's inputs per stay
    (``WITHDRAWAL_INPUTS``; the block values only for the stays that died early with a short
    stay, the others need no more).
    """
    par = data_table("withdrawal.csv").set_index("parameter")["value"].astype(float)
    width = par["block_hours"] * HOUR
    max_blocks = int(par["max_blocks"])
    s = stays
    died = s["dod"].notna() & ((s["dod"] - s["intime"])
                               <= pd.Timedelta(days=float(par["died_within_days"])))
    n_blk = np.ceil((s["outtime"] - s["intime"]) / width).clip(lower=1)
    cand = s.index[(died & (n_blk < max_blocks)).to_numpy()]
    table = pd.DataFrame({"died_within_90d": died.to_numpy(bool),
                          "stay_blocks_4h": n_blk.to_numpy("int64")}, index=s.index)
    if inputs is not None:
        inputs["frame"] = table.reindex(columns=list(WITHDRAWAL_INPUTS))
    if not len(cand):
        return pd.Index([], dtype="int64")
    # carried without a limit: AI-Clinician's record has every component in every block
    # (held, then interpolated and imputed), so its last block always scores every organ
    blocks = block_sofa(con, s.loc[cand], s.loc[cand, "intime"], max_blocks - 1,
                        carry="unlimited", opts=opts)
    last = n_blk.loc[cand].astype("int64") - 1
    keep = blocks.index.get_level_values("blk").to_numpy() <= last.reindex(
        blocks.index.get_level_values(0)).to_numpy()
    blocks = blocks[keep]
    mx = blocks.groupby(level=0)[["sofa", "vaso"]].max()
    lastrow = blocks.groupby(level=0).tail(1).droplevel(1).reindex(mx.index)
    flag = ((mx["vaso"] > par["max_vaso_gt"]) & (lastrow["vaso"] == par["last_vaso_eq"])
            & (lastrow["sofa"] >= par["last_sofa_fraction"] * mx["sofa"]))
    if inputs is not None:
        t = inputs["frame"]
        for col, v in (("max_block_vaso", mx["vaso"]), ("last_block_vaso", lastrow["vaso"]),
                       ("max_block_sofa", mx["sofa"]), ("last_block_sofa", lastrow["sofa"])):
            t[col] = v.reindex(t.index).to_numpy(float)
    return pd.Index(mx.index[flag.to_numpy()], dtype="int64")


ANCHORS = ("intime", "first_vitals")
ANCHOR_WINDOW_H = 6  # first_vitals: the complete vital set must start within the first 6 ICU h


def first_complete_vitals(held: pd.DataFrame, window_h: int) -> pd.Series:
    """Per stay, the first hour block k in 0..window_h - 1 (block [INTIME + k h,
    INTIME + (k + 1) h)) in which every vital of ``hourly.VITALS`` is present after
    blood-pressure completion and sample-and-hold; stays without one are left out.

    ``held`` is indexed by (icustay_id, t) with t counted in hours from INTIME. Returns
    icustay_id -> k (int64), sorted by icustay_id.
    """
    ok = held[list(hourly.VITALS)].notna().all(axis=1).to_numpy()
    sid = held.index.get_level_values("icustay_id")[ok]
    k = held.index.get_level_values("t")[ok].to_numpy("int64")
    first = pd.Series(k, index=sid).groupby(level=0).min()
    first = first[first < window_h].astype("int64")
    first.index.name = "icustay_id"
    return first.rename("anchor_h")


def realign(frame: pd.DataFrame, offset_h: pd.Series, t_max: int) -> pd.DataFrame:
    """Re-index hourly blocks from INTIME-relative hours to anchor-relative hours:
    row (stay, k) becomes (stay, k - offset_h[stay]); only t = 0..t_max are kept, and only
    stays in ``offset_h``. Exact because blocks and anchors both sit on whole hours from
    INTIME, so anchor-relative block t *is* INTIME-relative block offset + t."""
    sid = frame.index.get_level_values("icustay_id")
    off = offset_h.reindex(sid).to_numpy("float64")  # NaN for stays without an anchor
    rel = frame.index.get_level_values("t").to_numpy("float64") - off
    keep = (rel >= 0) & (rel <= t_max)
    out = frame[keep].copy()
    out.index = pd.MultiIndex.from_arrays([sid[keep], rel[keep].astype("int64")],
                                          names=["icustay_id", "t"])
    return out.sort_index()


STEPS = ("all_icu_stays", "adult", "suspected_infection", "sofa_ge_2", "mortality_documented",
         "intake_documented", "not_withdrawn", "anchor", "stay_covers_window",
         "weight_documented", "vitals_complete", "stays_per_patient", "imputable")


def extract_mimic3(folder: Path, *, t_max: int = schema.T_MAX, threads: int = 1,
                   anchor: str = "first_vitals", anchor_window_h: int = ANCHOR_WINDOW_H,
                   options: Mimic3Options | None = None, memory_limit: str | None = None,
                   temp_directory: str | Path | None = None,
                   stage: bool = True, layout: Layout = MIMIC3) -> Mimic3Cohort:
    """Sepsis-3 cohort from the MIMIC-III v1.4 tables in ``folder`` as hourly trajectories
    (``layout``: another release's tables mapped onto MIMIC-III's, e.g. MIMIC-IV's:
    ``twinfalsify.sources.mimic4``).

    Trajectory row (stay, t): features over hour [T0 + t h, T0 + (t+1) h) (block means,
    sample-and-hold from before the hour, weight and labs still missing imputed by 1-NN from
    other stays' rows of hours <= t), iv_fluid (mL/h) and vasopressor (ug/kg/min) given
    during that hour, where the anchor T0 is

    - ``anchor="intime"``: ICU admission (INTIME), the paper's "first ICU hours";
    - ``anchor="first_vitals"``: INTIME + k h for the first whole hour k < ``anchor_window_h``
      whose block holds every vital (``first_complete_vitals``); stays without such a block
      are excluded at the CONSORT step ``anchor``.

    I/O (``tables``): ``memory_limit`` and ``temp_directory`` go to DuckDB; ``stage`` copies
    the large tables once, reduced to the columns and items read, to Parquet in a temporary
    folder (under ``temp_directory``) that every query then reads (same result, one pass
    over the CSV instead of one per query).

    ``options``: the switches of ``options.Mimic3Options`` (project defaults). Every
    criterion is evaluated for every stay where it is defined (``stays`` of the result, one
    row per ICU stay); the CONSORT chain applies them in the order of ``STEPS``. See the
    module docstring and docs/how-to/mimic3.md.
    """
    opts = options or Mimic3Options()
    if anchor not in ANCHORS:
        raise ContractError(f"{layout.kind} source: anchor must be one of {ANCHORS}, "
                            f"got {anchor!r}")
    if int(anchor_window_h) < 1:
        raise ContractError(f"{layout.kind} source: anchor_window_h must be >= 1, "
                            f"got {anchor_window_h}")
    folder = Path(folder)
    optional = ("OUTPUTEVENTS",) if opts.sofa == "ai_clinician" else ()
    con = connect(folder, threads=threads, optional=optional, memory_limit=memory_limit,
                  temp_directory=temp_directory, layout=layout)
    try:
        if not stage:
            return _extract(con, folder, t_max, anchor, int(anchor_window_h), opts, layout)
        with staged(con, temp_directory):
            return _extract(con, folder, t_max, anchor, int(anchor_window_h), opts, layout)
    except duckdb.Error as exc:  # damage deep in a file: name it, no traceback
        raise diagnose(folder, (*REQUIRED_COLUMNS, *optional), exc, layout) from None
    finally:
        con.close()


@dataclass
class _Hours:
    """The hourly blocks of every stay, on the anchor (``_hours``)."""

    raw: pd.DataFrame  # block means, (icustay_id, t) on the anchor, t = 0..t_max
    held: pd.DataFrame  # the same after sample-and-hold
    offset: pd.Series  # per anchored stay: hours from INTIME to t = 0
    t0: pd.Series  # per anchored stay: the time of t = 0
    full: pd.Index  # anchored stays with every hour 0..t_max
    anchor_desc: str  # the CONSORT step ``anchor``'s description
    n_implausible: pd.Series | None  # per stay: charted values set aside as implausible


@dataclass
class _Imputed:
    """The cohort's hours after the own-weight fill and 1-NN imputation (``_impute``)."""

    held: pd.DataFrame  # every feature of every hour, imputed where still missing
    missing_after_hold: pd.DataFrame  # weight and labs: True = still missing after the hold
    n_own_weight: pd.Series  # per stay: hours given the patient's own earlier weight
    weight_implausible: pd.Index  # stays whose imputed weight is implausible
    n_weight_stays: int  # stays with a weight imputed
    n_weight_hours: int  # stay-hours with a weight imputed


def _urine_rule_counts(con, opts: Mimic3Options) -> dict[str, pd.Series]:
    """Per stay, over the whole stay: the OUTPUTEVENTS rows of a GU irrigant subtracted from
    the urine output (``urine_irrigant``; 0 under ``ignore``) and the tube-feed residual rows
    left out of it (``tf_residual``; 0 under ``count``)."""
    read = set(urine_items(opts)["itemid"].astype("int64"))
    u = data_table("urine.csv")
    neg = u.loc[(u["sign"] < 0) & u["itemid"].isin(read), ["itemid"]].astype("int64")
    # urine items of AI-Clinician's list left out (tf_residual = exclude: 227510)
    left = u.loc[(u["sign"] > 0) & ~u["itemid"].isin(read), ["itemid"]].astype("int64")

    def count(items: pd.DataFrame) -> pd.Series:
        con.register("uo_rule", items)
        return con.execute("""
            SELECT CAST(ICUSTAY_ID AS BIGINT) AS icustay_id, count(*) AS n FROM OUTPUTEVENTS
            WHERE CAST(ITEMID AS BIGINT) IN (SELECT itemid FROM uo_rule)
            GROUP BY 1""").df().set_index("icustay_id")["n"]
    return {"urine_irrigant": count(neg),
            "tf_residual": count(left)}


AUDIT_CHUNK = 5000  # stays per pass of ``_rule_counts``: bounded memory on the full database
# the features whose rows a semantic rule sets aside (MAP check: MeanBP; venous gas: the
# blood gases) or links by time (every lab)
AUDIT_FEATURES = ("MeanBP", *hourly.LABS, "sofa_platelets", "sofa_bilirubin",
                  "sofa_creatinine")


def _rule_counts(con, allst: pd.DataFrame, opts: Mimic3Options) -> dict[str, pd.Series]:
    """Per stay, the rows each semantic rule sets aside or links over the *whole stay*:
    every charted row of the stay and every lab row of [INTIME - 1 d, OUTTIME + 1 d] any
    step can read (window [INTIME - the longest hold, OUTTIME + 1 d], the lab window inside
    it), not only the hourly window, so that a rule changing the SOFA window shows in the
    audit: MAP check (``map_outside``), venous blood gas (``venous_gas``), labs linked by
    time (``lab_by_time``), vasopressor rows in a unit no rule converts
    (``vaso_unit_unknown``), rows of a vasopressor item read but not converted
    (``vaso_not_converted``: angiotensin II), input rows with a dose outside dose_limits.csv
    (``dose_implausible``; inputs over [INTIME, OUTTIME]). Read in chunks of
    ``AUDIT_CHUNK`` stays."""
    max_hold = float(data_table("sample_and_hold.csv")["hold_hours"].max())
    parts: dict[str, list[pd.Series]] = {}
    for c0 in range(0, len(allst), AUDIT_CHUNK):
        st = allst.iloc[c0:c0 + AUDIT_CHUNK]
        lo, hi = st["intime"] - max_hold * HOUR, st["outtime"] + LAB_WINDOW
        counts: dict = {}
        _events(con, st, lo, hi, AUDIT_FEATURES, opts, counts=counts)
        dropped: list = []
        _, _, mv_v, cv_v = _inputs(con, st.index, st["intime"], st["outtime"], opts.rewritten,
                                   implausible=dropped)
        counts["dose_implausible"] = pd.concat(dropped).value_counts()
        # vasopressor rows in a unit no conversion rule matches give no dose: counted; rows
        # of an item read but not converted (angiotensin II) apart
        nc = doses.not_converted_items()
        none = [pd.Series(dtype="int64")]
        counts["vaso_unit_unknown"] = pd.concat(
            [v.loc[doses.norepinephrine_equivalent(v, sysname).isna()
                   & ~v["itemid"].isin(nc), "icustay_id"]
             for v, sysname in ((mv_v, "mv"), (cv_v, "cv")) if len(v)] or none).value_counts()
        counts["vaso_not_converted"] = pd.concat(
            [v.loc[v["itemid"].isin(nc), "icustay_id"] for v in (mv_v, cv_v) if len(v)]
            or none).value_counts()
        for k, v in counts.items():
            parts.setdefault(k, []).append(v)
    return {k: pd.concat(v) for k, v in parts.items()}


def _clinical_criteria(con, allst: pd.DataFrame, crit: pd.DataFrame, opts: Mimic3Options,
                       evidence: dict, ev_counts: dict, wd_inputs: dict
                       ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The criteria read from the stay and its events, ``adult`` to ``not_withdrawn``, into
    ``crit``; returns the suspected infections and the max SOFA (for the audit)."""
    ids_all = allst.index
    crit["adult"] = (allst["age"] >= 18).to_numpy()
    inf = suspected_infection(con, allst, opts.event_stay, evidence=evidence,
                              screens=opts.screens)
    crit["suspected_infection"] = inf["in_window"].reindex(ids_all).fillna(False).astype(bool)
    has_onset = inf.index[inf["in_window"].to_numpy()]
    sofa = (max_sofa(con, allst.loc[has_onset], inf.loc[has_onset, "onset"], opts)
            if len(has_onset) else pd.DataFrame(columns=["max_sofa", "sofa_organs"]))
    crit["sofa_ge_2"] = (sofa["max_sofa"] >= 2).reindex(ids_all).astype("boolean")
    if opts.sofa == "ai_clinician":  # urine output read: irrigant and residual rows counted
        ev_counts.update(_urine_rule_counts(con, opts))
    crit["mortality_documented"] = allst["hospital_expire_flag"].isin([0, 1]).to_numpy()
    documented = con.execute("""
        SELECT DISTINCT TRY_CAST(ICUSTAY_ID AS BIGINT) FROM INPUTEVENTS_MV
        UNION SELECT DISTINCT TRY_CAST(ICUSTAY_ID AS BIGINT) FROM INPUTEVENTS_CV""").df()
    documented = set(documented.iloc[:, 0])
    crit["intake_documented"] = ids_all.isin(list(documented))
    crit["not_withdrawn"] = ~ids_all.isin(withdrawn(con, allst, opts, inputs=wd_inputs))
    return inf, sofa


def _hours(con, allst: pd.DataFrame, crit: pd.DataFrame, t_max: int, anchor: str,
           window_h: int, opts: Mimic3Options) -> _Hours:
    """Hourly blocks of every stay, anchored; the criteria ``anchor`` and
    ``stay_covers_window`` into ``crit``."""
    ids_all = allst.index
    # hourly blocks k = 0..n_blk - 1 from INTIME for every stay: enough to find the anchor
    # and hold t_max hours after it (intime: the anchor is block 0)
    window = window_h if anchor == "first_vitals" else 1
    n_blk = window + t_max
    intime = allst["intime"]
    max_hold = float(data_table("sample_and_hold.csv")["hold_hours"].max())
    feats = ("weight", *hourly.VITALS, *hourly.LABS)
    dropped: list = []
    ev = _events(con, allst, intime - max_hold * HOUR, intime + n_blk * HOUR, feats, opts,
                 dropped=dropped)
    n_implausible = pd.concat(dropped)["icustay_id"].value_counts() if dropped else None
    # blood pressure completed per charting time, then hourly means and sample-and-hold of
    # charted and completed values alike (AI-Clinician's order)
    ev = hourly.complete_bp(ev)
    raw = hourly.block_means(ev, intime, feats, n_blk - 1)
    held = hourly.sample_and_hold(raw, ev, intime, how=opts.hold)
    if anchor == "first_vitals":
        offset = first_complete_vitals(held, window)
        anchor_desc = (f"t = 0 at the first hour with every vital, within the first {window} "
                       "ICU hours")
    else:
        offset = pd.Series(0, index=ids_all, dtype="int64", name="anchor_h")
        anchor_desc = "t = 0 at ICU admission (INTIME)"
    crit["anchor"] = ids_all.isin(offset.index)
    t0_all = intime.loc[offset.index] + offset.to_numpy() * HOUR
    covers = allst.loc[offset.index, "outtime"] >= t0_all + (t_max + 1) * HOUR
    crit["stay_covers_window"] = covers.reindex(ids_all).astype("boolean")
    raw = realign(raw, offset, t_max)
    held = realign(held, offset, t_max)
    full = held.index.get_level_values("icustay_id").value_counts()
    full = full.index[full == t_max + 1]  # anchored stays with every hour 0..t_max (blocks)
    return _Hours(raw=raw, held=held, offset=offset, t0=t0_all, full=full,
                  anchor_desc=anchor_desc, n_implausible=n_implausible)


def _weight_documented(con, allst: pd.DataFrame, held: pd.DataFrame, t_max: int,
                       opts: Mimic3Options) -> tuple[pd.Series, str]:
    """Per stay: whether its weight is documented as ``opts.weight_missing`` asks; and the
    CONSORT description."""
    # weight: charted in hour t or held (72 h) from before it, never from a later charting;
    # hours still without one are imputed from other stays (weight_missing="impute", the
    # stay needs a weight charted in [INTIME - 72 h, OUTTIME]: documented, a selection
    # criterion, never a value) or the stay is excluded ("exclude")
    if opts.weight_missing == "exclude":
        wd = held["weight"].notna().groupby(level=0).all()
        return wd, f"weight charted at or before the end of every hour t = 0..{t_max} (held 72 h)"
    ids_all = allst.index
    wev = _events(con, allst, allst["intime"] - 72 * HOUR, allst["outtime"], ("weight",), opts)
    wd = pd.Series(ids_all.isin(wev["icustay_id"].unique()), index=ids_all)
    return wd, ("a weight charted in [INTIME - 72 h, OUTTIME]; hours without one charted "
                "at or before their end are imputed from other stays")


def _stays_per_patient(allst: pd.DataFrame, crit: pd.DataFrame, opts: Mimic3Options
                       ) -> tuple[pd.Series, str]:
    """The criterion ``stays_per_patient`` (on the stays meeting every criterion before it)
    and its CONSORT description."""
    ids_all = allst.index
    # stays_per_patient = first: only the patient's first ICU stay (earliest INTIME of all
    # the patient's ICU stays, as the MIMIC Code Repository's first_icu_stay), kept if it
    # meets every criterion above; a later stay never stands in for an ineligible first one
    # (that would select patients on what happened after their first stay). Evaluated on
    # the stays meeting every criterion above only
    before = ids_all[crit[list(STEPS[1:STEPS.index("stays_per_patient")])]
                     .fillna(False).all(axis=1).to_numpy(bool)]
    if opts.stays_per_patient == "first":
        first = allst.sort_values("intime", kind="stable").drop_duplicates("subject_id").index
        return (pd.Series(before.isin(first), index=before).reindex(ids_all).astype("boolean"),
                "the patient's first ICU stay (INTIME), if it meets every criterion above")
    return (pd.Series(True, index=before).reindex(ids_all).astype("boolean"),
            "every stay of each patient (stays_per_patient: all)")


def _consort(crit: pd.DataFrame, t_max: int, anchor_desc: str, w_desc: str, spp_desc: str
             ) -> tuple[Consort, pd.Index]:
    """The CONSORT chain up to ``stays_per_patient``, in the order of ``STEPS``; the stays
    left."""
    c = Consort()
    desc = {
        "all_icu_stays": "ICU stays in ICUSTAYS",
        "adult": "age >= 18 at ICU admission",
        "suspected_infection": "antibiotic + culture (culture <= 24 h after antibiotic, or "
        "antibiotic <= 72 h after culture), onset in [INTIME - 48 h, OUTTIME + 48 h]",
        "sofa_ge_2": "max SOFA >= 2 in [onset - 48 h, onset + 24 h]",
        "mortality_documented": "hospital mortality documented",
        "intake_documented": "IV fluid / vasopressor charting present (INPUTEVENTS_MV/CV)",
        "not_withdrawn": "treatment withdrawal excluded (AI-Clinician's rule in full, on 4 h "
        "blocks of the ICU stay)",
        "anchor": anchor_desc,
        "stay_covers_window": f"ICU stay lasts at least {t_max + 1} h after t = 0",
        "weight_documented": w_desc,
        "vitals_complete": f"every vital present in each hour t = 0..{t_max} (after "
        "sample-and-hold; the paper's change)",
        "stays_per_patient": spp_desc,
    }
    ids = crit.index
    c.add("all_icu_stays", desc["all_icu_stays"], ids)
    for step in STEPS[1:-1]:
        ids = ids[crit.loc[ids, step].fillna(False).to_numpy(bool)]
        c.add(step, desc[step], ids)
    return c, ids


def _impute(con, allst: pd.DataFrame, stays: pd.DataFrame, held: pd.DataFrame, t0: pd.Series
            ) -> _Imputed:
    """Weight and labs still missing after sample-and-hold: the patient's own earlier weight
    first, then 1-NN from other patients' same or earlier hours (``held`` is changed)."""
    ids = stays.index
    # an hour still without a weight takes the patient's own last weight charted before it
    # (this stay beyond the 72 h hold, or an earlier stay) before any other patient's
    own_w = own_earlier_weight(con, allst, held, t0) if len(ids) else pd.Series(dtype=float)
    if len(own_w):
        held.loc[own_w.index, "weight"] = own_w.to_numpy()
    n_own_w = (own_w.groupby(level=0).size() if len(own_w)
               else pd.Series(dtype="int64"))
    after_hold_missing = held[["weight", *hourly.LABS]].isna()
    imp_bad = pd.Index([], dtype="int64")  # stays whose imputed weight is implausible
    n_w = int(after_hold_missing["weight"].groupby(level=0).any().sum())
    n_w_hours = int(after_hold_missing["weight"].sum())
    if len(ids):
        # weight / labs still missing after sample-and-hold: 1-NN over all non-demographic
        # features, donors from other patients' stays at the same or an earlier hour only (a
        # donor from the stay itself would usually be its own future; one from another stay
        # of the same patient, possibly months later, is the patient's future too)
        x = held[list(schema.FEATURES[2:])].to_numpy(float)
        subj = stays["subject_id"].reindex(held.index.get_level_values("icustay_id"))
        imp = hourly.knn_impute(x, groups=subj.to_numpy("int64"),
                                times=held.index.get_level_values("t").to_numpy())
        held[list(schema.FEATURES[2:])] = imp
        # one body weight per stay: every imputed weight hour takes the value imputed for
        # the stay's first one (its donor saw only hours <= that hour; hourly donors
        # would let a weight jump between unrelated patients' weights hour by hour)
        wmiss = after_hold_missing["weight"]
        if wmiss.any():
            imp_bad = _one_weight_per_stay(con, stays, held, t0, wmiss)
    return _Imputed(held=held, missing_after_hold=after_hold_missing, n_own_weight=n_own_w,
                    weight_implausible=imp_bad, n_weight_stays=n_w, n_weight_hours=n_w_hours)


def _one_weight_per_stay(con, stays: pd.DataFrame, held: pd.DataFrame, t0: pd.Series,
                         wmiss: pd.Series) -> pd.Index:
    """Every imputed weight hour (``wmiss``) of a stay takes the stay's first imputed
    weight; one implausible with the patient's height is dropped (``held`` is changed).
    Returns the stays whose imputed weight was dropped."""
    w = held["weight"].where(wmiss)
    first_w = w.groupby(level=0).transform("first")
    held.loc[wmiss, "weight"] = first_w[wmiss]
    # the plausibility rule applies to an imputed weight as to a charted one: a
    # donor's weight whose BMI with the patient's height (charted before the first
    # imputed hour, by that hour's end) is implausible is not used; the stay then
    # fails ``imputable``
    firsts = wmiss[wmiss].reset_index()[["icustay_id", "t"]].drop_duplicates(
        "icustay_id")
    end = (t0.reindex(firsts["icustay_id"]).to_numpy()
           + (firsts["t"].to_numpy() + 1) * HOUR)
    kg = first_w.loc[pd.MultiIndex.from_frame(firsts)].to_numpy(float)
    ok = np.isfinite(kg)
    bad = np.zeros(len(kg), dtype=bool)
    bad[ok] = _bmi_implausible(
        con, stays["subject_id"].reindex(firsts["icustay_id"]).to_numpy("int64")[ok],
        end[ok], kg[ok])
    imp_bad = pd.Index(firsts["icustay_id"].to_numpy()[bad])
    if len(imp_bad):
        drop = wmiss & held.index.get_level_values(0).isin(imp_bad)
        held.loc[drop, "weight"] = np.nan
    return imp_bad


def _missingness(raw: pd.DataFrame, after_hold_missing: pd.DataFrame, n: int, t_max: int
                 ) -> pd.DataFrame:
    """Missing values before sample-and-hold and imputed cells, per feature and hour, on the
    final cohort of ``n`` stays."""
    miss_rows = []
    for f in schema.FEATURES:
        for t in range(t_max + 1):
            if f in ("age", "sex"):
                nm, ni = 0, 0
            else:
                col = raw[f].xs(t, level="t") if n else pd.Series(dtype=float)
                nm = int(col.isna().sum())
                ni = int(after_hold_missing[f].xs(t, level="t").sum()) if (
                    n and f in after_hold_missing) else 0
            miss_rows.append({"feature": f, "t": t, "n_missing_raw": nm,
                              "share_missing_raw": nm / n if n else np.nan, "n_imputed": ni})
    return pd.DataFrame(miss_rows)


def _trajectories(con, stays: pd.DataFrame, held: pd.DataFrame, t0: pd.Series, t_max: int,
                  opts: Mimic3Options, source: str) -> pd.DataFrame:
    """The cohort's trajectory rows: features, age, sex, the hour's doses, the patient."""
    ids = stays.index
    traj = held.reset_index()
    traj["age"] = stays["age"].reindex(traj["icustay_id"]).to_numpy()
    traj["sex"] = stays["sex"].reindex(traj["icustay_id"]).to_numpy()
    # doses on the same anchor: hour t of the doses is [t0 + t h, t0 + (t + 1) h)
    mv_f, cv_f, mv_v, cv_v = _inputs(con, ids, t0, t0 + (t_max + 1) * HOUR, opts.rewritten)
    fl = doses.hourly_fluid(t0, mv_f, cv_f, t_max)
    va = doses.hourly_vasopressor(t0, mv_v, cv_v, t_max)
    key = pd.MultiIndex.from_frame(traj[["icustay_id", "t"]])
    traj["iv_fluid"] = fl.reindex(key).to_numpy() if len(ids) else []
    traj["vasopressor"] = va.reindex(key).to_numpy() if len(ids) else []
    traj = traj.rename(columns={"icustay_id": schema.STAY_ID})
    # the patient of each stay: the split keeps a patient's stays on one side
    traj[schema.SUBJECT_ID] = stays["subject_id"].reindex(traj[schema.STAY_ID]).to_numpy()
    traj = traj[[*schema.TRAJECTORY_COLUMNS, schema.SUBJECT_ID]]
    if len(traj):
        traj = schema.validate_trajectories(traj, source=source, t_max=t_max)
    return traj


def _extract(con, folder: Path, t_max: int, anchor: str, window_h: int,
             opts: Mimic3Options, layout: Layout = MIMIC3) -> Mimic3Cohort:
    """The cohort, step by step: every criterion for every stay, the CONSORT chain in the
    order of ``STEPS``, imputation, trajectories with their doses, the audit."""
    allst = _stays(con, layout)
    ids_all = allst.index
    crit = pd.DataFrame(index=ids_all)  # True = met, False = failed, NA = not evaluated
    evidence: dict = {}
    ev_counts: dict = {}
    wd_inputs: dict = {}
    inf, sofa = _clinical_criteria(con, allst, crit, opts, evidence, ev_counts, wd_inputs)
    ev_counts.update(_rule_counts(con, allst, opts))
    hours = _hours(con, allst, crit, t_max, anchor, window_h, opts)
    held, full = hours.held, hours.full
    wd, w_desc = _weight_documented(con, allst, held, t_max, opts)
    crit["weight_documented"] = wd.reindex(full).reindex(ids_all).astype("boolean")
    vit = held[list(hourly.VITALS)].notna().all(axis=1).groupby(level=0).all()
    crit["vitals_complete"] = vit.reindex(full).reindex(ids_all).astype("boolean")
    spp, spp_desc = _stays_per_patient(allst, crit, opts)
    crit["stays_per_patient"] = spp
    c, ids = _consort(crit, t_max, hours.anchor_desc, w_desc, spp_desc)

    stays = allst.loc[ids]
    t0 = hours.t0.reindex(ids)
    imputed = _impute(con, allst, stays, held.loc[ids], t0)
    held = imputed.held
    done = held[list(schema.FEATURES[2:])].notna().all(axis=1).groupby(level=0).all()
    crit["imputable"] = done.reindex(ids_all).astype("boolean")
    ids = ids[done.reindex(ids).to_numpy(bool)]
    c.add("imputable", "weight and every lab of every hour observed, held or imputed from "
          f"another patient's same or earlier hour (weight imputed in {imputed.n_weight_stays} "
          f"stays, {imputed.n_weight_hours} stay-hours)", ids)
    stays, held, t0 = stays.loc[ids], held.loc[ids], t0.loc[ids]
    raw = hours.raw.loc[ids]
    offset = hours.offset.reindex(ids)
    after_hold_missing = imputed.missing_after_hold.loc[ids]
    missingness = _missingness(raw, after_hold_missing, len(ids), t_max)
    traj = _trajectories(con, stays, held, t0, t_max, opts,
                         f"{layout.kind} extraction of {folder}")
    anchors = pd.DataFrame({schema.STAY_ID: ids.to_numpy("int64"),
                            "intime": stays["intime"].to_numpy(), "t0": t0.to_numpy(),
                            "anchor_h": offset.to_numpy("int64")})
    imputed_cells = after_hold_missing.reset_index().rename(
        columns={"icustay_id": schema.STAY_ID})
    audit = _audit(allst, inf, sofa, crit, hours.t0, in_cohort=ids, imputed=after_hold_missing,
                   evidence=evidence, withdrawal=wd_inputs.get("frame"),
                   n_implausible=hours.n_implausible, n_own_weight=imputed.n_own_weight,
                   imputed_weight_implausible=imputed.weight_implausible,
                   counts={**ev_counts, "screens": evidence.get("screens"),
                           "culture_by_time": evidence.get("culture_by_time")})
    return Mimic3Cohort(trajectories=traj.reset_index(drop=True), consort=c.frame(),
                        missingness=missingness, anchors=anchors, imputed=imputed_cells,
                        stays=audit, options=opts.as_dict())


# counts of rows set aside by a rule, per stay -> audit column
AUDIT_COUNTS = {"map_outside": "n_map_outside_range",
                "vaso_unit_unknown": "n_vaso_rows_unit_unknown",
                "vaso_not_converted": "n_vaso_rows_not_converted",
                "dose_implausible": "n_dose_rows_implausible",
                "urine_irrigant": "n_urine_irrigant_rows",
                "tf_residual": "n_urine_tf_residual_rows",
                "venous_gas": "n_venous_gas_rows",
                "screens": "n_screen_cultures",
                "lab_by_time": "n_labs_linked_by_time",
                "culture_by_time": "n_cultures_linked_by_time"}

INFECTION_STATUS = ("onset", "onset_outside_window", "no_antibiotic_no_culture",
                    "no_antibiotic", "no_culture", "no_pair_in_time")


def _audit(allst: pd.DataFrame, inf: pd.DataFrame, sofa: pd.DataFrame, crit: pd.DataFrame,
           t0: pd.Series, in_cohort: pd.Index, imputed: pd.DataFrame,
           evidence: dict | None = None, withdrawal: pd.DataFrame | None = None,
           n_implausible: pd.Series | None = None, n_own_weight: pd.Series | None = None,
           imputed_weight_implausible: pd.Index | None = None,
           counts: dict | None = None) -> pd.DataFrame:
    """One row per ICU stay: identifiers, onset (time, source, the antibiotic and culture
    times; also an onset outside the window, flagged), ``infection_status`` (why the
    suspected-infection step passed or failed: ``INFECTION_STATUS``), max SOFA and the
    organs scoring in its block, the treatment-withdrawal rule's inputs
    (``WITHDRAWAL_INPUTS``), t0, each criterion (True / False / NA = not evaluated: the SOFA
    needs an onset, the hourly criteria an anchor, imputable the rest of the cohort), the
    first failed step, every failed criterion, the weights deleted as implausible
    (``n_weight_implausible``: charts in the extraction window), the hours given the
    patient's own earlier weight (``n_own_weight_hours``: beyond the 72 h hold, or from an
    earlier stay), whether the weight imputed from another patient was implausible for the
    patient's height (``weight_imputed_implausible``: the stay fails ``imputable``), the
    rows each semantic rule set aside over the whole stay (``counts``, from ``_rule_counts``:
    ``n_map_outside_range``, ...), and the imputed cells: weight hours and lab cells apart."""
    a = pd.DataFrame({schema.STAY_ID: allst.index.to_numpy("int64"),
                      "subject_id": allst["subject_id"].to_numpy(),
                      "hadm_id": allst["hadm_id"].to_numpy(),
                      "dbsource": allst["dbsource"].to_numpy(),
                      "intime": allst["intime"].to_numpy(), "outtime": allst["outtime"].to_numpy(),
                      "age": allst["age"].round(2).to_numpy()}, index=allst.index)
    for col in ("onset", "onset_source", "antibiotic_time", "culture_time"):
        a[col] = inf[col].reindex(allst.index).to_numpy()
    a["onset_in_window"] = inf["in_window"].reindex(allst.index).astype("boolean").to_numpy()
    ev = evidence or {}
    has_ab = allst.index.isin(ev.get("antibiotic", pd.Index([])))
    has_cu = allst.index.isin(ev.get("culture", pd.Index([])))
    has_onset = a["onset"].notna().to_numpy()
    status = np.select(
        [has_onset & a["onset_in_window"].fillna(False).to_numpy(bool), has_onset,
         ~has_ab & ~has_cu, ~has_ab, ~has_cu],
        list(INFECTION_STATUS[:5]), default=INFECTION_STATUS[5])
    a["has_antibiotic"], a["has_culture"], a["infection_status"] = has_ab, has_cu, status
    a["max_sofa"] = sofa["max_sofa"].reindex(allst.index).to_numpy()
    a["sofa_organs"] = sofa["sofa_organs"].reindex(allst.index).to_numpy()
    wd = (withdrawal if withdrawal is not None
          else pd.DataFrame(columns=list(WITHDRAWAL_INPUTS)))
    for col in WITHDRAWAL_INPUTS:
        a[col] = wd[col].reindex(allst.index).to_numpy() if col in wd else np.nan
    a["t0"] = t0.reindex(allst.index).to_numpy()
    steps = list(STEPS[1:])
    for st in steps:
        a[st] = crit[st].astype("boolean").to_numpy()
    failed = a[steps].eq(False).fillna(False)
    a["excluded_at"] = [next((st for st in steps if f[st]), "") for _, f in failed.iterrows()]
    a["reasons"] = [";".join(st for st in steps if f[st]) for _, f in failed.iterrows()]
    a["in_cohort"] = allst.index.isin(in_cohort)
    a["n_weight_implausible"] = (n_implausible.reindex(allst.index).fillna(0).astype("int64")
                                 .to_numpy() if n_implausible is not None else 0)
    a["n_own_weight_hours"] = (n_own_weight.reindex(allst.index).fillna(0).astype("int64")
                               .to_numpy() if n_own_weight is not None else 0)
    a["weight_imputed_implausible"] = allst.index.isin(
        imputed_weight_implausible if imputed_weight_implausible is not None else [])
    for key, col in AUDIT_COUNTS.items():
        n = (counts or {}).get(key)
        a[col] = (n.reindex(allst.index).fillna(0).astype("int64").to_numpy()
                  if n is not None else 0)
    per_stay = imputed.groupby(level=0).sum()
    n_w = per_stay["weight"] if "weight" in per_stay else pd.Series(dtype="int64")
    n_lab = per_stay.drop(columns="weight", errors="ignore").sum(axis=1)
    a["n_imputed_weight_hours"] = n_w.reindex(allst.index).fillna(0).astype("int64").to_numpy()
    a["n_imputed_lab_cells"] = n_lab.reindex(allst.index).fillna(0).astype("int64").to_numpy()
    a.loc[~a["in_cohort"], ["n_imputed_weight_hours", "n_imputed_lab_cells"]] = 0
    return a.reset_index(drop=True)


def main(argv: list[str] | None = None, layout: Layout = MIMIC3) -> None:
    """CLI: python -m twinfalsify.sources.mimic3 FOLDER OUTDIR [options] (MIMIC-IV:
    python -m twinfalsify.sources.mimic4 ...)."""
    from .options import CHOICES, PRESETS, options_from_config
    from .tables import resolve_dir

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("folder")
    p.add_argument("outdir")
    p.add_argument("--t-max", type=int, default=schema.T_MAX)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--anchor", choices=ANCHORS, default="first_vitals")
    p.add_argument("--anchor-window-h", type=int, default=ANCHOR_WINDOW_H)
    p.add_argument("--cohort-variant", choices=list(PRESETS), default="project")
    p.add_argument("--memory-limit", default=None, help="DuckDB memory limit, e.g. 4GB")
    p.add_argument("--temp-dir", default=None, help="folder for staged tables and spill files")
    for k, v in CHOICES.items():
        p.add_argument(f"--{k.replace('_', '-')}", choices=v, default=None)
    a = p.parse_args(argv)
    cfg = {"cohort_variant": a.cohort_variant, **{k: getattr(a, k) for k in CHOICES}}
    try:
        res = extract_mimic3(resolve_dir(a.folder, layout), t_max=a.t_max, threads=a.threads,
                             anchor=a.anchor, anchor_window_h=a.anchor_window_h,
                             options=options_from_config(cfg), memory_limit=a.memory_limit,
                             temp_directory=a.temp_dir, layout=layout)
    except ContractError as exc:  # bad input: one line naming the file, no traceback
        raise SystemExit(f"ERROR: {exc}") from None
    out = Path(a.outdir)
    out.mkdir(parents=True, exist_ok=True)
    res.trajectories.to_parquet(out / "trajectories.parquet", index=False)
    res.consort.to_csv(out / "cohort_consort.csv", index=False)
    res.missingness.to_csv(out / "cohort_missingness.csv", index=False)
    res.anchors.to_csv(out / "cohort_anchors.csv", index=False)
    res.stays.to_csv(out / "cohort_stays.csv", index=False)
    print(res.consort.to_string(index=False))


if __name__ == "__main__":
    main()
