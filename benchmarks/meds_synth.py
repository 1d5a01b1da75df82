"""A MIMIC-IV-sized MEDS dataset at any fraction of full size (invented values, no patient
data): ``mimic3_synth.py``'s MIMIC-IV tables written as the MIMIC-IV MEDS ETL
(MEDS_transforms) writes them.

``write_meds(folder, scale)`` generates the stays and tables of
``mimic3_synth.write_mimic3(..., shape=MIMIC4)`` (same seed, same stays, same values) and
writes them as MEDS 0.3 events instead of tables: ``data/{train,tuning,held_out}/{k}.parquet``
(``subject_id`` int64, ``time`` timestamp[us], ``code`` string, ``numeric_value`` float32,
``text_value``, ``unit``, ``hadm_id``, ``icustay_id``, ``order_id``, ``statusdescription``;
each shard sorted by subject and time, a subject in one shard), ``metadata/dataset.json``,
``metadata/codes.parquet`` and ``metadata/subject_splits.parquet``. Every shard is one
streaming DuckDB ``COPY`` over a slice of the stays, so memory stays flat whatever the scale.

The codes are the MIMIC-IV MEDS ETL's, the ones the ``meds`` source's ``mimic4`` preset reads:

- chartevents and labevents: ``LAB//{itemid}//{unit}`` (``UNK`` without a unit; MIMIC-IV's
  unit strings: ``°F``, ``mm Hg``, ``mg/dL``, ...), ``numeric_value`` = valuenum,
  ``text_value`` = value where there is no number;
- inputevents: ``INFUSION_START//{itemid}`` at starttime (rate, rate unit in ``unit``),
  ``INFUSION_END//{itemid}`` at endtime (amount, ``ml``), paired by ``order_id``, and
  ``SUBJECT_WEIGHT_AT_INFUSION//KG`` at starttime;
- outputevents: ``SUBJECT_FLUID_OUTPUT//{itemid}//ml``;
- icustays: ``ICU_ADMISSION//{careunit}`` / ``ICU_DISCHARGE//{careunit}`` with
  ``icustay_id``; admissions: ``HOSPITAL_ADMISSION//{type}//{location}`` /
  ``HOSPITAL_DISCHARGE//{location}``; patients: ``MEDS_BIRTH``, ``GENDER//{F,M}`` (no time),
  ``MEDS_DEATH``; prescriptions: ``MEDICATION//START//{drug}``;
- no microbiology (the MIMIC-IV MEDS ETL writes none), so the rows number chartevents +
  labevents + 3 x inputevents + outputevents + prescriptions + the stays', admissions' and
  patients' events: about 480 M at full size. The patients who never reach an ICU (MIMIC-IV
  v2.2's 299,712 patients and 431,231 admissions) are in the last shard.

What the ``meds`` source must find (cohort ``icu_admission``, t = 0 at ICU admission,
hours 0..4; ``expected_cohort`` / ``expected_hr``): every stay whose vitals start within its
first hour (``delay`` < 1 h) and that lasts at least 5 h, with heart rate
``60 + i % 40 + t`` in hour t.

Run:  PYTHONPATH=src python benchmarks/meds_synth.py OUT_DIR --scale 0.01
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import mimic3_synth as ms  # noqa: E402

SHAPE = ms.MIMIC4
T_MAX = 4
# MIMIC-IV's unit strings for the generator's items (labevents: the generator writes one
# placeholder unit for every lab; chartevents: MIMIC-III's '?F')
LAB_UNITS = {50971: "mEq/L", 50983: "mEq/L", 50902: "mEq/L", 50931: "mg/dL",
             50893: "mg/dL", 50882: "mEq/L", 50821: "mm Hg", 50818: "mm Hg", 50820: "units",
             50912: "mg/dL", 50885: "mg/dL", 51265: "K/uL"}
CHART_UNITS = {"?F": "°F"}
COLUMNS = {"subject_id": "BIGINT", "time": "TIMESTAMP", "code": "VARCHAR",
           "numeric_value": "FLOAT", "text_value": "VARCHAR", "unit": "VARCHAR",
           "hadm_id": "BIGINT", "icustay_id": "BIGINT", "order_id": "BIGINT",
           "statusdescription": "VARCHAR"}
# the MEDS splits; with 10 shards or more, every 9th shard is tuning and every 10th held_out
SPLITS = ("train", "tuning", "held_out")


def _row(**cols: str) -> str:
    """A SELECT list with every MEDS column (NULL of its type where not given)."""
    return ", ".join(f"CAST({cols.get(c, 'NULL')} AS {t}) AS {c}" for c, t in COLUMNS.items())


def _case(col: str, mapping: dict, default: str) -> str:
    whens = " ".join(f"WHEN {k!r} THEN {v!r}" if isinstance(k, str) else
                     f"WHEN {k} THEN {v!r}" for k, v in mapping.items())
    return f"CASE {col} {whens} ELSE {default} END"


def meds_queries(q3: dict[str, str]) -> dict[str, str]:
    """MEDS events per MIMIC-IV table (rows.json's keys), from ``mimic3_synth``'s
    MIMIC-III-shaped queries of a slice of the stays."""
    lab_unit = _case("ITEMID", LAB_UNITS, "coalesce(VALUEUOM, 'UNK')")
    chart_unit = _case("VALUEUOM", CHART_UNITS, "coalesce(VALUEUOM, 'UNK')")
    text = "CASE WHEN VALUENUM IS NULL THEN VALUE END"
    q: dict[str, str] = {}
    q["patients"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='DOB', code="'MEDS_BIRTH'")}
        FROM ({q3['PATIENTS']})
        UNION ALL SELECT {_row(subject_id='SUBJECT_ID', code="'GENDER//' || GENDER")}
        FROM ({q3['PATIENTS']})
        UNION ALL SELECT {_row(subject_id='SUBJECT_ID', time='DOD', code="'MEDS_DEATH'")}
        FROM ({q3['PATIENTS']}) WHERE DOD IS NOT NULL"""
    q["admissions"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='ADMITTIME', hadm_id='HADM_ID',
                     code="'HOSPITAL_ADMISSION//' || ADMISSION_TYPE || '//' "
                          "|| ADMISSION_LOCATION")} FROM ({q3['ADMISSIONS']})
        UNION ALL
        SELECT {_row(subject_id='SUBJECT_ID', time='DISCHTIME', hadm_id='HADM_ID',
                     code="'HOSPITAL_DISCHARGE//' || DISCHARGE_LOCATION")}
        FROM ({q3['ADMISSIONS']})"""
    unit = "'Medical Intensive Care Unit (MICU)'"
    q["icustays"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='INTIME', hadm_id='HADM_ID',
                     icustay_id='ICUSTAY_ID', code=f"'ICU_ADMISSION//' || {unit}")}
        FROM ({q3['ICUSTAYS']})
        UNION ALL
        SELECT {_row(subject_id='SUBJECT_ID', time='OUTTIME', hadm_id='HADM_ID',
                     icustay_id='ICUSTAY_ID', code=f"'ICU_DISCHARGE//' || {unit}")}
        FROM ({q3['ICUSTAYS']})"""
    q["chartevents"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='CHARTTIME', hadm_id='HADM_ID',
                     icustay_id='ICUSTAY_ID', numeric_value='VALUENUM', text_value=text,
                     code=f"'LAB//' || ITEMID || '//' || {chart_unit}")}
        FROM ({q3['CHARTEVENTS']})"""
    q["labevents"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='CHARTTIME', hadm_id='HADM_ID',
                     numeric_value='VALUENUM', text_value=text,
                     code=f"'LAB//' || ITEMID || '//' || {lab_unit}")}
        FROM ({q3['LABEVENTS']})"""
    inf = dict(subject_id="SUBJECT_ID", hadm_id="HADM_ID", icustay_id="ICUSTAY_ID",
               order_id="ORDERID", statusdescription="STATUSDESCRIPTION")
    q["inputevents"] = f"""
        SELECT {_row(**inf, time='STARTTIME', code="'INFUSION_START//' || ITEMID",
                     numeric_value='RATE', unit='RATEUOM')} FROM ({q3['INPUTEVENTS_MV']})
        UNION ALL
        SELECT {_row(**inf, time='ENDTIME', code="'INFUSION_END//' || ITEMID",
                     numeric_value='AMOUNT', unit='AMOUNTUOM')} FROM ({q3['INPUTEVENTS_MV']})
        UNION ALL
        SELECT {_row(subject_id='SUBJECT_ID', hadm_id='HADM_ID', icustay_id='ICUSTAY_ID',
                     time='STARTTIME', code="'SUBJECT_WEIGHT_AT_INFUSION//KG'",
                     numeric_value='PATIENTWEIGHT')} FROM ({q3['INPUTEVENTS_MV']})"""
    q["outputevents"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='CHARTTIME', hadm_id='HADM_ID',
                     icustay_id='ICUSTAY_ID', numeric_value='VALUE',
                     code="'SUBJECT_FLUID_OUTPUT//' || ITEMID || '//ml'")}
        FROM ({q3['OUTPUTEVENTS']})"""
    q["prescriptions"] = f"""
        SELECT {_row(subject_id='SUBJECT_ID', time='STARTDATE', hadm_id='HADM_ID',
                     code="'MEDICATION//START//' || DRUG")} FROM ({q3['PRESCRIPTIONS']})"""
    return q


def padding_query(n_stays: int) -> str:
    """Events of the patients and admissions that never reach an ICU (``mimic3_synth``'s
    MIMIC-IV padding: subjects n + 1, n + 2, ...; birth on 1 January of anchor_year -
    anchor_age)."""
    pad_pat = max(int(round(SHAPE.full_rows["PATIENTS"] * n_stays / SHAPE.full_stays))
                  - n_stays, 0)
    pad_adm = max(int(round(SHAPE.full_rows["ADMISSIONS"] * n_stays / SHAPE.full_stays))
                  - n_stays, 0) if pad_pat else 0
    subj = f"{n_stays + 1} + j"
    birth = "make_timestamp(2150 + j % 50 - (20 + j % 70), 1, 1, 0, 0, 0)"
    adm_subj = f"{n_stays + 1} + j % {max(pad_pat, 1)}"
    adm_t = ms._ts("TIMESTAMP '2150-01-01'", "24 * 7 * j")
    dis_t = ms._ts("TIMESTAMP '2150-01-01'", "24 * 7 * j + 72")
    hadm = f"{100_000 + n_stays} + j"
    return f"""
        SELECT {_row(subject_id=subj, time=birth, code="'MEDS_BIRTH'")}
        FROM range({pad_pat}) r(j)
        UNION ALL SELECT {_row(subject_id=subj,
                               code="CASE WHEN j % 2 = 0 THEN 'GENDER//F' ELSE 'GENDER//M' END")}
        FROM range({pad_pat}) r(j)
        UNION ALL SELECT {_row(subject_id=adm_subj, time=adm_t, hadm_id=hadm,
                               code="'HOSPITAL_ADMISSION//EW EMER.//EMERGENCY ROOM'")}
        FROM range({pad_adm}) r(j)
        UNION ALL SELECT {_row(subject_id=adm_subj, time=dis_t, hadm_id=hadm,
                               code="'HOSPITAL_DISCHARGE//HOME'")}
        FROM range({pad_adm}) r(j)"""


def write_meds(folder: Path, scale: float, seed: int = 0, stays_per_shard: int = 1500,
               threads: int = 2, memory_limit: str = "2GB") -> pd.DataFrame:
    """Write the MEDS dataset for ``scale`` x full MIMIC-IV v2.2 into ``folder``; returns the
    stays frame (for ``expected_cohort`` / ``expected_hr``). ``rows.json`` beside ``data/``:
    the events written per MIMIC-IV table."""
    ms._check_filler()
    folder = Path(folder)
    stays = ms.stays_frame(scale, seed, SHAPE)
    n = len(stays)
    cuts = list(range(0, n, stays_per_shard)) + [n]
    n_shards = len(cuts)  # the stays' slices and one shard of patients without an ICU stay
    split_of = [SPLITS[1] if n_shards >= 10 and k % 10 == 8 else
                SPLITS[2] if n_shards >= 10 and k % 10 == 9 else SPLITS[0]
                for k in range(n_shards)]
    for s in SPLITS:
        (folder / "data" / s).mkdir(parents=True, exist_ok=True)
    (folder / "metadata").mkdir(parents=True, exist_ok=True)
    con = duckdb.connect()
    con.execute(f"SET threads = {int(threads)}")
    con.execute(f"SET memory_limit = '{memory_limit}'")
    con.execute(f"SET temp_directory = '{folder / '.tmp'}'")
    rows: dict[str, int] = {}
    splits = []
    try:
        for k in range(n_shards):
            if k < n_shards - 1:
                chunk = stays.iloc[cuts[k]:cuts[k + 1]]
                q = meds_queries(ms.table_queries(con, chunk, scale, SHAPE))
                ids = chunk["subject_id"].to_numpy()
            else:
                q = {"patients_without_icu": padding_query(n)}
                pad = con.execute(f"SELECT DISTINCT subject_id FROM ({q['patients_without_icu']})"
                                  ).fetchnumpy()["subject_id"]
                ids = pad
            if not len(ids):
                continue
            for t, sql in q.items():  # rows per table (counted on the fly, cheap)
                con.execute(f"CREATE OR REPLACE TEMP VIEW v_{t} AS {sql}")
            union = " UNION ALL ".join(f"SELECT *, '{t}' AS _t FROM v_{t}" for t in q)
            path = folder / "data" / split_of[k] / f"{k}.parquet"
            con.execute(f"CREATE OR REPLACE TEMP TABLE shard AS {union}")
            for t, c in con.execute("SELECT _t, count(*) FROM shard GROUP BY 1").fetchall():
                rows[t] = rows.get(t, 0) + int(c)
            cols = ", ".join(COLUMNS)
            con.execute(f"COPY (SELECT {cols} FROM shard ORDER BY subject_id, time NULLS FIRST) "
                        f"TO '{path}' (FORMAT parquet, ROW_GROUP_SIZE 1000000)")
            con.execute("DROP TABLE shard")
            splits.append(pd.DataFrame({"subject_id": ids.astype("int64"),
                                        "split": split_of[k]}))
        shards = f"read_parquet('{folder}/data/*/*.parquet')"
        con.execute(f"COPY (SELECT code, CAST(NULL AS VARCHAR) AS description, "
                    f"CAST([] AS VARCHAR[]) AS parent_codes FROM {shards} GROUP BY code "
                    f"ORDER BY code) TO '{folder}/metadata/codes.parquet' (FORMAT parquet)")
    finally:
        con.close()
    sp = pd.concat(splits, ignore_index=True)
    sp.to_parquet(folder / "metadata" / "subject_splits.parquet", index=False)
    meta = {"dataset_name": "MIMIC-IV (synthetic, benchmarks/meds_synth.py)",
            "dataset_version": f"v2.2 shape, scale {scale}, seed {seed}",
            "etl_name": "twinfalsify benchmarks/meds_synth.py", "etl_version": "1",
            "meds_version": "0.3.3"}
    (folder / "metadata" / "dataset.json").write_text(json.dumps(meta, indent=1) + "\n")
    rows["ICUSTAYS"] = n
    rows["total"] = sum(v for t, v in rows.items() if t != "ICUSTAYS")
    (folder / "rows.json").write_text(json.dumps(rows, indent=1) + "\n")
    return stays


def expected_cohort(stays: pd.DataFrame, t_max: int = T_MAX) -> pd.Index:
    """ICU stay ids the ``meds`` source (cohort icu_admission, missing impute) must keep:
    vitals from within the first hour (every hour 0..t_max then has HR, BP, RR; temperature
    at hours 0 and 4, held in between) and a stay of at least t_max + 1 hours (every stay of
    the MIMIC-IV shape is adult and has birth and sex)."""
    ok = (stays["delay"] < 1) & (stays["los_h"] >= t_max + 1)
    return pd.Index(stays.loc[ok, "icustay_id"].to_numpy("int64"))


def expected_hr(stays: pd.DataFrame, t_max: int = T_MAX) -> pd.DataFrame:
    """stay_id, t, HR of the cohort's trajectories by construction: 60 + i % 40 + t."""
    ids = expected_cohort(stays, t_max)
    s = stays.set_index("icustay_id").loc[ids]
    t = np.tile(np.arange(t_max + 1), len(ids))
    return pd.DataFrame({"stay_id": np.repeat(ids.to_numpy(), t_max + 1), "t": t,
                         "HR": 60.0 + np.repeat(s["hr_shift"].to_numpy(), t_max + 1) + t})


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path)
    p.add_argument("--scale", type=float, required=True, help="fraction of full MIMIC-IV")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stays-per-shard", type=int, default=1500)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--memory-limit", default="2GB")
    a = p.parse_args()
    t = time.perf_counter()
    stays = write_meds(a.folder, a.scale, a.seed, a.stays_per_shard, a.threads,
                       a.memory_limit)
    rows = json.loads((a.folder / "rows.json").read_text())
    size = sum(f.stat().st_size for f in (a.folder / "data").rglob("*.parquet"))
    print(f"{len(stays)} stays, expected cohort {len(expected_cohort(stays))}; "
          f"{rows['total']:,} events, {size / 1e6:.1f} MB; {time.perf_counter() - t:.0f} s")
    for k, v in rows.items():
        print(f"  {k}: {v:,}")


if __name__ == "__main__":
    main()
