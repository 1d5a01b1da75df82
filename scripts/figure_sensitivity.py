"""Rule figure_sensitivity: rejections as [y_lo, y_up] is widened by Delta (per kind)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.figures import save_all, sensitivity_lines  # noqa: E402
from twinfalsify.io import log, read_parquet, run_rule, write_csv  # noqa: E402
from twinfalsify.twin_tests import load_twin_tests, sensitivity  # noqa: E402


def main(sm):
    tt = load_twin_tests(dict(sm.input.items()))  # the tests rule's own inputs
    deltas = [float(d) for d in sm.params.figures["sensitivity"]["deltas"]]
    results = read_parquet(sm.input.results, "results")  # the main analysis: Delta = 0
    table = sensitivity(tt, sm.params.testing, int(sm.params.seed), deltas, progress=log.info,
                        results=results)
    write_csv(table, sm.output.csv)
    save_all(sensitivity_lines(table, twin=sm.wildcards.twin), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
