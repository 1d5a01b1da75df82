"""Rule twin_shard_adaptive: simulate one shard batch by batch, stopping decided hypotheses."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify import bounds  # noqa: E402
from twinfalsify.design import ActionBins, StateBins  # noqa: E402
from twinfalsify.io import log, read_json, read_parquet, run_rule, write_json, write_parquet  # noqa: E402
from twinfalsify.runs.adaptive import budget_warning, run_adaptive_shard  # noqa: E402
from twinfalsify.runs.command import watch_code  # noqa: E402
from twinfalsify.runs.plan import TwinPlan, x0_frame  # noqa: E402
from twinfalsify.runs.registry import (  # noqa: E402
    LIBRARY_ROOT,
    make_twin,
    with_execution_keys,
)


class _Log:
    """Progress lines into the rule's log."""

    def write(self, text):
        if text.strip():
            log.info("%s", text.rstrip())

    def flush(self):
        pass


def main(sm):
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    hyps, obs = bounds.read_observational_side(
        sm.input.hypotheses, sm.input.counts, sm.input.follow
    )
    runs_cfg, testing = sm.params.runs, sm.params.testing
    spec = sm.params.spec
    spec = with_execution_keys(spec, sm.config["twins"][sm.wildcards.twin])
    twin = make_twin(sm.wildcards.twin, spec, sm.input.context)  # a served twin needs the file
    x0 = x0_frame(read_parquet(sm.input.d, "D"), plan.x0_stay_ids)
    # files the twin writes that its fingerprint reads: recorded (runs.command.watch_code)
    written = (Path(sm.output.runs).parents[2] / "code_written"
               / f"adaptive_shard_{sm.wildcards.shard}.json")
    with watch_code(spec, LIBRARY_ROOT, written):
        rows, decisions, summary = _run(sm, twin, plan, x0, hyps, obs, runs_cfg, testing)
    log.info("shard %s: %s", sm.wildcards.shard, summary)
    warning = budget_warning(summary)
    if warning:
        log.warning("WARNING: %s", warning)
    write_parquet(rows, sm.output.runs)
    write_parquet(decisions, sm.output.decisions)
    write_json(summary, sm.output.summary)


def _run(sm, twin, plan, x0, hyps, obs, runs_cfg, testing):
    return run_adaptive_shard(
        twin,
        plan,
        int(sm.wildcards.shard),
        x0,
        ActionBins.from_json(read_json(sm.input.actions)),
        hyps,
        obs,
        StateBins.from_json(read_json(sm.input.bins)),
        batch_size=int(runs_cfg["batch_size"]),
        alpha=float(testing["alpha"]),
        seed=int(sm.params.seed),
        correction=str(testing["correction"]),
        curtail=float(runs_cfg["curtail"]),
        combine=str(runs_cfg["combine"]),
        failed_runs=str(testing["failed_runs"]),
        log=_Log(),
    )


run_rule(snakemake, main)  # noqa: F821
