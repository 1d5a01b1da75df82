"""Rule figure_sample_sizes: n and nhat of every parameter set, one row per outcome."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.figures import sample_size_strips, save_all  # noqa: E402
from twinfalsify.io import read_parquet, run_rule  # noqa: E402


def main(sm):
    fig = sample_size_strips(read_parquet(sm.input[0], "results"), twin=sm.wildcards.twin)
    save_all(fig, sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
