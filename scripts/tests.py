"""Rule tests: both sides of every hypothesis, every method, multiple-testing correction."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, run_rule, write_parquet  # noqa: E402
from twinfalsify.summary import refusal_lines  # noqa: E402
from twinfalsify.twin_tests import load_twin_tests  # noqa: E402


def main(sm):
    tt = load_twin_tests(dict(sm.input.items()))  # failed runs keep their places
    results = tt.results(sm.params.testing, int(sm.params.seed))
    untestable = int(((tt.samples.n == 0) | (tt.samples.nhat == 0)).sum())
    if untestable:
        log.warning(
            "%d of %d parameter sets are untestable (n = 0 or nhat = 0: p = 1 by rule)",
            untestable, len(tt.hyps),
        )
    for line in refusal_lines(results):
        log.warning("%s", line)
    log.info("rejections: %s", results.groupby(["method", "kind"])["rejected"].sum().to_dict())
    write_parquet(results, sm.output.results)


run_rule(snakemake, main)  # noqa: F821
