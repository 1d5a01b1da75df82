"""Rule figure_pvalues: boxen plots of -log10 p per outcome, one row per test method."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.figures import pvalue_boxen_methods, save_all  # noqa: E402
from twinfalsify.io import read_parquet, run_rule  # noqa: E402


def main(sm):
    results = read_parquet(sm.input[0], "results")
    title = f"twin {sm.wildcards.twin}: p-values of the causal hypotheses"
    save_all(pvalue_boxen_methods(results, title=title), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
