"""MIMIC-IV source: the MIMIC-III sepsis-3 cohort code run on MIMIC-IV v2.2 / v3.x tables.

MIMIC-IV keeps its tables in module folders (``hosp/``, ``icu/``), lower-case, one ICU stay id
``stay_id``, and only the MetaVision ICU system, whose item ids MIMIC-III's MetaVision stays
use too. Nothing of the cohort is written twice: :data:`MIMIC4` maps each MIMIC-IV table onto
the MIMIC-III view the extraction's queries read (``sources.mimic3.tables.Layout``), and
:func:`extract_mimic4` is ``extract_mimic3`` on that layout. Every difference the schema
forces is listed in :data:`DIFFERENCES` (and in docs/how-to/mimic4.md).
"""

from __future__ import annotations

from pathlib import Path

from twinfalsify import schema
from twinfalsify.sources.mimic3.cohort import ANCHOR_WINDOW_H, Mimic3Cohort, extract_mimic3
from twinfalsify.sources.mimic3.options import Mimic3Options
from twinfalsify.sources.mimic3.tables import (
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    Layout,
    resolve_dir,
)

ENV_VAR = "TWINFALSIFY_MIMIC4_DIR"

# view (MIMIC-III table) -> MIMIC-IV file stems tried, relative to the MIMIC-IV folder
# (PhysioNet's download: <folder>/hosp/patients.csv.gz, <folder>/icu/icustays.csv.gz, ...;
# a flat folder of the same files also works). INPUTEVENTS_CV: none (no CareVue in MIMIC-IV).
FILES: dict[str, tuple[str, ...]] = {
    "PATIENTS": ("hosp/patients", "patients"),
    "ADMISSIONS": ("hosp/admissions", "admissions"),
    "ICUSTAYS": ("icu/icustays", "icustays"),
    "CHARTEVENTS": ("icu/chartevents", "chartevents"),
    "LABEVENTS": ("hosp/labevents", "labevents"),
    "PRESCRIPTIONS": ("hosp/prescriptions", "prescriptions"),
    "MICROBIOLOGYEVENTS": ("hosp/microbiologyevents", "microbiologyevents"),
    "INPUTEVENTS_MV": ("icu/inputevents", "inputevents"),
    "INPUTEVENTS_CV": (),
    "OUTPUTEVENTS": ("icu/outputevents", "outputevents"),
}

# view -> {MIMIC-III column: the MIMIC-IV expression giving it}; a column not named here is
# the MIMIC-IV column of the same name in lower case (DuckDB matches names without case).
RENAMED: dict[str, dict[str, str]] = {
    "PATIENTS": {"DOB": "CAST(NULL AS VARCHAR)", "ANCHOR_AGE": "anchor_age",
                 "ANCHOR_YEAR": "anchor_year"},
    "ICUSTAYS": {"ICUSTAY_ID": "stay_id", "DBSOURCE": "'metavision'"},
    "CHARTEVENTS": {"ICUSTAY_ID": "stay_id", "ERROR": "CAST(NULL AS VARCHAR)"},
    "PRESCRIPTIONS": {"ICUSTAY_ID": "CAST(NULL AS VARCHAR)", "STARTDATE": "starttime"},
    "MICROBIOLOGYEVENTS": {"TEST_NAME": "test_name"},
    "INPUTEVENTS_MV": {"ICUSTAY_ID": "stay_id"},
    "OUTPUTEVENTS": {"ICUSTAY_ID": "stay_id"},
}

# What MIMIC-IV's schema changes for the extraction (the cohort code is the same).
DIFFERENCES: tuple[tuple[str, str], ...] = (
    ("layout", "tables in hosp/ and icu/, lower-case file and column names; icustays.stay_id "
     "is MIMIC-III's ICUSTAY_ID"),
    ("CareVue", "no CareVue stays: no INPUTEVENTS_CV (an empty table), ICUSTAYS has no "
     "DBSOURCE (every stay is MetaVision), and the CareVue item ids never occur"),
    ("age", "patients has no DOB: age = anchor_age + year(INTIME) - anchor_year, known to the "
     "year (MIMIC-III: (INTIME - DOB) / 365.25 d, to the day); ages over 89 (anchor_age 91) "
     "are 91.4 as MIMIC-III's shifted ones"),
    ("antibiotic time", "prescriptions.starttime is a time of day (MIMIC-III STARTDATE: a "
     "date at 00:00), so an onset from an antibiotic can move within its day"),
    ("antibiotic stay", "prescriptions has no ICU stay id: every antibiotic is given a stay "
     "by the event_stay rule (MIMIC-III fills ICUSTAY_ID for about two thirds of them)"),
    ("chart errors", "chartevents has no ERROR column: no row is dropped as an error"),
)


def _view_columns(view: str) -> dict[str, str]:
    """MIMIC-III column -> the MIMIC-IV expression giving it, for every column the view has:
    the extraction's (REQUIRED_COLUMNS / OPTIONAL_COLUMNS), then the extra ones of RENAMED."""
    ren = RENAMED.get(view, {})
    cols = (*{**REQUIRED_COLUMNS, **OPTIONAL_COLUMNS}[view], *ren)
    return {c: ren.get(c, c.lower()) for c in dict.fromkeys(cols)}


def _select(view: str) -> str:
    return ", ".join(f'{expr} AS "{col}"' for col, expr in _view_columns(view).items())


def _file_columns(view: str) -> tuple[str, ...]:
    """The MIMIC-IV columns the view reads (checked when the file is opened): the
    expressions that are plain column names."""
    exprs = _view_columns(view).values()
    return tuple(dict.fromkeys(e for e in exprs if e.isidentifier()))


MIMIC4 = Layout(
    name="MIMIC-IV", kind="mimic4", env_var=ENV_VAR, files=FILES,
    columns={v: _file_columns(v) for v in FILES if FILES[v]},
    select={v: _select(v) for v in FILES if FILES[v]},
    age="anchor",
    example="hosp/patients.csv.gz, icu/icustays.csv.gz, icu/chartevents.csv.gz, ...")


def resolve_mimic4_dir(configured: str | Path | None) -> Path:
    """The MIMIC-IV folder: env var ``TWINFALSIFY_MIMIC4_DIR`` if set, else ``configured``."""
    return resolve_dir(configured, MIMIC4)


def extract_mimic4(folder: Path, *, t_max: int = schema.T_MAX, threads: int = 1,
                   anchor: str = "first_vitals", anchor_window_h: int = ANCHOR_WINDOW_H,
                   options: Mimic3Options | None = None, memory_limit: str | None = None,
                   temp_directory: str | Path | None = None,
                   stage: bool = True) -> Mimic3Cohort:
    """The sepsis-3 cohort of ``extract_mimic3`` from the MIMIC-IV tables in ``folder``:
    the same steps, switches, presets, audit table and CONSORT (``DIFFERENCES``: what the
    schema changes)."""
    return extract_mimic3(folder, t_max=t_max, threads=threads, anchor=anchor,
                          anchor_window_h=anchor_window_h, options=options,
                          memory_limit=memory_limit, temp_directory=temp_directory,
                          stage=stage, layout=MIMIC4)


__all__ = ["DIFFERENCES", "ENV_VAR", "MIMIC4", "extract_mimic4", "resolve_mimic4_dir"]
