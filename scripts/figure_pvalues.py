"""Rule figure_pvalues: boxen plots of -log10 p per outcome."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.figures import pvalue_boxen, save  # noqa: E402
from twinfalsify.io import read_parquet, run_rule  # noqa: E402


def main(sm):
    results = read_parquet(sm.input[0], "results")
    for path in (sm.output.png, sm.output.pdf):
        fig = pvalue_boxen(
            results,
            method=sm.params.method,
            title=f"twin {sm.wildcards.twin}: {sm.params.method} p-values",
        )
        save(fig, path)


run_rule(snakemake, main)  # noqa: F821
