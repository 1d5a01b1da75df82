"""Rule design: action bins, B-sets and hypotheses, all from D0."""

import json  # noqa: F401
import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify import design  # noqa: E402
from twinfalsify.figure_ids import figure_ids_error  # noqa: E402
from twinfalsify.io import log, read_parquet, run_rule, write_csv, write_json, write_parquet  # noqa: E402
from twinfalsify.schema import OUTCOMES, ContractError, validate_trajectories  # noqa: E402


def main(sm):
    cfg = sm.params.design
    d0 = validate_trajectories(read_parquet(sm.input.d0, "D0"), source=sm.input.d0)
    d = validate_trajectories(read_parquet(sm.input.d, "D"), source=sm.input.d)
    outcomes = tuple(cfg.get("outcomes", OUTCOMES))
    actions, states, hyps, report = design.design_on_d0(
        d0, outcomes=outcomes, quantiles=tuple(cfg["quantiles"]),
        min_support=int(cfg["min_support"]),
        kinds=tuple(cfg["kinds"]),
        horizon=cfg.get("horizon"), sequences=cfg.get("sequences"),
    )
    log.info("hypotheses: %s", hyps.groupby("kind").size().to_dict())
    problem = figure_ids_error(sm.config, hyps["hyp_id"])
    if problem:  # a figure would fail at the end of the study: say so now
        raise ContractError(problem)
    write_json(actions.to_json(), sm.output.actions)
    write_json(states.to_json(), sm.output.bins)
    write_parquet(hyps, sm.output.hypotheses)
    write_csv(report, sm.output.report)
    write_csv(design.action_space_table(d, actions), sm.output.action_space)


run_rule(snakemake, main)  # noqa: F821
