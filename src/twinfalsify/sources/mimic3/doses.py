"""Hourly IV fluid (mL/h, tonicity-normalised) and vasopressor (norepinephrine-equivalent
ug/kg/min) doses from MetaVision and CareVue input events.

Conventions (after AI-Clinician, Komorowski et al. 2018, AIClinician_mimic3_dataset_160219.m,
section DATA COMBINATION, with 1 h blocks instead of 4 h):

- Block t covers [INTIME + t h, INTIME + (t+1) h).
- IV fluid during block t (mL, = mL/h since the block is 1 h):
  MetaVision infusion (RATE present, ENDTIME > STARTTIME):
      tev * overlap([start, end), block) / (end - start)
  which equals AI-Clinician's normalised rate (rate * tev / amount) times the overlap when
  amount = rate * duration; MetaVision bolus (no RATE): tev if STARTTIME in the block;
  CareVue (charted amounts, all treated as boluses by AI-Clinician): tev if CHARTTIME in
  the block. tev = AMOUNT * tonicity factor (data/mimic3/fluids.csv).
- Vasopressor during block t: the maximum norepinephrine-equivalent rate among
  MetaVision infusions overlapping the block and CareVue rates charted in the block
  (AI-Clinician's max_dose_vaso); 0 when none. Rates are converted with
  data/mimic3/vasopressors.csv (first matching row by priority).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .tables import data_table

HOUR = pd.Timedelta(hours=1)


def tonicity_factors() -> pd.Series:
    """itemid -> tonicity factor (normal-saline equivalent volume per mL)."""
    t = data_table("fluids.csv")
    return pd.Series(t["tonicity_factor"].to_numpy(float), index=t["itemid"].astype("int64"))


def norepinephrine_equivalent(events: pd.DataFrame, system: str,
                              rules: pd.DataFrame | None = None) -> pd.Series:
    """Norepinephrine-equivalent rate (ug/kg/min) per event row; NaN when no rule matches.

    ``events`` has columns itemid, rate, rateuom and optionally patientweight. Formula:
    rate * factor / weight_divisor, with the first matching row of vasopressors.csv (lowest
    priority number; rateuom '*' matches any unit; min_rate_exclusive: the row needs
    rate > it; patientweight_eq: the row needs that PATIENTWEIGHT, so it never matches
    events without the column; a row without a factor converts nothing: NaN). ``rules``:
    rows in vasopressors.csv's columns to use instead (the meds source's code map).
    """
    rules = data_table("vasopressors.csv") if rules is None else rules
    rules = rules[rules["system"] == system].sort_values("priority", kind="stable")
    out = pd.Series(np.nan, index=events.index, dtype="float64")
    rate = pd.to_numeric(events["rate"], errors="coerce")
    uom = events["rateuom"].astype("string").str.strip()
    item = events["itemid"].astype("int64")
    for _, r in rules.iterrows():
        if pd.isna(r["factor"]):  # read, not converted (not_converted_items)
            continue
        m = (item == int(r["itemid"])) & out.isna() & rate.notna()
        if r["rateuom"] != "*":
            m &= uom == r["rateuom"]
        if pd.notna(r["min_rate_exclusive"]):
            m &= rate > float(r["min_rate_exclusive"])
        if pd.notna(r.get("patientweight_eq")):  # column absent (a meds code map): none
            w = (pd.to_numeric(events["patientweight"], errors="coerce")
                 if "patientweight" in events else pd.Series(np.nan, index=events.index))
            m &= w == float(r["patientweight_eq"])
        div = 1.0 if pd.isna(r["weight_divisor"]) else float(r["weight_divisor"])
        out[m] = rate[m] * float(r["factor"]) / div
    return out


def not_converted_items() -> frozenset[int]:
    """Vasopressor items read but not converted (vasopressors.csv rows without a factor:
    MIMIC-IV's angiotensin II): their rows give no dose and are counted per stay."""
    rules = data_table("vasopressors.csv")
    return frozenset(rules.loc[rules["factor"].isna(), "itemid"].astype("int64"))


def dose_plausible(values: pd.Series, action: str) -> pd.Series:
    """True where a row's dose (``action`` ``vasopressor``: its norepinephrine-equivalent
    rate, ug/kg/min; ``iv_fluid``: its amount, mL) lies in dose_limits.csv's [lo, hi];
    NaN (no dose: e.g. a unit no rule converts) counts as plausible here, as it gives no
    dose anyway."""
    lim = data_table("dose_limits.csv").set_index("action")
    lo, hi = float(lim.loc[action, "lo"]), float(lim.loc[action, "hi"])
    v = pd.to_numeric(values, errors="coerce")
    return v.isna() | ((v >= lo) & (v <= hi))


def _overlap_hours(start: pd.Series, end: pd.Series, t0: pd.Series, t1: pd.Series) -> np.ndarray:
    lo = np.maximum(start.to_numpy("datetime64[ns]"), t0.to_numpy("datetime64[ns]"))
    hi = np.minimum(end.to_numpy("datetime64[ns]"), t1.to_numpy("datetime64[ns]"))
    return np.clip((hi - lo) / np.timedelta64(1, "h"), 0.0, None)


def _blocks(intime: pd.Series, t_max: int, width: pd.Timedelta = HOUR) -> pd.DataFrame:
    """One row per (icustay_id, t) with block start t0 = intime + t * width and end t1."""
    b = pd.DataFrame({"icustay_id": intime.index.repeat(t_max + 1),
                      "t": np.tile(np.arange(t_max + 1), len(intime))})
    b["t0"] = intime.reindex(b["icustay_id"]).to_numpy() + b["t"].to_numpy() * width
    b["t1"] = b["t0"] + width
    return b


def hourly_fluid(intime: pd.Series, mv: pd.DataFrame, cv: pd.DataFrame, t_max: int,
                 tonicity: pd.Series | None = None) -> pd.Series:
    """Tonicity-normalised IV fluid (mL) per (icustay_id, t); see the module docstring.

    intime: INTIME indexed by icustay_id. mv: icustay_id, itemid, starttime, endtime, amount,
    rate. cv: icustay_id, itemid, charttime, amount. ``tonicity``: itemid -> factor to use
    instead of fluids.csv's (the meds source's code map).
    """
    fac = tonicity_factors() if tonicity is None else tonicity
    blocks = _blocks(intime, t_max)
    total = pd.Series(0.0, index=pd.MultiIndex.from_frame(blocks[["icustay_id", "t"]]))
    if len(mv):
        m = mv.merge(blocks, on="icustay_id")
        tev = m["amount"].astype(float) * m["itemid"].map(fac).astype(float)
        dur_h = (m["endtime"] - m["starttime"]) / HOUR
        infusion = m["rate"].notna() & (dur_h > 0)
        share = np.where(infusion, _overlap_hours(m["starttime"], m["endtime"], m["t0"], m["t1"])
                         / np.where(dur_h > 0, dur_h, 1.0), 0.0)
        bolus = ~infusion & (m["starttime"] >= m["t0"]) & (m["starttime"] < m["t1"])
        vol = np.where(infusion, tev * share, np.where(bolus, tev, 0.0))
        total = total.add(pd.Series(vol, index=pd.MultiIndex.from_frame(m[["icustay_id", "t"]]))
                          .groupby(level=[0, 1]).sum(), fill_value=0.0)
    if len(cv):
        c = cv.merge(blocks, on="icustay_id")
        c = c[(c["charttime"] >= c["t0"]) & (c["charttime"] < c["t1"])]
        tev = c["amount"].astype(float) * c["itemid"].map(fac).astype(float)
        total = total.add(pd.Series(tev.to_numpy(), index=pd.MultiIndex.from_frame(
            c[["icustay_id", "t"]])).groupby(level=[0, 1]).sum(), fill_value=0.0)
    return total.rename("iv_fluid")


def hourly_vasopressor(intime: pd.Series, mv: pd.DataFrame, cv: pd.DataFrame, t_max: int,
                       width: pd.Timedelta = HOUR, rules: pd.DataFrame | None = None
                       ) -> pd.Series:
    """Max norepinephrine-equivalent rate (ug/kg/min) per (icustay_id, t); 0 when none.

    mv: icustay_id, itemid, starttime, endtime, rate, rateuom (MetaVision).
    cv: icustay_id, itemid, charttime, rate, rateuom (CareVue). ``width``: block length
    (4 h for the SOFA blocks). ``rules``: conversion rows instead of vasopressors.csv's
    (``norepinephrine_equivalent``).
    """
    blocks = _blocks(intime, t_max, width)
    idx = pd.MultiIndex.from_frame(blocks[["icustay_id", "t"]])
    parts = []
    if len(mv):
        m = mv.assign(ne=norepinephrine_equivalent(mv, "mv", rules)).merge(blocks, on="icustay_id")
        m = m[(m["starttime"] < m["t1"]) & (m["endtime"] > m["t0"]) & m["ne"].notna()]
        parts.append(m[["icustay_id", "t", "ne"]])
    if len(cv):
        c = cv.assign(ne=norepinephrine_equivalent(cv, "cv", rules)).merge(blocks, on="icustay_id")
        c = c[(c["charttime"] >= c["t0"]) & (c["charttime"] < c["t1"]) & c["ne"].notna()]
        parts.append(c[["icustay_id", "t", "ne"]])
    if not parts:
        return pd.Series(0.0, index=idx, name="vasopressor")
    allp = pd.concat(parts)
    mx = allp.groupby(["icustay_id", "t"])["ne"].max()
    return mx.reindex(idx).fillna(0.0).clip(lower=0.0).rename("vasopressor")
