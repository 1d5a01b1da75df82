"""The mimic3 source as the trajectories rule uses it: extract, write the cohort report."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.io import log, write_csv, write_text
from twinfalsify.schema import ContractError


def data_params(cfg: dict[str, Any] | None) -> str:
    """The ``trajectories`` rule's data parameter for a mimic3 source: the resolved MIMIC-III
    folder (config path or $TWINFALSIFY_MIMIC3_DIR) and a fingerprint of the names, sizes
    and mtimes of the files the extraction reads (``sources.checksums.read_fingerprint``),
    as JSON. Another folder, or a changed table, changes it, and Snakemake reruns the
    extraction; another file in the folder does not. An unresolvable folder (or two files
    for one table) gives a fixed string: the rule itself then fails with the one-line error."""
    from twinfalsify.sources.checksums import read_fingerprint
    from twinfalsify.sources.mimic3.tables import resolve_mimic3_dir

    try:
        folder = resolve_mimic3_dir((cfg or {}).get("path"))
        return json.dumps(read_fingerprint(folder), sort_keys=True)
    except ContractError:
        return "unresolved"


def extract_for_study(cfg: dict[str, Any], out_dir: Path) -> pd.DataFrame:
    """Extract the cohort from ``cfg['path']`` (or $TWINFALSIFY_MIMIC3_DIR) with the time
    anchor ``cfg['anchor']`` (``first_vitals`` by default, see docs/how-to/mimic3.md),
    ``cfg['anchor_window_h']`` and the switches / ``cohort_variant`` preset of
    ``options.options_from_config``, DuckDB's ``memory_limit`` and ``temp_directory``; write
    cohort/consort.csv, cohort/missingness.csv,
    cohort/anchors.csv, cohort/stays.csv (one audit row per ICU stay) and
    cohort/options.json next to the trajectories."""
    from twinfalsify.sources.checksums import verify
    from twinfalsify.sources.mimic3 import extract_mimic3, resolve_mimic3_dir
    from twinfalsify.sources.mimic3.cohort import ANCHOR_WINDOW_H
    from twinfalsify.sources.mimic3.options import options_from_config
    from twinfalsify.sources.mimic3.tables import data_fingerprint

    folder = resolve_mimic3_dir(cfg.get("path"))
    # two files for one table: an error naming both; files that differ from PhysioNet's
    # published checksums: one warning each (hashed once per data fingerprint)
    for warning in verify(folder, cfg.get("checksums"), out_dir / "cohort" / "checksums.json"):
        log.warning("%s", warning)
        print(f"WARNING: {warning}", file=sys.stderr, flush=True)
    anchor = cfg.get("anchor") or "first_vitals"
    window = int(cfg.get("anchor_window_h") or ANCHOR_WINDOW_H)
    opts = options_from_config(cfg)
    cohort = extract_mimic3(folder, threads=int(cfg.get("threads", 2)), anchor=anchor,
                            anchor_window_h=window, options=opts,
                            memory_limit=cfg.get("memory_limit"),
                            temp_directory=cfg.get("temp_directory"))
    c = cohort.consort
    log.info("MIMIC-III cohort from %s, anchor %s, options %s: %s", folder, anchor,
             opts.as_dict(), ", ".join(f"{s} {n}" for s, n in
                                       zip(c["step"], c["n_stays"], strict=True)))
    write_csv(cohort.consort, out_dir / "cohort" / "consort.csv")
    write_csv(cohort.missingness, out_dir / "cohort" / "missingness.csv")
    write_csv(cohort.anchors, out_dir / "cohort" / "anchors.csv")
    write_csv(cohort.stays, out_dir / "cohort" / "stays.csv")
    meta = {"data": data_fingerprint(folder), "anchor": anchor, "anchor_window_h": window,
            "cohort_variant": cfg.get("cohort_variant") or "project", "options": opts.as_dict()}
    write_text(json.dumps(meta, indent=1) + "\n", out_dir / "cohort" / "options.json")
    return cohort.trajectories
