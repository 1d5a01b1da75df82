"""Causality of the MIMIC-III extraction: no value of hour t depends on a row charted after
the end of hour t (t0 + (t + 1) h), in its own stay or in any other.

Property test: for each t, every CHARTEVENTS / LABEVENTS value charted after the end of
hour t of its stay is perturbed (every stay at once); the values of hours 0..t of every stay
kept in both extractions must not change. Cohort membership may change (selection criteria
look at the whole stay: the vitals of hours up to t_max, mortality, SOFA around the onset);
values may not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers.paths import FIXTURES, ROOT, shared_dir

from twinfalsify import schema
from twinfalsify.sources.mimic3 import extract_mimic3, itemmap
from twinfalsify.sources.mimic3.tables import connect

FIX = FIXTURES / "mimic3"
DEMO = (shared_dir() or ROOT.parent / "shared") / "data" / "mimic-iii-demo"
EARLY = pd.Timestamp("1700-01-01")
VALUE_FEATURES = [f for f in schema.FEATURES if f not in ("age", "sex")]


PERTURBED = ("CHARTEVENTS", "LABEVENTS")


def read_events(src: Path) -> dict[str, pd.DataFrame]:
    """The tables ``perturb_after`` changes, as the extraction reads them (every column text,
    upper-case names)."""
    con = connect(src, tables=PERTURBED)
    try:
        out = {}
        for table in PERTURBED:
            df = con.execute(f'SELECT * FROM "{table}"').df()
            df.columns = [c.upper() for c in df.columns]
            out[table] = df
        return out
    finally:
        con.close()


def perturb_after(src: Path, dst: Path, t0: pd.Series, t: int, seed: int = 0,
                  scale: float = 0.02, events: dict[str, pd.DataFrame] | None = None) -> int:
    """Copy the MIMIC tables of ``src`` to ``dst``, multiplying VALUENUM (and VALUE, where
    numeric) of every CHARTEVENTS row charted at or after t0 + (t + 1) h of its stay, and of
    every LABEVENTS row charted at or after that time for every stay of its admission, by
    1 + U(-scale, scale). Stays not in ``t0`` (not in the cohort): all their rows are
    perturbed. Weights (read across the patient's stays: an hour without one takes the
    patient's own last earlier weight) are perturbed from the latest cut of the patient's
    cohort stays on, all of them for a patient without one. The two perturbed tables are
    written as Parquet with every column text (what the extraction reads from a CSV), the
    others linked unchanged. ``events``: ``read_events(src)``, when the caller perturbs the
    same folder several times. Returns the number of perturbed rows."""
    from twinfalsify.sources.mimic3.tables import REQUIRED_COLUMNS, find_table

    events = read_events(src) if events is None else events
    con = connect(src, tables=("ICUSTAYS",))
    stays = con.execute("SELECT CAST(ICUSTAY_ID AS BIGINT) AS icustay_id, "
                        "CAST(HADM_ID AS BIGINT) AS hadm_id, "
                        "CAST(SUBJECT_ID AS BIGINT) AS subject_id FROM ICUSTAYS").df()
    con.close()
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    cut = (t0 + (t + 1) * pd.Timedelta(hours=1)).rename("cut")
    stays["cut"] = stays["icustay_id"].map(cut)  # NaT: not in the cohort
    subj_cut = stays.dropna(subset=["cut"]).groupby("subject_id")["cut"].max()
    stays["cut"] = stays["cut"].fillna(EARLY)
    weight_items = set(itemmap.ITEM_LISTS[[x.name for x in itemmap.ITEM_LISTS].index(
        "weight")].itemids())
    hadm_cut = stays.groupby("hadm_id")["cut"].max()  # later than the cut of every stay
    n = 0
    for table in REQUIRED_COLUMNS:
        if table not in PERTURBED:
            path = find_table(src, table)
            (dst / path.name).symlink_to(path.resolve())
            continue
        df = events[table].copy()
        time = pd.to_datetime(df["CHARTTIME"], errors="coerce")
        if table == "CHARTEVENTS":
            c = pd.to_numeric(df["ICUSTAY_ID"], errors="coerce").map(
                stays.set_index("icustay_id")["cut"])
            wt = pd.to_numeric(df["ITEMID"], errors="coerce").isin(weight_items)
            cs = pd.to_numeric(df["SUBJECT_ID"], errors="coerce").map(subj_cut)
            c = c.where(~wt, cs)
        else:
            c = pd.to_numeric(df["HADM_ID"], errors="coerce").map(hadm_cut)
        later = (time >= c.fillna(EARLY)).to_numpy()
        v = pd.to_numeric(df["VALUENUM"], errors="coerce")
        f = 1 + rng.uniform(-scale, scale, len(df))
        hit = later & v.notna().to_numpy()
        newv = (v * f).where(hit, v)
        df["VALUENUM"] = np.where(hit, newv.map(lambda x: f"{x:.10g}"), df["VALUENUM"])
        num = pd.to_numeric(df["VALUE"], errors="coerce")
        vh = hit & num.notna().to_numpy()
        df["VALUE"] = np.where(vh, (num * f).map(lambda x: f"{x:.10g}"), df["VALUE"])
        n += int(hit.sum())
        df.astype("string").to_parquet(dst / f"{table}.parquet", index=False)
    return n


def check_causal(folder: Path, tmp: Path, hours=range(schema.T_MAX), **kw) -> dict:
    """Run the property for each t in ``hours``. Cells kept from the stay's own data
    (charted, held) must be unchanged; imputed cells too when the cohort is the same (their
    donors are other stays' rows of hours <= t, but the donor pool is the cohort, whose
    membership looks at whole stays). Returns per t: common stays, same cohort or not."""
    base = extract_mimic3(folder, **kw)
    t0 = base.anchors.set_index(schema.STAY_ID)["t0"]
    a = base.trajectories.set_index([schema.STAY_ID, "t"])[VALUE_FEATURES]
    ia = base.imputed.set_index([schema.STAY_ID, "t"]).reindex(columns=VALUE_FEATURES,
                                                                fill_value=False)
    out = {}
    events = read_events(folder)
    for t in hours:
        d = tmp / f"t{t}"
        assert perturb_after(folder, d, t0, t, events=events) > 0
        other = extract_mimic3(d, **kw)
        b = other.trajectories.set_index([schema.STAY_ID, "t"])[VALUE_FEATURES]
        ib = other.imputed.set_index([schema.STAY_ID, "t"]).reindex(columns=VALUE_FEATURES,
                                                                    fill_value=False)
        sa, sb = set(a.index.get_level_values(0)), set(b.index.get_level_values(0))
        ids = sorted(sa & sb)
        key = pd.MultiIndex.from_tuples([(s, h) for s in ids for h in range(t + 1)])
        va, vb = a.loc[key], b.loc[key]
        own = ~(ia.loc[key].to_numpy() | ib.loc[key].to_numpy())
        same = sa == sb
        check = np.ones_like(own) if same else own
        bad = check & ~np.isclose(va.to_numpy(float), vb.to_numpy(float), rtol=0, atol=0)
        assert not bad.any(), (t, va[bad.any(axis=1)], vb[bad.any(axis=1)])
        # the perturbation reaches the later hours: the test can fail
        later = pd.MultiIndex.from_tuples(
            [(s, h) for s in ids for h in range(t + 1, schema.T_MAX + 1)])
        assert not a.loc[later].equals(b.loc[later])
        out[t] = (len(ids), same)
    return out


def test_fixture_values_never_see_later_rows(tmp_path):
    res = check_causal(FIX, tmp_path)
    assert all(n >= 2 and same for n, same in res.values())


@pytest.mark.slow
@pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(), reason="demo absent")
def test_demo_values_never_see_later_rows(tmp_path):
    res = check_causal(DEMO, tmp_path, hours=(0, 2))
    assert min(n for n, _ in res.values()) >= 40
