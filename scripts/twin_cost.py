"""Rule twin_cost: the engine-hours the plan asks of one twin, and its projected wall time
(from the hello's measured probe run: written under benchmarks/, as every measured time)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, read_json, run_rule, write_json  # noqa: E402
from twinfalsify.runs.hello import cost_line, projected_cost, with_timing  # noqa: E402
from twinfalsify.runs.plan import TwinPlan  # noqa: E402


def main(sm):
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    runs = len(plan.x0_stay_ids) * sum(len(shard) for shard in plan.shards)
    workers = int(sm.config["twins"][sm.wildcards.twin].get("workers", 1))
    hello = with_timing(read_json(sm.input.hello), read_json(sm.input.timing))
    cost = projected_cost(plan.hours(), runs, hello, workers)
    line = cost_line(sm.wildcards.twin, cost)
    log.info("%s", line)  # the log handler also writes it to the study's console
    write_json(cost, sm.output[0])


run_rule(snakemake, main)  # noqa: F821
