"""Rule table_rejections_tex: LaTeX-ready rejections per outcome (paper's Tables 1, 5-7)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import pandas as pd  # noqa: E402

from twinfalsify.io import run_rule, write_text  # noqa: E402
from twinfalsify.tables import rejections_latex  # noqa: E402


def main(sm):
    write_text(rejections_latex(pd.read_csv(sm.input[0])), sm.output[0])


run_rule(snakemake, main)  # noqa: F821
