"""The mimic3 source as the trajectories rule uses it: extract, write the cohort report."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.io import write_csv


def extract_for_study(cfg: dict[str, Any], out_dir: Path) -> pd.DataFrame:
    """Extract the cohort from ``cfg['path']`` (or $TWINFALSIFY_MIMIC3_DIR); write
    cohort/consort.csv and cohort/missingness.csv next to the trajectories."""
    from twinfalsify.sources.mimic3 import extract_mimic3, resolve_mimic3_dir

    folder = resolve_mimic3_dir(cfg.get("path"))
    cohort = extract_mimic3(folder, threads=int(cfg.get("threads", 2)))
    write_csv(cohort.consort, out_dir / "cohort" / "consort.csv")
    write_csv(cohort.missingness, out_dir / "cohort" / "missingness.csv")
    return cohort.trajectories
