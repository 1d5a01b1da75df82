"""Rule twin_shard: simulate one shard of the prefix tree with one twin."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.design import ActionBins  # noqa: E402
from twinfalsify.io import log, read_json, read_parquet, run_rule, write_parquet  # noqa: E402
from twinfalsify.runs.command import watch_code  # noqa: E402
from twinfalsify.runs.plan import TwinPlan, restart_warning, run_shard, x0_frame  # noqa: E402
from twinfalsify.runs.registry import (  # noqa: E402
    LIBRARY_ROOT,
    make_twin,
    with_execution_keys,
)


def main(sm):
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    spec = sm.params.spec
    spec = with_execution_keys(spec, sm.config["twins"][sm.wildcards.twin])
    if "workers" in spec:
        # Snakemake gave this job sm.threads cores (fewer than asked when --cores is
        # smaller): never run more twin processes than that.
        spec["workers"] = max(1, min(int(spec["workers"]), int(sm.threads)))
    twin = make_twin(sm.wildcards.twin, spec, sm.input.context)
    x0 = x0_frame(read_parquet(sm.input.d, "D"), plan.x0_stay_ids)
    shard = int(sm.wildcards.shard)
    # files the twin writes that its fingerprint reads: recorded (runs.command.watch_code)
    written = Path(sm.output[0]).parents[1] / "code_written" / f"shard_{shard}.json"
    with watch_code(spec, LIBRARY_ROOT, written):
        runs = run_shard(twin, plan, shard, x0, ActionBins.from_json(read_json(sm.input.actions)))
    log.info(
        "shard %s: %d node rows, status %s",
        sm.wildcards.shard,
        len(runs),
        runs["status"].value_counts().to_dict() if len(runs) else {},
    )
    hello = getattr(twin, "last_hello", None)
    if hello:  # what the twin said it is: recorded with its runs (run_summary.json)
        log.info("twin %s says it is %s", sm.wildcards.twin, hello)
        runs.attrs["twin_hello"] = dict(hello)
    workers = getattr(twin, "last_workers", None)
    if workers is not None:  # a served twin: its worker restarts, kept with its runs
        runs.attrs["twin_workers"] = dict(workers)
        if warning := restart_warning(sm.wildcards.twin, int(sm.wildcards.shard), workers):
            log.warning("WARNING: %s", warning)
    write_parquet(runs, sm.output[0])


run_rule(snakemake, main)  # noqa: F821
