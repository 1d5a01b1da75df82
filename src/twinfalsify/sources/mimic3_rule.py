"""The mimic3 source as the trajectories rule uses it: extract, write the cohort report."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.io import log, write_csv


def extract_for_study(cfg: dict[str, Any], out_dir: Path) -> pd.DataFrame:
    """Extract the cohort from ``cfg['path']`` (or $TWINFALSIFY_MIMIC3_DIR) with the time
    anchor ``cfg['anchor']`` (``first_vitals`` by default, see docs/mimic3.md) and
    ``cfg['anchor_window_h']``; write cohort/consort.csv, cohort/missingness.csv and
    cohort/anchors.csv next to the trajectories."""
    from twinfalsify.sources.mimic3 import extract_mimic3, resolve_mimic3_dir
    from twinfalsify.sources.mimic3.cohort import ANCHOR_WINDOW_H

    folder = resolve_mimic3_dir(cfg.get("path"))
    anchor = cfg.get("anchor") or "first_vitals"
    window = int(cfg.get("anchor_window_h") or ANCHOR_WINDOW_H)
    cohort = extract_mimic3(folder, threads=int(cfg.get("threads", 2)), anchor=anchor,
                            anchor_window_h=window)
    c = cohort.consort
    log.info("MIMIC-III cohort from %s, anchor %s: %s", folder, anchor,
             ", ".join(f"{s} {n}" for s, n in zip(c["step"], c["n_stays"], strict=True)))
    write_csv(cohort.consort, out_dir / "cohort" / "consort.csv")
    write_csv(cohort.missingness, out_dir / "cohort" / "missingness.csv")
    write_csv(cohort.anchors, out_dir / "cohort" / "anchors.csv")
    return cohort.trajectories
