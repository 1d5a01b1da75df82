"""Rule figure_confounding: observed outcome under a treatment vs everyone treated (synthetic)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install


from twinfalsify.design import N_DOSE_BINS, ActionBins  # noqa: E402
from twinfalsify.figures import confounding, save_all  # noqa: E402
from twinfalsify.io import read_json, read_parquet, run_rule  # noqa: E402
from twinfalsify.schema import ContractError  # noqa: E402
from twinfalsify.summary import confounding_frame  # noqa: E402


def main(sm):
    from twinfalsify.sources.synthetic import SyntheticWorld

    source = sm.params.source
    if source["kind"] != "synthetic":
        raise ContractError("figure_confounding: needs source.kind synthetic (the truth)")
    opts = sm.params.figures.get("confounding") or {}
    outcome = opts.get("outcome", "MeanBP")
    world = SyntheticWorld.from_config(source.get("synthetic"))
    actions = ActionBins.from_json(read_json(sm.input.actions))
    frame = confounding_frame(read_parquet(sm.input.d, "D"), world, actions, outcome,
                              seed=int(sm.params.seed))  # fmt: skip
    labels = {a: f"({a // N_DOSE_BINS}, {a % N_DOSE_BINS})" for a in range(N_DOSE_BINS**2)}
    fig = confounding(frame, outcome, show_action=opts.get("action"), labels=labels)
    save_all(fig, sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
