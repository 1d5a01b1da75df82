"""Rule twin_runs: merge shards; check every planned (node, X_0) is there exactly once."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import pandas as pd  # noqa: E402

from twinfalsify.io import log, read_json, read_parquet, run_rule, write_json, write_parquet  # noqa: E402
from twinfalsify.runs.plan import (  # noqa: E402
    TwinPlan,
    failing_patients,
    restart_warning,
    status_summary,
    twin_hellos,
    worker_summary,
)
from twinfalsify.schema import ContractError  # noqa: E402


def main(sm):
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    shards = [read_parquet(p, "twin shard") for p in sm.input.shards]
    hellos = twin_hellos([s.attrs.get("twin_hello") for s in shards])
    workers = worker_summary([s.attrs.get("twin_workers") for s in shards])
    runs = pd.concat(shards, ignore_index=True)
    expected = len(plan.nodes) * len(plan.x0_stay_ids)
    dup = runs.duplicated(["node", "init_stay_id"])
    if dup.any() or len(runs) != expected:
        raise ContractError(
            f"twin {sm.wildcards.twin}: shards hold {len(runs)} rows "
            f"({int(dup.sum())} duplicated), "
            f"plan needs {expected} = {len(plan.nodes)} nodes x {len(plan.x0_stay_ids)} X_0"
        )
    runs = runs.sort_values(["node", "init_stay_id"], kind="stable").reset_index(drop=True)
    summary = {
        "rows": len(runs),
        "by_hour_and_status": status_summary(runs),
        "twin_hours": plan.hours(),
        **hellos,
        **({"workers": workers} if workers else {}),
    }
    warnings = [w for w in (failing_patients(runs, sm.wildcards.twin),
                            restart_warning(sm.wildcards.twin, None, workers.get("total")))
                if w]
    if warnings:
        summary["warnings"] = warnings
    for warning in warnings:  # on stderr too: the study's own output, not only its log
        log.warning("%s", warning)
        print(f"WARNING: {warning}", file=sys.stderr, flush=True)
    log.info("%s", summary)
    # the merged runs keep their shards' worker restarts: the study summary shows them
    runs.attrs = {"twin_workers": workers} if workers else {}
    write_parquet(runs, sm.output.runs)
    write_json(summary, sm.output.summary)


run_rule(snakemake, main)  # noqa: F821
