"""Rule observational_side: n, followers and their outcomes for every hypothesis on D."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from twinfalsify import bounds, design  # noqa: E402
from twinfalsify.io import log, read_json, read_parquet, run_rule, write_parquet  # noqa: E402
from twinfalsify.schema import FEATURES, to_array  # noqa: E402


def main(sm):
    d = read_parquet(sm.input.d, "D")
    hyps = read_parquet(sm.input.hypotheses, "hypotheses")
    actions = design.ActionBins.from_json(read_json(sm.input.actions))
    states = design.StateBins.from_json(read_json(sm.input.bins))
    obs = bounds.observational_side(
        hyps, to_array(d, FEATURES), design.action_codes(d, actions), states,
        order_seed=int(sm.params.seed),
    )
    counts = pd.DataFrame({"hyp_id": hyps["hyp_id"], "n": obs.n, "n_follow": obs.follow.sizes})
    follow = pd.DataFrame(
        {
            "hyp_id": hyps["hyp_id"].to_numpy()[obs.follow.group_ids()],
            "value": obs.follow.values,
            "pos": obs.follow_pos.values.astype("int64"),  # betting's content-keyed order
        }
    )
    log.info(
        "%d hypotheses; median n %.0f; %d follower outcomes",
        len(hyps),
        np.median(obs.n),
        len(follow),
    )
    write_parquet(counts, sm.output.counts)
    write_parquet(follow, sm.output.follow)


run_rule(snakemake, main)  # noqa: F821
