"""Rule tests: both sides of every hypothesis, every method, multiple-testing correction."""

import json  # noqa: F401
import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify import bounds  # noqa: E402
from twinfalsify.design import StateBins  # noqa: E402
from twinfalsify.falsify import make_methods, run_tests  # noqa: E402
from twinfalsify.io import log, read_json, read_parquet, run_rule, write_parquet  # noqa: E402
from twinfalsify.runs.plan import TwinPlan, load_nodes, x0_frame  # noqa: E402


def main(sm):
    hyps, obs = bounds.read_observational_side(
        sm.input.hypotheses, sm.input.counts, sm.input.follow
    )
    plan = TwinPlan.from_json(read_json(sm.input.plan))
    states = StateBins.from_json(read_json(sm.input.bins))
    x0 = x0_frame(read_parquet(sm.input.d, "D"), plan.x0_stay_ids)
    nodes = load_nodes(read_parquet(sm.input.runs, "twin runs"), plan, x0)
    twin = bounds.twin_runs(hyps, nodes, states)  # failed runs keep their places
    n_failed = twin.n_failed
    samples = bounds.hypothesis_samples(hyps, obs, twin)
    cfg = sm.params.testing
    results = run_tests(
        hyps,
        samples,
        n_failed,
        make_methods(cfg["methods"], int(sm.params.seed)),
        alpha=float(cfg.get("alpha", 0.05)),
        correction=cfg.get("correction", "holm"),
        failed_runs=cfg.get("failed_runs", "conservative"),
    )
    untestable = int(((samples.n == 0) | (samples.nhat == 0)).sum())
    if untestable:
        log.warning(
            "%d of %d parameter sets are untestable (n = 0 or nhat = 0: p = 1 by rule)",
            untestable, len(hyps),
        )
    log.info("rejections: %s", results.groupby(["method", "kind"])["rejected"].sum().to_dict())
    write_parquet(results, sm.output.results)


run_rule(snakemake, main)  # noqa: F821
