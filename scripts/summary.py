"""Rule summary: cohort, split, hypotheses, twin runs, clamps, rejections, untestable."""

import json
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.design import ActionBins  # noqa: E402
from twinfalsify.io import read_json, read_parquet, run_rule, write_text  # noqa: E402
from twinfalsify.summary import (  # noqa: E402
    clipped_shares,
    load_study_twin,
    study_summary,
    summary_html,
    summary_markdown,
    summary_warnings,
    tie_table,
)

SHARED = ("d0", "d", "actions", "bins", "hypotheses", "counts", "follow", "plan")


def _dataset(path: Path) -> dict | None:
    """The source's dataset record (meds source: written by the trajectories rule)."""
    return json.loads(path.read_text()) if path.is_file() else None


def main(sm):
    twins = {}
    for name, runs, res in zip(sm.params.twins, sm.input.runs, sm.input.results, strict=True):
        # the samples the tests saw, to show how many twin outputs sit at the bounds
        st = load_study_twin({**{k: getattr(sm.input, k) for k in SHARED}, "runs": runs,
                              "results": res})
        twins[name] = {"runs": read_parquet(runs, "twin runs"),
                       "results": read_parquet(res, "results"),
                       "clipped": clipped_shares(st.hyps, st.samples)}
    tables = study_summary(
        sm.params.study,
        read_parquet(sm.input.d0, "D0"),
        read_parquet(sm.input.d, "D"),
        read_parquet(sm.input.hypotheses, "hypotheses"),
        twins,
        ties=tie_table(read_parquet(sm.input.d, "D"),
                       ActionBins.from_json(read_json(sm.input.actions)), int(sm.params.seed)),
        data=_dataset(Path(sm.input.d0).parent / "cohort" / "dataset.json"),
    )
    write_text(summary_markdown(sm.params.study, tables), sm.output.md)
    write_text(summary_html(sm.params.study, tables), sm.output.html)
    # also printed last by the Snakefile's onsuccess, after Snakemake's closing lines
    for warning in summary_warnings(tables):
        logging.getLogger("summary").warning("WARNING: %s", warning)


run_rule(snakemake, main)  # noqa: F821
