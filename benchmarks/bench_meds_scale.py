"""Benchmark: the ``meds`` source's extraction on a MEDS dataset of a given scale, per stage.

Runs ``extract_meds`` (preset code map ``mimic4``, cohort ``icu_admission``) on a folder
written by ``meds_synth.py`` and records, for each stage (the stage functions of
``meds.cohort`` and of the hourly / dose rules it shares with the MIMIC sources): wall time,
CPU time of the whole process (user + system, every DuckDB thread included) and the peak
resident memory during the stage (sampled every 50 ms); the whole run's peak memory, the
largest size of the DuckDB temporary folder and the load average during the run. With
``--check-scale``: whether the cohort, its hourly heart rate and its doses are exactly the
ones the generator built in. Writes one JSON file.

Run:  PYTHONPATH=src python benchmarks/bench_meds_scale.py MEDS_DIR OUT.json [--threads 2]
      (wrap in ``/usr/bin/time -v`` for the kernel's peak-RSS figure)
      PYTHONPATH=src python benchmarks/bench_meds_scale.py --table A.json B.json ...
      (the scaling table: per stage CPU time against MEDS events, a least-squares line
      through the origin per stage and its projection to full MIMIC-IV size; peak memory:
      a least-squares line with intercept, the interpreter and libraries being its base)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import psutil  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_mimic3_scale import Sampler, _dir_size  # noqa: E402,F401

from twinfalsify.sources.meds import cohort  # noqa: E402
from twinfalsify.sources.mimic3 import doses, hourly  # noqa: E402

STAGES = {cohort: ("open_dataset", "code_counts", "check_codes", "icu_stays", "_anchor",
                   "_feature_events", "infusions", "missingness"),
          hourly: ("block_means", "sample_and_hold", "knn_impute", "complete_bp"),
          doses: ("hourly_fluid", "hourly_vasopressor")}
GROUPS = {"folder check (footers)": ("open_dataset",),
          "code counts (one scan of every event)": ("code_counts", "check_codes"),
          "ICU stays, birth, sex (one scan)": ("icu_stays", "_anchor"),
          "feature values of the windows (one scan)": ("_feature_events",),
          "hourly blocks, hold, BP completion": ("block_means", "sample_and_hold",
                                                 "complete_bp"),
          "1-NN imputation": ("knn_impute",),
          "doses (one scan + hourly)": ("infusions", "hourly_fluid", "hourly_vasopressor"),
          "missingness table": ("missingness",)}


def instrument(sampler: Sampler) -> list[dict]:
    """Wrap the stage functions in their modules; returns the list the records go to."""
    import functools

    records: list[dict] = []
    stack: list[str] = []

    def wrap(name, fn):
        @functools.wraps(fn)
        def inner(*a, **k):
            path = "/".join([*stack, name])
            stack.append(name)
            outer_peak = sampler.stage_peak
            sampler.stage_peak = psutil.Process().memory_info().rss
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                records.append({"stage": path, "wall_s": time.perf_counter() - w,
                                "cpu_s": time.process_time() - c,
                                "peak_rss_mb": sampler.stage_peak / 2**20})
                sampler.stage_peak = max(outer_peak, sampler.stage_peak)
                stack.pop()
        return inner

    for mod, names in STAGES.items():
        for name in names:
            setattr(mod, name, wrap(name, getattr(mod, name)))
    return records


def check_built_in(res, scale: float, seed: int) -> dict[str, bool]:
    """Whether the extraction returned exactly the cohort, hourly heart rates and doses that
    ``meds_synth.py`` built into a dataset of this scale and seed: HR 60 + i % 40 + t; an
    NaCl 500 mL infusion from 0.5 h to 3 h (100, 200, 200, 0, 0 mL in hours 0..4) and
    norepinephrine 0.1 ug/kg/min over the same span (0.1 in hours 0..2)."""
    import meds_synth  # beside this script

    stays = meds_synth.ms.stays_frame(scale, seed, meds_synth.SHAPE)
    want = meds_synth.expected_hr(stays).set_index(["stay_id", "t"]).sort_index()
    got = res.trajectories.set_index(["stay_id", "t"]).sort_index()
    same_ids = set(got.index.get_level_values(0)) == set(want.index.get_level_values(0))
    same_idx = bool(same_ids and got.index.equals(want.index))
    t = want.index.get_level_values("t").to_numpy()
    fluid = np.array([100.0, 200.0, 200.0, 0.0, 0.0])[t]
    vaso = np.array([0.1, 0.1, 0.1, 0.0, 0.0])[t]

    def eq(col, ref):
        return bool(same_idx and np.allclose(got[col].to_numpy(float), ref, rtol=0,
                                             atol=1e-6))
    return {"cohort_equal": bool(same_ids), "hr_equal": eq("HR", want["HR"].to_numpy()),
            "fluid_equal": eq("iv_fluid", fluid), "vasopressor_equal": eq("vasopressor", vaso)}


def table(paths: list[Path]) -> str:
    """Markdown scaling table from bench JSON files, with a per-stage projection to full
    MIMIC-IV size from the runs below full size: CPU seconds per MEDS event (least squares
    through the origin) x the full size's events; peak memory by a line with intercept. A
    run at full size (scale 1) is shown as measured, beside the projection."""
    runs = sorted((json.loads(p.read_text()) for p in paths), key=lambda r: r["events"])
    part = [r for r in runs if r["scale"] < 1]
    ev = [r["events"] for r in part]
    full = part[-1]["events"] / part[-1]["scale"]  # events at scale 1 (the generator's)

    def name(r):
        return ("**full size, measured**" if r["scale"] >= 1 else f"scale {r['scale']:g}") \
            + f": {r['events'] / 1e6:.1f} M events"

    head = ("| | " + " | ".join(name(r) for r in runs)
            + f" | projected to {full / 1e6:.0f} M events from the scales below 1 |")
    lines = [head, "|---|" + "---:|" * (len(runs) + 1)]

    def stage(r, names, key="cpu_s"):
        return sum(x[key] for x in r["stages"] if x["stage"] in names)

    def fit(ys):
        den = sum(x * x for x in ev)
        return sum(x * y for x, y in zip(ev, ys, strict=True)) / den * full

    def row(label, f, fmt, proj=True):
        cells = " | ".join(fmt(f(r)) for r in runs)
        tail = fmt(fit([f(r) for r in part])) if proj else ""
        lines.append(f"| {label} | {cells} | {tail} |")

    for label, names in GROUPS.items():
        row(f"{label}, CPU s", lambda r, n=names: stage(r, n), lambda y: f"{y:.1f}")
    row("the rest (criteria, trajectories, audit), CPU s",
        lambda r: r["cpu_s"] - sum(stage(r, n) for n in GROUPS.values()), lambda y: f"{y:.1f}")
    row("**whole extraction, CPU s**", lambda r: r["cpu_s"], lambda y: f"**{y:.1f}**")
    lines.append("| whole extraction, wall s (load average) | " + " | ".join(
        f"{r['wall_s']:.0f} ({r['load_mean']:.1f})" for r in runs) + " | |")
    ys = [r["peak_rss_mb"] for r in part]
    slope, base = np.polyfit(ev, ys, 1) if len(part) > 1 else (ys[0] / ev[0], 0.0)
    lines.append("| peak resident memory, MB (projection: line with intercept) | " + " | ".join(
        f"{r['peak_rss_mb']:.0f}" for r in runs) + f" | {base + slope * full:.0f} |")
    lines.append("| DuckDB spill, peak MB | " + " | ".join(
        f"{r['temp_peak_mb']:.0f}" for r in runs) + " | |")

    def built(r):
        b = r.get("built_in")
        return "not checked" if not b else "as built" if all(b.values()) else "DIFFERS"

    lines.append("| ICU stays / cohort (against the generator) | " + " | ".join(
        f"{r['stays']:,} / {r['cohort']:,} ({built(r)})" for r in runs) + " | |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path, nargs="?")
    p.add_argument("out", type=Path, nargs="?")
    p.add_argument("--table", type=Path, nargs="+", help="print the scaling table of these")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--memory-limit", default=None, help="DuckDB memory_limit, e.g. 3GB")
    p.add_argument("--temp-dir", type=Path, default=None, help="DuckDB temp_directory")
    p.add_argument("--check-scale", type=float, default=None,
                   help="the dataset's meds_synth.py --scale: after timing, check the cohort, "
                   "its hourly HR and its doses against what the generator built in")
    p.add_argument("--check-seed", type=int, default=0, help="the dataset's --seed")
    a = p.parse_args()
    if a.table:
        print(table(a.table))
        return
    rows_file = a.folder / "rows.json"
    rows = json.loads(rows_file.read_text()) if rows_file.is_file() else {}
    sampler = Sampler(a.temp_dir)
    records = instrument(sampler)
    sampler.start()
    load0 = os.getloadavg()
    w, c = time.perf_counter(), time.process_time()
    res = cohort.extract_meds(a.folder, "mimic4", cohort="icu_admission", threads=a.threads,
                              memory_limit=a.memory_limit, temp_directory=a.temp_dir)
    wall, cpu = time.perf_counter() - w, time.process_time() - c
    sampler.stop.set()
    sampler.join()
    c0 = res.consort
    out = {"folder": a.folder.name, "scale": a.check_scale, "threads": a.threads,
           "memory_limit": a.memory_limit, "rows": rows,
           "events": rows.get("total") or int(sum(
               pq.ParquetFile(f).metadata.num_rows for f in (a.folder / "data").rglob(
                   "*.parquet"))),
           "stays": int(c0["n_stays"].iloc[0]),
           "cohort": int(res.trajectories["stay_id"].nunique()),
           "consort": c0[["step", "n_stays"]].to_dict("records"),
           "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": sampler.peak / 2**20,
           "temp_peak_mb": sampler.temp_peak / 2**20,
           "load_start": load0[0], "load_mean": sum(sampler.loads) / max(len(sampler.loads), 1),
           "load_max": max(sampler.loads, default=load0[0]),
           "cpu_count": os.cpu_count(), "ram_gb": psutil.virtual_memory().total / 2**30,
           "stages": records}
    if a.check_scale is not None:
        out["built_in"] = check_built_in(res, a.check_scale, a.check_seed)
    a.out.write_text(json.dumps(out, indent=1, default=str) + "\n")
    if "built_in" in out:
        print(f"built-in cohort, HR and doses reproduced: {out['built_in']}")
    print(f"{out['events']:,} events, {out['stays']:,} stays, cohort {out['cohort']:,}; "
          f"wall {wall:.1f} s, cpu {cpu:.1f} s, peak {out['peak_rss_mb']:.0f} MB, "
          f"load {out['load_mean']:.2f}")
    top: dict[str, list[float]] = {}
    for r in records:
        if "/" not in r["stage"]:
            t = top.setdefault(r["stage"], [0.0, 0.0, 0.0])
            t[0] += r["wall_s"]
            t[1] += r["cpu_s"]
            t[2] = max(t[2], r["peak_rss_mb"])
    for k, (wl, cp, pk) in sorted(top.items(), key=lambda kv: -kv[1][1]):
        print(f"  {k:24s} wall {wl:8.1f} s  cpu {cp:8.1f} s  peak {pk:7.0f} MB")


if __name__ == "__main__":
    main()
