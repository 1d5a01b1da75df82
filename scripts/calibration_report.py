"""Rule calibration_report: merge the chunks into the table, figures and Markdown summary."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import pandas as pd  # noqa: E402

from twinfalsify import calibration as cal  # noqa: E402
from twinfalsify.io import log, read_parquet, run_rule, write_csv, write_parquet, write_text  # noqa: E402
from twinfalsify.schema import ContractError  # noqa: E402


def _merge(paths, what):
    frames = [read_parquet(p, what) for p in paths]
    frames = [f for f in frames if not f.empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def main(sm):
    cfg = cal.load_config(sm.input.config)
    tests = _merge(sm.input.tests, "calibration tests")
    cov = _merge(sm.input.coverage, "calibration coverage")
    wid = _merge(sm.input.widths, "calibration widths")
    timing = _merge(sm.input.timing, "calibration timing")
    adaptive = _merge(sm.input.adaptive, "calibration adaptive rows")
    if cfg.adaptive and adaptive["replicate"].nunique() != cfg.replicates:
        raise ContractError(
            f"{sm.input.config}: adaptive: true but the chunks hold adaptive rows for "
            f"{adaptive['replicate'].nunique() if not adaptive.empty else 0} of "
            f"{cfg.replicates} replicates"
        )
    n_rep = tests["replicate"].nunique()
    if n_rep != cfg.replicates:
        raise ContractError(
            f"{sm.input.config}: {cfg.replicates} replicates configured, chunks hold {n_rep}"
        )
    summary = cal.summarise(tests, cfg.alpha)
    dom = cal.dominance(summary)
    asum = cal.adaptive_summary(adaptive) if not adaptive.empty else pd.DataFrame()
    write_csv(cal.attach_hours(summary, asum), sm.output.table)
    write_csv(asum, sm.output.adaptive)
    write_csv(dom, sm.output.dominance)
    write_csv(cov, sm.output.coverage)
    write_csv(wid, sm.output.widths)
    write_parquet(tests, sm.output.replicates)
    cal.plot_power(summary, sm.output.power_png, sm.output.power_pdf)
    if cov.empty:
        raise ContractError(f"{sm.input.config}: no coverage checks ran (coverage_per_replicate)")
    cal.plot_coverage(cov, sm.output.coverage_png, sm.output.coverage_pdf)
    md = cal.markdown_summary(cfg, summary, dom, cov, wid, timing, adaptive)
    write_text(md, sm.output.summary)
    log.info("\n%s", md)


run_rule(snakemake, main)  # noqa: F821
