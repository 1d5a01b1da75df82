"""Rule table_action_space: the 5 x 5 action grid with bin edges and frequencies (Table 4)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import pandas as pd  # noqa: E402

from twinfalsify.io import run_rule, write_csv, write_text  # noqa: E402
from twinfalsify.tables import action_space_grid, grid_latex  # noqa: E402


def main(sm):
    grid = action_space_grid(pd.read_csv(sm.input[0]))
    write_csv(grid, sm.output.csv)
    caption = (
        "Action space: IV-fluid bins (rows) by vasopressor bins (columns), bin 0 = no dose, "
        "bins 1-4 = quartiles of non-zero D0 doses; cells: share of test-set hours (count)."
    )
    write_text(grid_latex(grid, caption), sm.output.tex)


run_rule(snakemake, main)  # noqa: F821
