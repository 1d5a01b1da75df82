"""Benchmark: the MIMIC-III (or MIMIC-IV) extraction on tables of a given scale, per stage.

Runs ``extract_mimic3`` on a folder written by ``mimic3_synth.py`` (``extract_mimic4`` when
the folder has MIMIC-IV's layout, ``--shape mimic4``) and records, for each
stage of the extraction (the stage functions of ``cohort``; nested calls are reported under
their caller, e.g. ``max_sofa/_events``): wall time, CPU time of the whole process (user +
system, every DuckDB thread included; load on a shared machine changes it little, unlike wall
time) and the peak resident memory of the process during the stage (sampled every 50 ms).
Also: the whole run's peak memory, the largest size of the DuckDB temporary folder, the load
average during the run, and the rows of each input table. Writes one JSON file.

Run:  PYTHONPATH=src python benchmarks/bench_mimic3_scale.py TABLES_DIR OUT.json [--threads 2]
      (wrap in ``/usr/bin/time -v`` for the kernel's peak-RSS figure)
      PYTHONPATH=src python benchmarks/bench_mimic3_scale.py --table A.json B.json ...
      (the scaling table: per stage CPU time against CHARTEVENTS rows, a least-squares line
      through the origin per stage and its projection to the full release's CHARTEVENTS)
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import duckdb  # noqa: E402
import numpy as np  # noqa: E402
import psutil  # noqa: E402

from twinfalsify.sources.mimic3 import cohort, doses, hourly, tables  # noqa: E402
from twinfalsify.sources.mimic4 import extract_mimic4  # noqa: E402

STAGES = {tables: ("stage",),
          cohort: ("_stays", "suspected_infection", "max_sofa", "withdrawn", "_events",
                   "_inputs", "first_complete_vitals", "_audit"),
          hourly: ("block_means", "sample_and_hold", "knn_impute", "complete_bp"),
          doses: ("hourly_fluid", "hourly_vasopressor")}


def _dir_size(path: Path) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total


class Sampler(threading.Thread):
    """Peak RSS of this process (and of the current stage), temp-folder size, load."""

    def __init__(self, temp_dir: Path | None) -> None:
        super().__init__(daemon=True)
        self.proc = psutil.Process()
        self.temp_dir = temp_dir
        self.peak = self.stage_peak = 0
        self.temp_peak = 0
        self.loads: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        n = 0
        while not self.stop.is_set():
            rss = self.proc.memory_info().rss
            self.peak = max(self.peak, rss)
            self.stage_peak = max(self.stage_peak, rss)
            if n % 20 == 0:
                self.loads.append(os.getloadavg()[0])
                if self.temp_dir is not None and self.temp_dir.exists():
                    self.temp_peak = max(self.temp_peak, _dir_size(self.temp_dir))
            n += 1
            time.sleep(0.05)


def instrument(sampler: Sampler) -> list[dict]:
    """Wrap the stage functions in their modules; returns the list the records go to."""
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


def table_rows(folder: Path) -> dict[str, int]:
    """Rows per table: the generator's rows.json when present, else counted."""
    if (folder / "rows.json").is_file():
        return json.loads((folder / "rows.json").read_text())
    con = duckdb.connect()
    out = {}
    for p in sorted(folder.iterdir()):
        if p.name.endswith((".csv.gz", ".parquet")):
            rd = (f"read_parquet('{p}')" if p.name.endswith(".parquet") else
                  f"read_csv('{p}', header = true, all_varchar = true)")
            out[p.name.split(".")[0]] = con.execute(f"SELECT count(*) FROM {rd}").fetchone()[0]
    con.close()
    return out


GROUPS = {"staging (one pass over the files)": ("stage",),
          "suspected infection": ("suspected_infection",),
          "SOFA (max over onset window)": ("max_sofa",),
          "withdrawal": ("withdrawn",),
          "hourly events + weight": ("_events",),
          "hourly blocks, hold, anchor": ("block_means", "sample_and_hold", "complete_bp",
                                          "first_complete_vitals"),
          "1-NN imputation": ("knn_impute",),
          "doses": ("_inputs", "hourly_fluid", "hourly_vasopressor"),
          "audit table": ("_audit",)}
# full CHARTEVENTS rows per release (MIMIC-III v1.4; MIMIC-IV v2.2 chartevents)
FULL_CHARTEVENTS = {"mimic3": 330_712_483, "mimic4": 313_645_063}


def shape_of(folder: Path) -> str:
    """``mimic4`` when the folder has MIMIC-IV's layout (icu/icustays.*), else ``mimic3``."""
    return "mimic4" if list((folder / "icu").glob("icustays.*")) else "mimic3"


def table(paths: list[Path]) -> str:
    """Markdown scaling table from bench JSON files, with a per-stage projection to full
    size: CPU seconds per CHARTEVENTS row (least squares through the origin) x full rows."""
    runs = sorted((json.loads(p.read_text()) for p in paths),
                  key=lambda r: r["rows"].get("CHARTEVENTS", 0))
    shapes = {r.get("shape", "mimic3") for r in runs}
    if len(shapes) != 1:
        raise SystemExit(f"--table: runs of different releases {sorted(shapes)}; give one")
    full = FULL_CHARTEVENTS[shapes.pop()]
    rows = [r["rows"].get("CHARTEVENTS", 0) for r in runs]
    head = ("| | " + " | ".join(f"{n / 1e6:.1f} M rows" for n in rows)
            + f" | projected to {full / 1e6:.1f} M rows |")
    lines = [head, "|---|" + "---:|" * (len(runs) + 1)]

    def stage_cpu(r, names):
        return sum(x["cpu_s"] for x in r["stages"] if x["stage"] in names)

    def fit(ys):
        num = sum(x * y for x, y in zip(rows, ys, strict=True))
        den = sum(x * x for x in rows)
        return num / den * full if den else float("nan")

    for label, names in GROUPS.items():
        ys = [stage_cpu(r, names) for r in runs]
        if not any(ys):
            continue
        lines.append(f"| {label}, CPU s | " + " | ".join(f"{y:.1f}" for y in ys)
                     + f" | {fit(ys):.0f} |")
    grouped = [sum(stage_cpu(r, names) for names in GROUPS.values()) for r in runs]
    ys = [r["cpu_s"] - g for r, g in zip(runs, grouped, strict=True)]
    lines.append("| the rest (opening files, stays, criteria, CONSORT), CPU s | "
                 + " | ".join(f"{y:.1f}" for y in ys) + f" | {fit(ys):.0f} |")
    ys = [r["cpu_s"] for r in runs]
    lines.append("| **whole extraction, CPU s** | " + " | ".join(f"**{y:.1f}**" for y in ys)
                 + f" | **{fit(ys):.0f}** |")
    lines.append("| whole extraction, wall s (load) | " + " | ".join(
        f"{r['wall_s']:.0f} ({r['load_mean']:.0f})" for r in runs) + " | |")
    lines.append("| peak resident memory, MB | " + " | ".join(
        f"{r['peak_rss_mb']:.0f}" for r in runs) + " | |")
    lines.append("| staged copies + spill, peak MB | " + " | ".join(
        f"{r['temp_peak_mb']:.0f}" for r in runs) + " | |")
    lines.append("| ICU stays / cohort | " + " | ".join(
        f"{r['rows'].get('ICUSTAYS', 0):,} / {r['cohort']:,}" for r in runs) + " | |")
    return "\n".join(lines)


def check_built_in(res, scale: float, seed: int, shape: str) -> dict[str, bool]:
    """Whether the extraction returned exactly the cohort (stay ids) and hourly heart rates
    that ``mimic3_synth.py`` built into tables of this scale and seed."""
    import mimic3_synth  # beside this script

    stays = mimic3_synth.stays_frame(scale, seed, mimic3_synth.SHAPES[shape])
    want = mimic3_synth.expected_hr(stays).set_index(["stay_id", "t"])["HR"].sort_index()
    got = res.trajectories.set_index(["stay_id", "t"])["HR"].sort_index()
    same_ids = set(got.index.get_level_values(0)) == set(want.index.get_level_values(0))
    same_hr = bool(same_ids and got.index.equals(want.index)
                   and np.allclose(got.to_numpy(), want.to_numpy(), rtol=0, atol=1e-9))
    return {"cohort_equal": bool(same_ids), "hr_equal": same_hr}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path, nargs="?")
    p.add_argument("out", type=Path, nargs="?")
    p.add_argument("--table", type=Path, nargs="+", help="print the scaling table of these")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--memory-limit", default=None, help="DuckDB memory_limit, e.g. 4GB")
    p.add_argument("--temp-dir", type=Path, default=None, help="DuckDB temp_directory")
    p.add_argument("--no-count", action="store_true", help="skip counting the input rows")
    p.add_argument("--no-stage", action="store_true", help="query the files directly")
    p.add_argument("--check-scale", type=float, default=None,
                   help="the tables' mimic3_synth.py --scale: after timing, check that the "
                   "cohort and its hourly HR are exactly the ones the generator built in")
    p.add_argument("--check-seed", type=int, default=0, help="the tables' --seed")
    a = p.parse_args()
    if a.table:
        print(table(a.table))
        return
    rows = {} if a.no_count else table_rows(a.folder)
    sampler = Sampler(a.temp_dir)
    records = instrument(sampler)
    sampler.start()
    load0 = os.getloadavg()
    shape = shape_of(a.folder)
    extract = extract_mimic4 if shape == "mimic4" else cohort.extract_mimic3
    w, c = time.perf_counter(), time.process_time()
    res = extract(a.folder, threads=a.threads, memory_limit=a.memory_limit,
                  temp_directory=a.temp_dir, stage=not a.no_stage)
    wall, cpu = time.perf_counter() - w, time.process_time() - c
    sampler.stop.set()
    sampler.join()
    out = {"folder": a.folder.name, "shape": shape, "threads": a.threads,
           "staged": not a.no_stage,
           "memory_limit": a.memory_limit, "rows": rows,
           "cohort": int(res.trajectories["stay_id"].nunique()),
           # equal digests = equal outputs (staged against --no-stage runs of the same tables)
           "digest": {f: hashlib.sha256(getattr(res, f).to_csv(index=False).encode()
                                        ).hexdigest()[:16]
                      for f in ("trajectories", "consort", "missingness", "anchors", "imputed",
                                "stays")},
           "consort": res.consort[["step", "n_stays"]].to_dict("records"),
           "wall_s": wall, "cpu_s": cpu, "peak_rss_mb": sampler.peak / 2**20,
           "temp_peak_mb": sampler.temp_peak / 2**20,
           "load_start": load0[0], "load_mean": sum(sampler.loads) / max(len(sampler.loads), 1),
           "load_max": max(sampler.loads, default=load0[0]),
           "cpu_count": os.cpu_count(), "ram_gb": psutil.virtual_memory().total / 2**30,
           "stages": records}
    if a.check_scale is not None:
        out["built_in"] = check_built_in(res, a.check_scale, a.check_seed, shape)
    a.out.write_text(json.dumps(out, indent=1, default=str) + "\n")
    if "built_in" in out:
        print(f"built-in cohort and HR reproduced: {out['built_in']}")
    print(f"cohort {out['cohort']}; wall {wall:.1f} s, cpu {cpu:.1f} s, peak "
          f"{out['peak_rss_mb']:.0f} MB, load {out['load_mean']:.2f}")
    top = {}
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
