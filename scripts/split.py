"""Rule split: held-out design set D0 and test set D."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, read_parquet, run_rule, write_parquet  # noqa: E402
from twinfalsify.schema import STAY_ID  # noqa: E402
from twinfalsify.split import split_stays  # noqa: E402


def main(sm):
    traj = read_parquet(sm.input[0], "trajectories")
    d0, d = split_stays(
        traj, float(sm.params.d0_fraction), int(sm.params.seed), sm.params.split_by
    )
    log.info("D0: %d stays, D: %d stays", d0[STAY_ID].nunique(), d[STAY_ID].nunique())
    write_parquet(d0, sm.output.d0)
    write_parquet(d, sm.output.d)


run_rule(snakemake, main)  # noqa: F821
