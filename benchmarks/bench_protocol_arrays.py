"""One served shard with batch answers in arrays against plain JSON answers, back to back.

    PYTHONPATH=src python benchmarks/bench_protocol_arrays.py results/paper-scale-4x \
        [--twin oracle] [--shard 0] [--rounds 2]

Runs ``run_shard`` on a finished study's plan, D and action bins with the builtin twin served
over the protocol (one worker), alternating: the client not asking for arrays (plain JSON
answers, one object per hour), then asking for them. Prints, per run, the wall time and the
CPU of the shard process and of its worker process (``getrusage``; the worker is reaped when
the shard ends), and checks that the two forms give the same ``runs`` table, bit for bit.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import resource
import time
from pathlib import Path

import pandas as pd

import twinfalsify.runs.worker as worker_mod
from twinfalsify.design import ActionBins
from twinfalsify.io import read_json, read_parquet
from twinfalsify.runs.plan import TwinPlan, run_shard, x0_frame
from twinfalsify.runs.registry import make_twin

ASKS = worker_mod.ARRAYS


def _cpu() -> tuple[float, float]:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


def one_shard(study: Path, twin: str, shard: int, arrays: bool) -> tuple[dict, pd.DataFrame]:
    # the client asks for arrays when the hello advertises this name (runs.worker)
    worker_mod.ARRAYS = ASKS if arrays else "not-asked"
    plan = TwinPlan.from_json(read_json(study / "twin_plan.json"))
    served = make_twin(twin, {"kind": twin, "protocol": True, "workers": 1, "timeout_s": 60},
                       study / "twin_context.json")
    x0 = x0_frame(read_parquet(study / "d.parquet", "D"), plan.x0_stay_ids)
    actions = ActionBins.from_json(read_json(study / "design" / "actions.json"))
    (s0, w0), t0 = _cpu(), time.perf_counter()
    with contextlib.redirect_stderr(io.StringIO()):  # the progress lines
        runs = run_shard(served, plan, shard, x0, actions)
    wall = time.perf_counter() - t0
    s1, w1 = _cpu()
    return {"answers": "arrays" if arrays else "plain", "rows": len(runs),
            "wall_s": round(wall, 1), "shard_cpu_s": round(s1 - s0, 1),
            "worker_cpu_s": round(w1 - w0, 1)}, runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("study", type=Path, help="a finished study's results folder")
    ap.add_argument("--twin", default="oracle", help="a builtin twin kind (oracle, biased)")
    ap.add_argument("--shard", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    tables = {}
    for _ in range(args.rounds):
        for arrays in (False, True):
            row, runs = one_shard(args.study, args.twin, args.shard, arrays)
            print(json.dumps(row), flush=True)
            tables.setdefault(arrays, runs)
    pd.testing.assert_frame_equal(tables[False], tables[True], check_exact=True)
    print("runs tables identical (every value, NaN where NaN)")


if __name__ == "__main__":
    main()
