"""Rule rejections_table: paper's Table 1 layout from the results table."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import read_parquet, run_rule, write_csv  # noqa: E402
from twinfalsify.tables import rejections_table  # noqa: E402


def main(sm):
    write_csv(rejections_table(read_parquet(sm.input[0], "results")), sm.output[0])


run_rule(snakemake, main)  # noqa: F821
