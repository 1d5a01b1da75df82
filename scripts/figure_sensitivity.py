"""Rule figure_sensitivity: rejections as [y_lo, y_up] is widened by Delta (per kind)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import time  # noqa: E402

import pandas as pd  # noqa: E402

from twinfalsify.falsify import make_methods  # noqa: E402
from twinfalsify.figures import save_all, sensitivity_lines  # noqa: E402
from twinfalsify.io import log, run_rule, write_csv  # noqa: E402
from twinfalsify.summary import load_study_twin  # noqa: E402


def main(sm):
    from twinfalsify.inference.sensitivity import sensitivity_sweep

    st = load_study_twin(dict(sm.input.items()))
    testing = sm.params.testing
    opts = sm.params.figures.get("sensitivity") or {}
    deltas = [float(d) for d in opts.get("deltas", [0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2])]
    methods = make_methods(testing["methods"], int(sm.params.seed))
    parts = []
    alpha = float(testing.get("alpha", 0.05))
    correction = testing.get("correction", "holm")
    families = st.hyps.groupby("kind").indices  # two families, corrected apart as in tests
    log.info("sensitivity sweep: %d Delta values x %d methods (%s) x %d families (%s)",
             len(deltas), len(methods), ", ".join(methods), len(families),
             ", ".join(f"{k}: {len(i)} parameter sets" for k, i in families.items()))  # fmt: skip
    t_start = time.perf_counter()
    for kind, idx in families.items():
        samples, group = st.samples.take(idx), st.hyps["outcome"].to_numpy()[idx]
        for j, delta in enumerate(deltas, 1):  # one Delta at a time: progress in the log
            t0 = time.perf_counter()
            sweep = sensitivity_sweep(samples, [delta], methods, alpha=alpha,
                                      correction=correction, group=group)  # fmt: skip
            parts.append(sweep.assign(kind=kind))
            log.info("%s: Delta = %g (%d/%d): %d rejections in %.1f s", kind, delta, j,
                     len(deltas), int(sweep["n_rejected"].sum()), time.perf_counter() - t0)
    log.info("sensitivity sweep done in %.1f s", time.perf_counter() - t_start)
    table = pd.concat(parts, ignore_index=True)
    write_csv(table, sm.output.csv)
    save_all(sensitivity_lines(table, twin=sm.wildcards.twin), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
