"""Hourly trajectories from a MEDS dataset and a code map, with the CONSORT, audit, unit
screen and missingness tables of the other sources.

Hour 0 is ICU admission (``cohort: icu_admission``) or the ``prediction_time`` of a MEDS
label table (``cohort: labels``). Hour t is [t0 + t h, t0 + (t + 1) h); its value of a
feature is the mean of the values timed in it, else the last value timed before t0 + t h,
carried forward for at most the feature's hold (``sample_and_hold.csv``), never a later one
(no value of hour t comes from an event timed after t0 + (t + 1) h). The event time is the
MEDS ``time`` of the row: for the MIMIC-IV ETL a lab's time is its specimen's collection
time (``charttime``), as the mimic4 source reads it. Doses of hour t are the IV fluid given
and the maximum vasopressor rate running in the same hour (``mimic3.doses``).

The per-value rules are the mimic3 / mimic4 sources' own functions (``mimic3.hourly``:
unit conversion, outlier deletion, the MAP check, blood-pressure completion, block means,
sample-and-hold, 1-NN imputation from other patients' same or earlier hours;
``mimic3.doses``: tonicity and norepinephrine equivalents).
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify import schema
from twinfalsify.schema import ContractError
from twinfalsify.sources.consort import Consort
from twinfalsify.sources.mimic3 import doses, hourly
from twinfalsify.sources.mimic3.tables import data_table

from .codemap import CodeMap, load_code_map, split_unit
from .dataset import MedsDataset, connect, open_dataset
from .labels import read_labels

HOUR = pd.Timedelta(hours=1)
COHORTS = ("icu_admission", "labels", "sepsis3")
LABEL_VALUES = ("all", "true", "false")
MISSING = ("impute", "exclude")
FEATS = ("weight", *hourly.VITALS, *hourly.LABS)
ADULT_AGE = 18


@dataclass
class MedsCohort:
    trajectories: pd.DataFrame  # schema.TRAJECTORY_COLUMNS + schema.SUBJECT_ID
    consort: pd.DataFrame  # step, description, n_stays, n_excluded
    missingness: pd.DataFrame  # feature, t, n_missing_raw, share_missing_raw, n_imputed
    stays: pd.DataFrame  # one audit row per ICU stay: times, criteria, rows set aside
    units: pd.DataFrame  # the unit screen: code, unit, feature, n_rows, read
    anchors: pd.DataFrame  # stay_id, subject_id, intime, t0
    dataset: str  # the dataset's name, version and ETL (metadata/dataset.json)


def _lit(s: str) -> str:
    return "'" + s.replace("'", "''") + "'"


def _match(col: str, pattern: str) -> str:
    """SQL: ``col`` matches a map code (exact, or a ``//*`` prefix)."""
    if pattern.endswith("//*"):
        return f"starts_with({col}, {_lit(pattern[:-1])})"
    return f"{col} = {_lit(pattern)}"


def code_counts(con) -> pd.DataFrame:
    """Rows per code of the whole dataset (one streaming scan of the code column)."""
    return con.execute("SELECT code, count(*) AS n FROM events GROUP BY code").df()


def check_codes(cmap: CodeMap, counts: pd.DataFrame, ds: MedsDataset) -> list[str]:
    """The map's codes that match no event. A strict (user) map: ContractError naming the
    first, with the nearest code of the dataset; the preset: the list (coverage table)."""
    codes = counts["code"].astype(str)
    stems = set(codes.map(lambda c: split_unit(c)[0] + "//"))
    have = set(codes)
    absent = []
    for c in cmap.all_codes():
        hit = (c[:-1] in stems or any(x.startswith(c[:-1]) for x in have)) \
            if c.endswith("//*") else c in have
        if not hit:
            absent.append(c)
    if absent and cmap.strict:
        c = absent[0]
        near = difflib.get_close_matches(c.rstrip("*"), list(have), n=1)
        raise ContractError(f"{cmap.source}: code {c!r} occurs in no event of {ds.path} "
                            f"({len(have)} codes)" + (f"; nearest: {near[0]!r}" if near else "")
                            + " (rule: every code of a code map is in the dataset)")
    return absent


def _sepsis3_error(counts: pd.DataFrame, ds: MedsDataset) -> ContractError:
    micro = counts["code"].astype(str).str.upper().str.contains("MICRO").sum()
    what = ("it holds no microbiology (no code containing MICRO: MIMIC-IV's MEDS ETL writes "
            "no microbiologyevents)" if micro == 0 else
            f"its {micro} microbiology codes have no culture/antibiotic map in the meds source")
    return ContractError(f"source.meds.cohort: sepsis3 needs cultures and antibiotics to find "
                         f"a suspected infection, and {ds.path} ({ds.label}): {what}; give "
                         "the cohort as a MEDS label table (cohort: labels, e.g. an ACES "
                         "sepsis task) or use cohort: icu_admission")


def icu_stays(con, cmap: CodeMap, ds: MedsDataset) -> pd.DataFrame:
    """One row per ICU stay: stay_id, subject_id, intime, outtime (NaT: no discharge), age
    at admission, sex. With ``stays.id_column`` the admission and discharge rows pair by
    it; without, the k-th admission of a patient pairs with the k-th discharge after it and
    stays are numbered 1, 2, ... in (subject, admission time) order."""
    adm, dis = cmap.stays["admission"], cmap.stays["discharge"]
    idc = cmap.stays.get("id_column")
    if idc:
        if idc not in _columns(con):
            raise ContractError(f"{cmap.source}: stays.id_column {idc!r} is no column of "
                                f"{ds.path}'s shards")
        st = con.execute(f"""
            SELECT CAST("{idc}" AS BIGINT) AS stay_id, min(subject_id) AS subject_id,
                   count(DISTINCT subject_id) AS n_subj,
                   min(time) FILTER (WHERE {_match('code', adm)}) AS intime,
                   max(time) FILTER (WHERE {_match('code', dis)}) AS outtime
            FROM events WHERE ({_match('code', adm)} OR {_match('code', dis)})
              AND "{idc}" IS NOT NULL GROUP BY 1""").df()
        bad = st[st["n_subj"] > 1]
        if len(bad):
            raise ContractError(f"{ds.path}: {idc} {int(bad['stay_id'].iloc[0])} belongs to "
                                "several subjects (rule: a stay belongs to one patient)")
        st = st.drop(columns="n_subj").dropna(subset=["intime"])
    else:
        ev = con.execute(f"""
            SELECT subject_id, time, {_match('code', adm)} AS is_adm FROM events
            WHERE {_match('code', adm)} OR {_match('code', dis)} ORDER BY subject_id, time
            """).df()
        rows = []
        for sid, g in ev.groupby("subject_id", sort=True):
            open_t = None
            for t, is_adm in zip(g["time"], g["is_adm"], strict=True):
                if is_adm:
                    if open_t is not None:
                        rows.append((sid, open_t, pd.NaT))
                    open_t = t
                elif open_t is not None:
                    rows.append((sid, open_t, t))
                    open_t = None
            if open_t is not None:
                rows.append((sid, open_t, pd.NaT))
        st = pd.DataFrame(rows, columns=["subject_id", "intime", "outtime"])
        st.insert(0, "stay_id", np.arange(1, len(st) + 1, dtype="int64"))
    if st.empty:
        raise ContractError(f"{ds.path}: no ICU stay (no event {adm!r} in {ds.label})")
    sex_case = "CASE " + " ".join(f"WHEN code = {_lit(c)} THEN {v}"
                                  for c, v in cmap.sex.items()) + " END"
    demo = con.execute(f"""
        SELECT subject_id, min(time) FILTER (WHERE code = {_lit(cmap.birth)}) AS birth,
               max({sex_case}) AS sex_max, min({sex_case}) AS sex_min
        FROM events WHERE code IN ({', '.join(_lit(c) for c in [cmap.birth, *cmap.sex])})
        GROUP BY 1""").df().set_index("subject_id")
    for col in ("intime", "outtime"):  # one time resolution everywhere (DuckDB gives us)
        st[col] = pd.to_datetime(st[col]).astype("datetime64[ns]")
    demo["birth"] = pd.to_datetime(demo["birth"]).astype("datetime64[ns]")
    st = st.sort_values(["subject_id", "intime"], kind="stable").set_index("stay_id")
    birth = demo["birth"].reindex(st["subject_id"]).to_numpy()
    st["age"] = (st["intime"].to_numpy() - birth) / pd.Timedelta(days=365.25)
    one_sex = demo["sex_max"] == demo["sex_min"]
    st["sex"] = demo["sex_max"].where(one_sex).reindex(st["subject_id"]).to_numpy()
    return st


def _columns(con) -> set[str]:
    return set(con.execute("SELECT * FROM events LIMIT 0").df().columns)


def _anchor(con, st: pd.DataFrame, cohort: str, labels: str | Path | None, label_value: str
            ) -> tuple[pd.Series, str]:
    """t0 per stay in the cohort, and the CONSORT description."""
    if cohort == "icu_admission":
        return st["intime"].rename("t0"), "every ICU stay; t = 0 at ICU admission"
    lab = read_labels(labels)
    if label_value != "all":
        if "boolean_value" not in lab:
            raise ContractError(f"source.meds.label_value: {label_value} needs the label "
                                f"table's boolean_value column, which {labels} lacks")
        lab = lab[lab["boolean_value"].fillna(False) == (label_value == "true")]
    s = st.reset_index()[["stay_id", "subject_id", "intime", "outtime"]]
    m = lab.merge(s, on="subject_id")
    inside = (m["prediction_time"] >= m["intime"]) & (
        m["outtime"].isna() | (m["prediction_time"] < m["outtime"]))
    m = m[inside].sort_values("prediction_time", kind="stable")
    n_lab, n_in = len(lab), m[["subject_id", "prediction_time"]].drop_duplicates().shape[0]
    first = m.drop_duplicates("stay_id")
    t0 = first.set_index("stay_id")["prediction_time"].rename("t0")
    desc = (f"ICU stays with a label's prediction_time in the stay (t = 0 there; "
            f"{n_lab} labels{'' if label_value == 'all' else f' with boolean_value {label_value}'}"
            f", {n_lab - n_in} outside every ICU stay, {n_in - len(first)} later in a stay "
            "already labelled: not used)")
    return t0, desc


def _feature_events(con, cmap: CodeMap, win: pd.DataFrame, cols: set[str]
                    ) -> tuple[pd.DataFrame, pd.DataFrame, pd.Series]:
    """Mapped values of the stays' windows (icustay_id, time, feature, value in contract
    units, outliers deleted, venous blood gases deleted); the unit screen (code, unit,
    feature, n_rows, read); venous-gas rows deleted per stay."""
    fm = cmap.features.assign(
        exact=~cmap.features["code"].str.endswith("//*"),
        key=cmap.features["code"].map(lambda c: c[:-3] if c.endswith("//*") else c))
    con.register("fmap", fm[["key", "exact", "feature", "conversion"]])
    con.register("win", win)
    ev = con.execute("""
        WITH e AS (
            SELECT e.subject_id, e.time, e.code, e.numeric_value AS value,
                   regexp_extract(e.code, '^(.*)//', 1) AS stem,
                   regexp_extract(e.code, '^.*//(.*)$', 1) AS unit
            FROM events e
            WHERE e.numeric_value IS NOT NULL AND e.time IS NOT NULL
              AND e.subject_id IN (SELECT subject_id FROM win))
        SELECT w.stay_id AS icustay_id, e.time, e.code, e.unit, m.feature, m.conversion,
               CAST(e.value AS DOUBLE) AS value
        FROM e JOIN fmap m ON (m.exact AND e.code = m.key) OR (NOT m.exact AND e.stem = m.key)
        JOIN win w ON e.subject_id = w.subject_id AND e.time >= w.lo AND e.time < w.hi
        """).df()
    ev["time"] = pd.to_datetime(ev["time"]).astype("datetime64[ns]")
    accepted = {r["code"]: set(r["units"]) for _, r in cmap.features.iterrows()}
    pattern = {r["key"]: r["code"] for _, r in fm.iterrows() if not r["exact"]}
    stem = ev["code"].map(lambda c: split_unit(c)[0])
    mapcode = stem.map(pattern).fillna(ev["code"])
    ok = np.array([(not accepted[m]) or (not e) or (u in accepted[m])
                   for m, u, e in zip(mapcode, ev["unit"], mapcode != ev["code"], strict=True)],
                  dtype=bool)
    screen = (ev.assign(read=ok).groupby(["code", "unit", "feature", "read"], as_index=False)
              .size().rename(columns={"size": "n_rows"}))
    ev = ev[ok]
    venous = pd.Series(dtype="int64")
    spec = cmap.specimen
    if spec and "text_value" in cols and len(ev):
        bad = ", ".join(_lit(v.upper()) for v in spec["not_arterial"])
        ven = con.execute(f"""
            SELECT DISTINCT w.stay_id AS icustay_id, e.time FROM events e
            JOIN win w ON e.subject_id = w.subject_id AND e.time >= w.lo AND e.time < w.hi
            WHERE {_match('e.code', spec['code'])} AND upper(trim(e.text_value)) IN ({bad})
            """).df()
        ven["time"] = pd.to_datetime(ven["time"]).astype("datetime64[ns]")
        gas = ev["feature"].isin(spec["features"]).to_numpy()
        hit = gas & pd.MultiIndex.from_frame(ev[["icustay_id", "time"]]).isin(
            pd.MultiIndex.from_frame(ven)) if len(ven) else np.zeros(len(ev), dtype=bool)
        venous = ev.loc[hit, "icustay_id"].value_counts()
        ev = ev[~hit]
    out = convert(ev).assign(itemid=code_itemids(ev["code"]))
    out = hourly.delete_outliers(out)
    # a MAP judged only against the systolic and diastolic of its own device at its own
    # instant (hourly.map_outside_range; devices by MIMIC item id, as the codes carry it)
    is_map = (out["feature"] == "MeanBP").to_numpy()
    refs = out[out["feature"].isin(["SysBP", "DiaBP"])]
    bad_map = np.zeros(len(out), dtype=bool)
    bad_map[is_map] = hourly.map_outside_range(out[is_map], refs)
    return out[~bad_map].drop(columns="itemid").reset_index(drop=True), screen, venous


def code_itemids(codes: pd.Series) -> np.ndarray:
    """The MIMIC item id a MEDS code carries (``LAB//220052//mmHg`` -> 220052), -1 if none."""
    part = codes.astype(str).str.split("//").str[1]
    return pd.to_numeric(part, errors="coerce").fillna(-1).astype("int64").to_numpy()


def convert(ev: pd.DataFrame) -> pd.DataFrame:
    """Values in contract units: (value + offset) * scale of the entry's conversion
    (``unit_conversions.csv``), with the MIMIC sources' temperature fix (a Celsius value
    > 70 is Fahrenheit, a Fahrenheit value in (25, 45) Celsius: charted in the wrong item)."""
    cm = data_table("unit_conversions.csv").set_index("conversion")
    v = ev["value"].to_numpy(float)
    conv = ev["conversion"].to_numpy(object).copy()
    temp = (ev["feature"] == "Temp_C").to_numpy()
    conv[temp & (conv == "none") & (v > 70)] = "F_to_C"
    conv[temp & (conv == "F_to_C") & (v > 25) & (v < 45)] = "none"
    out = (v + cm.loc[conv, "offset"].to_numpy(float)) * cm.loc[conv, "scale"].to_numpy(float)
    return pd.DataFrame({"icustay_id": ev["icustay_id"].to_numpy(),
                         "time": ev["time"].to_numpy(), "feature": ev["feature"].to_numpy(),
                         "value": out})


def infusions(con, cmap: CodeMap, win: pd.DataFrame, cols: set[str]) -> pd.DataFrame:
    """The mapped infusions overlapping the stays' windows: icustay_id, itemid (the map's
    item key), action, starttime, endtime, rate, rateuom, amount, amountuom, status. A start
    pairs with its end by (subject, order_id, item) when the shards have ``order_id``, else
    with the next end of the same item; an unpaired start is not used."""
    im = cmap.infusions[["item", "start", "end", "action"]]
    con.register("imap", im)
    con.register("win_in", win)
    unit = "e.unit" if "unit" in cols else "CAST(NULL AS VARCHAR)"
    status = "e.statusdescription" if "statusdescription" in _columns(con) else \
        "CAST(NULL AS VARCHAR)"
    order = "e.order_id" if "order_id" in _columns(con) else "CAST(NULL AS BIGINT)"
    base = f"""
        SELECT e.subject_id, e.time, m.item, m.action, CAST(e.numeric_value AS DOUBLE) AS v,
               {unit} AS unit, {status} AS status, {order} AS order_id,
               row_number() OVER (PARTITION BY e.subject_id, m.item ORDER BY e.time) AS k
        FROM events e JOIN imap m ON e.code = m.{{side}}
        WHERE e.subject_id IN (SELECT subject_id FROM win_in) AND e.time IS NOT NULL"""
    by_order = "order_id" in _columns(con)
    on = ("s.order_id = x.order_id" if by_order else "s.k = x.k")
    pairs = con.execute(f"""
        WITH s AS ({base.format(side='start')}), x AS ({base.format(side='end')})
        SELECT w.stay_id AS icustay_id, s.item AS itemid, s.action, s.time AS starttime,
               x.time AS endtime, s.v AS rate, s.unit AS rateuom, x.v AS amount,
               x.unit AS amountuom, coalesce(x.status, '') AS status
        FROM s JOIN x ON s.subject_id = x.subject_id AND s.item = x.item AND {on}
        JOIN win_in w ON s.subject_id = w.subject_id
        WHERE s.time < w.hi AND x.time > w.lo AND x.time >= s.time""").df()
    for col in ("starttime", "endtime"):
        pairs[col] = pd.to_datetime(pairs[col]).astype("datetime64[ns]")
    return pairs


def extract_meds(path: str | Path, code_map: str | Path | CodeMap = "mimic4", *,
                 cohort: str = "icu_admission", labels: str | Path | None = None,
                 label_value: str = "all", missing: str = "impute",
                 t_max: int = schema.T_MAX, threads: int = 1,
                 memory_limit: str | None = None,
                 temp_directory: str | Path | None = None) -> MedsCohort:
    """The hourly trajectories of a MEDS dataset (module doc); ContractError in one line at
    the first broken rule of the folder, the map or the labels."""
    if cohort not in COHORTS:
        raise ContractError(f"source.meds.cohort: {cohort!r} is not one of {COHORTS}")
    if missing not in MISSING:
        raise ContractError(f"source.meds.missing: {missing!r} is not one of {MISSING}")
    ds = open_dataset(path)
    cmap = code_map if isinstance(code_map, CodeMap) else load_code_map(code_map)
    con = connect(ds, threads, memory_limit, temp_directory)
    try:
        counts = code_counts(con)
        check_codes(cmap, counts, ds)
        if cohort == "sepsis3":
            raise _sepsis3_error(counts, ds)
        return _extract(con, ds, cmap, cohort, labels, label_value, missing, t_max)
    finally:
        con.close()


def _extract(con, ds: MedsDataset, cmap: CodeMap, cohort: str, labels, label_value: str,
             missing: str, t_max: int) -> MedsCohort:
    allst = icu_stays(con, cmap, ds)
    ids_all = allst.index
    crit = pd.DataFrame(index=ids_all)
    c = Consort()
    c.add("icu_stays", f"ICU stays ({cmap.stays['admission']} events) in {ds.label}", ids_all)
    t0_all, desc = _anchor(con, allst, cohort, labels, label_value)
    crit["cohort"] = ids_all.isin(t0_all.index)
    ids = ids_all[crit["cohort"].to_numpy()]
    c.add("cohort", desc, ids)
    t0 = t0_all.reindex(ids)
    age = (t0 - allst.loc[ids, "intime"]) / pd.Timedelta(days=365.25) + allst.loc[ids, "age"]
    crit["demographics"] = pd.Series(age.notna() & allst.loc[ids, "sex"].notna(),
                                     index=ids).reindex(ids_all)
    ids = ids[crit.loc[ids, "demographics"].to_numpy(bool)]
    c.add("demographics", f"birth ({cmap.birth}) and one sex code documented", ids)
    crit["adult"] = (age >= ADULT_AGE).reindex(ids_all)
    ids = ids[crit.loc[ids, "adult"].to_numpy(bool)]
    c.add("adult", f"age >= {ADULT_AGE} at t = 0", ids)
    end = t0.reindex(ids) + (t_max + 1) * HOUR
    covers = allst.loc[ids, "outtime"].notna() & (allst.loc[ids, "outtime"] >= end)
    crit["stay_covers_window"] = covers.reindex(ids_all)
    ids = ids[covers.to_numpy(bool)]
    c.add("stay_covers_window", f"ICU stay lasts at least {t_max + 1} h after t = 0", ids)

    t0 = t0.reindex(ids)
    max_hold = float(data_table("sample_and_hold.csv")["hold_hours"].max())
    win = pd.DataFrame({"stay_id": ids.to_numpy("int64"),
                        "subject_id": allst.loc[ids, "subject_id"].to_numpy("int64"),
                        "lo": (t0 - max_hold * HOUR).to_numpy(),
                        "hi": (t0 + (t_max + 1) * HOUR).to_numpy()})
    cols = set(ds.columns)
    ev, screen, venous = _feature_events(con, cmap, win, cols)
    ev = hourly.complete_bp(ev)
    raw = hourly.block_means(ev, t0, FEATS, t_max)
    held = hourly.sample_and_hold(raw, ev, t0, how="last_value")
    vit = held[list(hourly.VITALS)].notna().all(axis=1).groupby(level=0).all()
    crit["vitals_complete"] = vit.reindex(ids_all)
    ids = ids[vit.reindex(ids).fillna(False).to_numpy(bool)]
    c.add("vitals_complete", f"every vital present in each hour t = 0..{t_max} (after "
          "sample-and-hold)", ids)
    held = held.loc[ids]
    after_hold_missing = held[["weight", *hourly.LABS]].isna()
    if missing == "impute" and len(ids):
        x = held[list(schema.FEATURES[2:])].to_numpy(float)
        subj = allst["subject_id"].reindex(held.index.get_level_values(0)).to_numpy("int64")
        held[list(schema.FEATURES[2:])] = hourly.knn_impute(
            x, groups=subj, times=held.index.get_level_values("t").to_numpy())
        step_desc = ("weight and every lab of every hour observed, held or imputed from "
                     "another patient's same or earlier hour (1-NN)")
    else:
        step_desc = f"weight and every lab observed or held in each hour t = 0..{t_max}"
    done = held[list(schema.FEATURES[2:])].notna().all(axis=1).groupby(level=0).all()
    crit["complete"] = done.reindex(ids_all)
    ids = ids[done.reindex(ids).fillna(False).to_numpy(bool)]
    c.add("complete", step_desc, ids)
    held, t0 = held.loc[ids], t0.reindex(ids)
    stays = allst.loc[ids]

    inf = infusions(con, cmap, win[win["stay_id"].isin(ids)], cols)
    inf = inf[inf["status"] != "Rewritten"]
    fl = inf[(inf["action"] == "fluid") & inf["amount"].notna()]
    ml = fl["amountuom"].isna() | fl["amountuom"].str.lower().isin(["ml"])
    fl_unit_bad = fl.loc[~ml, "icustay_id"].value_counts()
    fl = fl[ml]
    va = inf[(inf["action"] == "vasopressor") & inf["rate"].notna()]
    ne = doses.norepinephrine_equivalent(va, "mv", cmap.vaso_rules) if len(va) else \
        pd.Series(dtype=float)
    va_unit_bad = va.loc[ne.isna(), "icustay_id"].value_counts() if len(va) else \
        pd.Series(dtype="int64")
    tonicity = cmap.infusions.dropna(subset=["tonicity"]).set_index("item")["tonicity"]
    none_cv = pd.DataFrame(columns=["icustay_id", "itemid", "charttime", "amount", "rate",
                                    "rateuom"])
    fluid = doses.hourly_fluid(t0, fl, none_cv, t_max, tonicity=tonicity)
    vaso = doses.hourly_vasopressor(t0, va, none_cv, t_max, rules=cmap.vaso_rules)

    traj = held.reset_index()
    key = pd.MultiIndex.from_frame(traj[["icustay_id", "t"]])
    traj["iv_fluid"] = fluid.reindex(key).fillna(0.0).to_numpy() if len(ids) else []
    traj["vasopressor"] = vaso.reindex(key).fillna(0.0).to_numpy() if len(ids) else []
    age = (t0 - stays["intime"]) / pd.Timedelta(days=365.25) + stays["age"]
    traj["age"] = age.reindex(traj["icustay_id"]).to_numpy()
    traj["sex"] = stays["sex"].reindex(traj["icustay_id"]).to_numpy(float)
    traj[schema.SUBJECT_ID] = stays["subject_id"].reindex(traj["icustay_id"]).to_numpy()
    traj = traj.rename(columns={"icustay_id": schema.STAY_ID})
    traj = traj[[*schema.TRAJECTORY_COLUMNS, schema.SUBJECT_ID]]
    if len(traj):
        traj = schema.validate_trajectories(traj, source=f"meds extraction of {ds.path}",
                                            t_max=t_max)
    audit = allst.reset_index()[["stay_id", "subject_id", "intime", "outtime"]]
    audit["t0"] = t0_all.reindex(audit["stay_id"]).to_numpy()
    for col in crit.columns:
        audit[col] = crit[col].reindex(audit["stay_id"]).astype("boolean").to_numpy()
    audit["in_cohort"] = audit["stay_id"].isin(ids)
    for name, s in (("n_venous_gas_rows", venous),
                    ("n_fluid_rows_unit_unknown", fl_unit_bad),
                    ("n_vaso_rows_unit_unknown", va_unit_bad)):
        audit[name] = s.reindex(audit["stay_id"]).fillna(0).astype("int64").to_numpy()
    units = screen.sort_values(["feature", "code"]).reset_index(drop=True)
    anchors = pd.DataFrame({schema.STAY_ID: ids.to_numpy("int64"),
                            schema.SUBJECT_ID: stays["subject_id"].to_numpy("int64"),
                            "intime": stays["intime"].to_numpy(), "t0": t0.to_numpy()})
    return MedsCohort(trajectories=traj.reset_index(drop=True), consort=c.frame(),
                      missingness=missingness(raw.loc[ids], after_hold_missing.loc[ids],
                                              len(ids), t_max),
                      stays=audit, units=units, anchors=anchors, dataset=ds.label)


def missingness(raw: pd.DataFrame, after_hold_missing: pd.DataFrame, n: int, t_max: int
                ) -> pd.DataFrame:
    """Missing values before sample-and-hold and imputed cells, per feature and hour."""
    rows = []
    for f in schema.FEATURES:
        for t in range(t_max + 1):
            nm = ni = 0
            if f not in ("age", "sex") and n:
                nm = int(raw[f].xs(t, level="t").isna().sum())
                if f in after_hold_missing:
                    ni = int(after_hold_missing[f].xs(t, level="t").sum())
            rows.append({"feature": f, "t": t, "n_missing_raw": nm,
                         "share_missing_raw": nm / n if n else np.nan, "n_imputed": ni})
    return pd.DataFrame(rows)
