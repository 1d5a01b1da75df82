"""The mimic3 and mimic4 sources as the trajectories rule uses them: extract, write the
cohort report. The two differ only in their table layout (``sources.mimic3.tables.Layout``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.io import log, write_csv, write_text
from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3.tables import MIMIC3, Layout


def layout_of(kind: str) -> Layout:
    """The table layout of source kind ``mimic3`` or ``mimic4``."""
    if kind == "mimic4":
        from twinfalsify.sources.mimic4 import MIMIC4

        return MIMIC4
    if kind == "mimic3":
        return MIMIC3
    raise ContractError(f"source kind {kind!r} is not a MIMIC source (mimic3, mimic4)")


def data_params(cfg: dict[str, Any] | None, kind: str = "mimic3") -> str:
    """The ``trajectories`` rule's data parameter for a MIMIC source: the resolved folder
    (config path or $TWINFALSIFY_MIMIC3_DIR / $TWINFALSIFY_MIMIC4_DIR) and a fingerprint of
    the names, sizes and mtimes of the files the extraction reads
    (``sources.checksums.read_fingerprint``), as JSON. Another folder, or a changed table,
    changes it, and Snakemake reruns the extraction; another file in the folder does not. An
    unresolvable folder (or two files for one table) gives a fixed string: the rule itself
    then fails with the one-line error."""
    from twinfalsify.sources.checksums import read_fingerprint
    from twinfalsify.sources.mimic3.tables import resolve_dir

    layout = layout_of(kind)
    try:
        folder = resolve_dir((cfg or {}).get("path"), layout)
        return json.dumps(read_fingerprint(folder, layout), sort_keys=True)
    except ContractError:
        return "unresolved"


def extract_for_study(cfg: dict[str, Any], out_dir: Path, kind: str = "mimic3") -> pd.DataFrame:
    """Extract the cohort from ``cfg['path']`` (or the layout's environment variable) with
    the time anchor ``cfg['anchor']`` (``first_vitals`` by default, see
    docs/how-to/mimic3.md), ``cfg['anchor_window_h']`` and the switches / ``cohort_variant``
    preset of ``options.options_from_config``, DuckDB's ``memory_limit`` and
    ``temp_directory``; write cohort/consort.csv, cohort/missingness.csv,
    cohort/anchors.csv, cohort/stays.csv (one audit row per ICU stay) and
    cohort/options.json next to the trajectories."""
    from twinfalsify.sources.checksums import read_fingerprint, verify
    from twinfalsify.sources.mimic3 import extract_mimic3
    from twinfalsify.sources.mimic3.cohort import ANCHOR_WINDOW_H
    from twinfalsify.sources.mimic3.options import options_from_config
    from twinfalsify.sources.mimic3.tables import resolve_dir

    layout = layout_of(kind)
    folder = resolve_dir(cfg.get("path"), layout)
    # two files for one table: an error naming both; files that differ from PhysioNet's
    # published checksums: one warning each (hashed once per data fingerprint)
    for warning in verify(folder, cfg.get("checksums"), out_dir / "cohort" / "checksums.json",
                          layout=layout):
        log.warning("%s", warning)
        print(f"WARNING: {warning}", file=sys.stderr, flush=True)
    anchor = cfg.get("anchor") or "first_vitals"
    window = int(cfg.get("anchor_window_h") or ANCHOR_WINDOW_H)
    opts = options_from_config(cfg)
    cohort = extract_mimic3(folder, threads=int(cfg.get("threads", 2)), anchor=anchor,
                            anchor_window_h=window, options=opts,
                            memory_limit=cfg.get("memory_limit"),
                            temp_directory=cfg.get("temp_directory"), layout=layout)
    c = cohort.consort
    log.info("%s cohort from %s, anchor %s, options %s: %s", layout.name, folder, anchor,
             opts.as_dict(), ", ".join(f"{s} {n}" for s, n in
                                       zip(c["step"], c["n_stays"], strict=True)))
    write_csv(cohort.consort, out_dir / "cohort" / "consort.csv")
    write_csv(cohort.missingness, out_dir / "cohort" / "missingness.csv")
    write_csv(cohort.anchors, out_dir / "cohort" / "anchors.csv")
    write_csv(cohort.stays, out_dir / "cohort" / "stays.csv")
    meta = {"release": layout.name, "data": read_fingerprint(folder, layout), "anchor": anchor,
            "anchor_window_h": window,
            "cohort_variant": cfg.get("cohort_variant") or "project", "options": opts.as_dict()}
    write_text(json.dumps(meta, indent=1) + "\n", out_dir / "cohort" / "options.json")
    return cohort.trajectories
