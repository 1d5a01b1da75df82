"""Rule twin_plan: X_0 permutation, prefix tree of action sequences, shards."""

import json  # noqa: F401
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, read_parquet, run_rule, write_json  # noqa: E402
from twinfalsify.runs.plan import plan_twin_runs, x0_frame  # noqa: E402
from twinfalsify.schema import FEATURES, STAY_ID  # noqa: E402


def main(sm):
    d = read_parquet(sm.input.d, "D")
    hyps = read_parquet(sm.input.hypotheses, "hypotheses")
    runs = sm.params.runs
    ids = d[STAY_ID].unique()
    plan = plan_twin_runs(
        hyps,
        ids,
        runs["runs_per_sequence"],
        int(runs["n_shards"]),
        int(sm.params.seed),
        x0=x0_frame(d, [int(s) for s in ids])[list(FEATURES)].to_numpy(float),
        x0_stays=runs.get("x0_stays"),
    )
    log.info(
        "%d X_0 per sequence, %d nodes, twin-hours %s",
        len(plan.x0_stay_ids),
        len(plan.nodes),
        plan.hours(),
    )
    write_json(plan.to_json(), sm.output.plan)
    write_json(
        # relative to the context's folder: the study folder may be moved or copied
        {
            "source": sm.params.source,
            "d0": os.path.relpath(sm.input.d0, Path(sm.output.context).parent),
        },
        sm.output.context,
    )


run_rule(snakemake, main)  # noqa: F821
