"""Benchmark: MIMIC-III extraction time against the number of ICU stays.

Writes synthetic tables in the MIMIC-III v1.4 schema (the columns the extraction reads;
invented values, no patient data) for N stays, runs ``extract_mimic3`` on them and reports
wall time per stage (cProfile cumulative times of the stage functions) and per stay. A step
that is linear in N keeps its time per stay flat as N grows; a quadratic one doubles it
when N doubles.

Each synthetic stay: MetaVision (even ids) or CareVue (odd ids); antibiotic + culture
(suspected infection); platelets 80 (SOFA 2); vitals hourly from a random delay of 0-2.5 h
after INTIME for 12 h (so both anchors have work), temperature every 3 h, a weight; labs at
INTIME - 1 h and + 3 h with 25 % of values missing (1-NN imputation has work); an NaCl
infusion and a norepinephrine infusion (MV) or charted rates (CV).

Run:  PYTHONPATH=src python benchmarks/bench_mimic3.py --n 1000 2000 5000 --knn-rows 10000 20000
"""

from __future__ import annotations

import os

# one BLAS thread: on a shared, loaded machine a second spinning BLAS thread makes the matrix
# products of the 1-NN imputation 2x slower and the timings erratic (measured)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from twinfalsify.sources.mimic3 import extract_mimic3  # noqa: E402
from twinfalsify.sources.mimic3 import hourly as hourly_mod  # noqa: E402

H = np.timedelta64(3600, "s")
LAB_ITEMS = {50971: 4.0, 50983: 140.0, 50902: 100.0, 50931: 120.0, 50893: 8.5, 50882: 24.0,
             50821: 90.0, 50818: 40.0, 50820: 7.4, 50912: 1.0, 50885: 0.5}
MV_VITALS = {220045: 85.0, 220179: 115.0, 220180: 60.0, 220181: 78.0, 220210: 19.0}
CV_VITALS = {211: 85.0, 51: 115.0, 8368: 60.0, 52: 78.0, 618: 19.0}


def _fmt(t: np.ndarray) -> np.ndarray:
    return np.datetime_as_string(t.astype("datetime64[s]"), unit="s")


def write_tables(folder: Path, n: int, seed: int = 0) -> None:
    """Synthetic MIMIC-III v1.4-schema CSVs for ``n`` stays in ``folder`` (vectorised)."""
    rng = np.random.default_rng(seed)
    ids = np.arange(1, n + 1)
    icu = 200_000 + ids
    hadm = 100_000 + ids
    cv = ids % 2 == 1
    intime = (np.datetime64("2150-01-01T00:00:00")
              + rng.integers(0, 3650 * 24, n) * H).astype("datetime64[s]")
    outtime = intime + 48 * H
    dob = intime - (rng.uniform(20, 85, n) * 365.25 * 24 * H).astype("timedelta64[s]")
    pd.DataFrame({"SUBJECT_ID": ids, "GENDER": np.where(rng.random(n) < .5, "F", "M"),
                  "DOB": _fmt(dob), "DOD": ""}).to_csv(folder / "PATIENTS.csv", index=False)
    pd.DataFrame({"SUBJECT_ID": ids, "HADM_ID": hadm, "ADMITTIME": _fmt(intime - 6 * H),
                  "DISCHTIME": _fmt(intime + 120 * H), "DEATHTIME": "",
                  "HOSPITAL_EXPIRE_FLAG": 0}).to_csv(folder / "ADMISSIONS.csv", index=False)
    pd.DataFrame({"SUBJECT_ID": ids, "HADM_ID": hadm, "ICUSTAY_ID": icu,
                  "DBSOURCE": np.where(cv, "carevue", "metavision"), "INTIME": _fmt(intime),
                  "OUTTIME": _fmt(outtime)}).to_csv(folder / "ICUSTAYS.csv", index=False)
    pd.DataFrame({"SUBJECT_ID": ids, "HADM_ID": hadm, "ICUSTAY_ID": icu,
                  "STARTDATE": _fmt(intime - 2 * H), "DRUG": "Vancomycin", "ROUTE": "IV"}
                 ).to_csv(folder / "PRESCRIPTIONS.csv", index=False)
    ct = intime - 4 * H
    pd.DataFrame({"SUBJECT_ID": ids, "HADM_ID": hadm, "CHARTDATE": _fmt(ct), "CHARTTIME": _fmt(ct)}
                 ).to_csv(folder / "MICROBIOLOGYEVENTS.csv", index=False)

    # CHARTEVENTS: vitals hourly from a per-stay delay, temperature every 3 h, one weight
    delay = rng.choice([0.25, 0.5, 1.5, 2.5], n, p=[.4, .2, .3, .1])
    hours = np.arange(12)
    parts = []
    for mv_item, cv_item in zip(MV_VITALS, CV_VITALS, strict=True):
        sid = np.repeat(np.arange(n), len(hours))
        t = intime[sid] + ((delay[sid] + np.tile(hours, n)) * 3600).astype("timedelta64[s]")
        item = np.where(cv[sid], cv_item, mv_item)
        val = MV_VITALS[mv_item] + rng.normal(0, 5, len(sid))
        parts.append(pd.DataFrame({"i": sid, "ITEMID": item, "t": t, "VALUENUM": val}))
    sid = np.repeat(np.arange(n), 4)
    t = intime[sid] + ((delay[sid] + np.tile([0, 3, 6, 9], n)) * 3600).astype("timedelta64[s]")
    parts.append(pd.DataFrame({"i": sid, "ITEMID": np.where(cv[sid], 678, 223761), "t": t,
                               "VALUENUM": 98.6 + rng.normal(0, 1, len(sid))}))
    parts.append(pd.DataFrame({"i": np.arange(n), "ITEMID": np.where(cv, 3581, 226512),
                               "t": intime + 600 * np.timedelta64(1, "s"),
                               "VALUENUM": np.where(cv, 165.0, 75.0)}))
    ce = pd.concat(parts, ignore_index=True)
    i = ce["i"].to_numpy()
    pd.DataFrame({"SUBJECT_ID": ids[i], "HADM_ID": hadm[i], "ICUSTAY_ID": icu[i],
                  "ITEMID": ce["ITEMID"], "CHARTTIME": _fmt(ce["t"].to_numpy()),
                  "VALUE": ce["VALUENUM"].round(1).astype(str), "VALUENUM": ce["VALUENUM"].round(1),
                  "ERROR": np.where(cv[i], "", "0")}
                 ).to_csv(folder / "CHARTEVENTS.csv", index=False)

    # LABEVENTS: two draws, 25 % of lab values missing; platelets always (SOFA)
    rows = []
    for off in (-1, 3):
        for item, v in LAB_ITEMS.items():
            keep = rng.random(n) >= 0.25
            rows.append(pd.DataFrame({"i": np.flatnonzero(keep), "ITEMID": item,
                                      "t": intime[keep] + off * H,
                                      "VALUENUM": v * (1 + rng.normal(0, .03, keep.sum()))}))
        rows.append(pd.DataFrame({"i": np.arange(n), "ITEMID": 51265, "t": intime + off * H,
                                  "VALUENUM": 80.0}))
    le = pd.concat(rows, ignore_index=True)
    i = le["i"].to_numpy()
    pd.DataFrame({"SUBJECT_ID": ids[i], "HADM_ID": hadm[i], "ITEMID": le["ITEMID"],
                  "CHARTTIME": _fmt(le["t"].to_numpy()), "VALUENUM": le["VALUENUM"].round(3)}
                 ).to_csv(folder / "LABEVENTS.csv", index=False)

    # inputs: MV NaCl infusion + norepinephrine infusion; CV NaCl bolus + Levophed rate
    mv = np.flatnonzero(~cv)
    s, e = intime[mv] + H // 2, intime[mv] + 3 * H
    pd.DataFrame({
        "ICUSTAY_ID": np.concatenate([icu[mv], icu[mv]]),
        "STARTTIME": _fmt(np.concatenate([s, s])), "ENDTIME": _fmt(np.concatenate([e, e])),
        "ITEMID": np.repeat([225158, 221906], len(mv)),
        "AMOUNT": np.repeat([500.0, np.nan], len(mv)),
        "RATE": np.repeat([200.0, 0.1], len(mv)),
        "RATEUOM": np.repeat(["mL/hour", "mcg/kg/min"], len(mv)),
        "STATUSDESCRIPTION": "FinishedRunning"}).to_csv(folder / "INPUTEVENTS_MV.csv", index=False)
    c = np.flatnonzero(cv)
    pd.DataFrame({
        "ICUSTAY_ID": np.concatenate([icu[c], icu[c]]),
        "CHARTTIME": _fmt(np.concatenate([intime[c] + H, intime[c] + 2 * H])),
        "ITEMID": np.repeat([30018, 30047], len(c)),
        "AMOUNT": np.repeat([250.0, np.nan], len(c)),
        "RATE": np.repeat([np.nan, 8.0], len(c)),
        "RATEUOM": np.repeat(["", "mcgmin"], len(c))}).to_csv(folder / "INPUTEVENTS_CV.csv",
                                                               index=False)


STAGES = ("suspected_infection", "max_sofa", "withdrawn", "_events", "_inputs", "block_means",
          "sample_and_hold", "first_complete_vitals", "knn_impute", "hourly_fluid",
          "hourly_vasopressor", "validate_trajectories")


def run(n: int, anchor: str, threads: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        t = time.perf_counter()
        write_tables(folder, n)
        gen = time.perf_counter() - t
        prof = cProfile.Profile()
        t = time.perf_counter()
        prof.enable()
        res = extract_mimic3(folder, anchor=anchor, threads=threads)
        prof.disable()
        total = time.perf_counter() - t
    st = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    out = {"n_stays": n, "kept": res.trajectories["stay_id"].nunique(), "generate_s": gen,
           "extract_s": total}
    for name in STAGES:
        out[name] = sum(v[3] for k, v in st.items() if k[2] == name)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1000, 2000, 5000])
    p.add_argument("--anchor", default="first_vitals")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--knn-rows", type=int, nargs="*", default=[],
                   help="also time knn_impute (and the direct definition) alone on this many rows")
    a = p.parse_args()
    rows = [run(n, a.anchor, a.threads) for n in a.n]
    df = pd.DataFrame(rows).set_index("n_stays")
    pd.set_option("display.width", 200)
    print(f"anchor={a.anchor}, threads={a.threads}; seconds (cumulative, cProfile)")
    print(df.round(2).T.to_string())
    print("\nms per stay:")
    print((df[["extract_s", *STAGES]].div(df.index.to_series(), axis=0) * 1000).round(3)
          .T.to_string())
    rng = np.random.default_rng(1)
    for m in a.knn_rows:
        x = rng.normal(size=(m, 16))
        x[:, 7:][rng.random((m, 9)) < 0.25] = np.nan
        t = time.perf_counter()
        fast = hourly_mod.knn_impute(x)
        t_fast = time.perf_counter() - t
        t = time.perf_counter()
        direct = hourly_mod._knn_impute_direct(x)
        t_direct = time.perf_counter() - t
        same = np.array_equal(fast, direct, equal_nan=True)
        print(f"knn_impute, {m} rows x 16 columns (25 % of 9 columns missing): "
              f"{t_fast:.2f} s; direct definition {t_direct:.2f} s; identical: {same}")


if __name__ == "__main__":
    main()
