"""Rule calibration_chunk: run this job's replicates of the calibration harness."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify import calibration  # noqa: E402
from twinfalsify.io import log, run_rule, write_parquet  # noqa: E402


def main(sm):
    cfg = calibration.load_config(sm.input.config)
    chunk = int(sm.wildcards.chunk)
    reps = calibration.chunk_replicates(cfg, chunk)
    log.info("chunk %d of %d: replicates %s", chunk, cfg.chunks, reps)
    out = calibration.run_replicates(cfg, reps, log=log)
    for name in ("tests", "coverage", "widths", "timing", "adaptive"):
        write_parquet(out[name], getattr(sm.output, name))


run_rule(snakemake, main)  # noqa: F821
