"""Rule trajectories: the observational cohort from the configured source."""

import json  # noqa: F401
import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, run_rule, write_parquet  # noqa: E402
from twinfalsify.schema import STAY_ID, validate_trajectories  # noqa: E402


def main(sm):
    source = sm.params.source
    if source["kind"] == "synthetic":
        from twinfalsify.sources.synthetic import generate

        traj = generate(source.get("synthetic"), seed=int(sm.params.seed))
    elif source["kind"] == "table":
        from twinfalsify.sources.table import check_units, read_table

        traj = read_table(source["table"]["path"])
        # before any twin runs: a table in another unit would be blamed on the twin
        check_units(traj, source["table"]["path"])
    elif source["kind"] == "meds":
        from twinfalsify.sources.meds.study import extract_for_study as extract_meds

        traj = extract_meds(source["meds"], Path(sm.output[0]).parent)
    else:
        from twinfalsify.sources.mimic_rule import extract_for_study

        kind = source["kind"]
        traj = extract_for_study(source.get(kind) or {}, Path(sm.output[0]).parent, kind)
    traj = validate_trajectories(traj, source=f"source {source['kind']}")
    log.info("%d stays, %d rows", traj[STAY_ID].nunique(), len(traj))
    write_parquet(traj, sm.output[0])


run_rule(snakemake, main)  # noqa: F821
