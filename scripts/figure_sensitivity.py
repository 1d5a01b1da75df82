"""Rule figure_sensitivity: rejections as [y_lo, y_up] is widened by Delta (per kind)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import json  # noqa: E402

import pandas as pd  # noqa: E402

from twinfalsify.falsify import make_methods  # noqa: E402
from twinfalsify.figures import save_all, sensitivity_lines  # noqa: E402
from twinfalsify.io import run_rule, write_csv  # noqa: E402
from twinfalsify.summary import load_study_twin  # noqa: E402


def main(sm):
    from twinfalsify.inference.sensitivity import sensitivity_sweep

    st = load_study_twin(dict(sm.input.items()))
    testing = json.loads(sm.params.testing)
    opts = json.loads(sm.params.figures).get("sensitivity") or {}
    deltas = [float(d) for d in opts.get("deltas", [0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2])]
    methods = make_methods(testing["methods"], int(sm.params.seed))
    parts = []
    for kind, idx in st.hyps.groupby("kind").indices.items():  # two families, as in tests
        sweep = sensitivity_sweep(
            st.samples.take(idx), deltas, methods, alpha=float(testing.get("alpha", 0.05)),
            correction=testing.get("correction", "holm"),
            group=st.hyps["outcome"].to_numpy()[idx],
        )  # fmt: skip
        parts.append(sweep.assign(kind=kind))
    table = pd.concat(parts, ignore_index=True)
    write_csv(table, sm.output.csv)
    save_all(sensitivity_lines(table), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
