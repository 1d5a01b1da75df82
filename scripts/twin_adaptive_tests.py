"""Rule tests_adaptive: merge adaptive shards, account for every run, Holm/BY on the
anytime-valid p-values at the stopping times."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import pandas as pd  # noqa: E402

from twinfalsify import bounds  # noqa: E402
from twinfalsify.design import StateBins  # noqa: E402
from twinfalsify.io import log, read_json, read_parquet, run_rule, write_json, write_parquet  # noqa: E402
from twinfalsify.runs.adaptive import adaptive_results, load_simulated  # noqa: E402
from twinfalsify.runs.plan import TwinPlan, status_summary, x0_frame  # noqa: E402
from twinfalsify.schema import ContractError  # noqa: E402


def main(sm):
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    hyps, obs = bounds.read_observational_side(
        sm.input.hypotheses, sm.input.counts, sm.input.follow
    )
    rows = pd.concat([read_parquet(p, "adaptive twin shard") for p in sm.input.runs],
                     ignore_index=True)
    decisions = pd.concat([read_parquet(p, "adaptive decisions") for p in sm.input.decisions],
                          ignore_index=True)
    summaries = [read_json(p) for p in sm.input.summaries]
    simulated = sum(s["node_rows"] for s in summaries)
    if simulated != len(rows):
        raise ContractError(
            f"twin {sm.wildcards.twin}: shard summaries report {simulated} simulated node rows, "
            f"shard tables hold {len(rows)}"
        )
    x0 = x0_frame(read_parquet(sm.input.d, "D"), plan.x0_stay_ids)
    nodes = load_simulated(rows, plan, x0)
    testing = sm.params.testing
    results = adaptive_results(
        hyps, obs, nodes, StateBins.from_json(read_json(sm.input.bins)), decisions,
        alpha=float(testing["alpha"]), correction=testing["correction"],
        failed_runs=str(testing["failed_runs"]),
    )
    hours_a = sum(s["twin_hours_adaptive"] for s in summaries)
    hours_f = sum(s["twin_hours_fixed"] for s in summaries)
    summary = {
        "twin_hours_adaptive": hours_a,
        "twin_hours_fixed": hours_f,
        # hours asked of the twin: what a twin without prefix reuse would simulate
        "twin_hours_requested": sum(s["twin_hours_requested"] for s in summaries),
        "ratio": hours_a / max(hours_f, 1),
        # hours of runs that had left every B-set needing them were not kept (in-process
        # twins); protocol twins simulate whole paths (docs/explanation/sequential.md)
        "depth_truncation": all(s.get("depth_truncation", False) for s in summaries),
        "node_rows_simulated": len(rows),
        "by_hour_and_status": status_summary(rows) if len(rows) else {},
        "decisions": results.groupby(["side", "decision"]).size().unstack(fill_value=0)
        .to_dict(),
        "rejected": results.groupby("kind")["rejected"].sum().to_dict(),
    }
    log.info("%s", summary)
    write_parquet(results, sm.output.results)
    write_json(summary, sm.output.summary)


run_rule(snakemake, main)  # noqa: F821
