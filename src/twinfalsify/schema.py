"""Column contracts shared by every stage, and validation with clear errors.

Feature names follow the AI-Clinician sepsis cohort (Komorowski et al. 2018),
which the paper's MIMIC-III data comes from; units are MIMIC's.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pandas is imported where a table is read: a twin's protocol needs none
    import pandas as pd

T_MAX = 4  # hourly steps after t = 0 (docs/explanation/method.md: T = 4)

STAY_ID = "stay_id"
TIME = "t"
IV_FLUID = "iv_fluid"  # mL/h during hour t -> t+1
VASOPRESSOR = "vasopressor"  # norepinephrine-equivalent ug/kg/min during hour t -> t+1
DOSES = (IV_FLUID, VASOPRESSOR)
WHOLE_SPACE = -1  # B-set code meaning "no restriction" (Manski hypotheses)


@dataclass(frozen=True)
class Feature:
    name: str
    unit: str
    kind: str  # demographic | vital | lab
    lo: float  # plausible range (values outside are rejected by validation)
    hi: float
    meaning: str


FEATURE_TABLE: tuple[Feature, ...] = (
    Feature("age", "years", "demographic", 18, 110, "age at ICU admission"),
    Feature("sex", "0/1", "demographic", 0, 1, "sex, 1 = female, 0 = male"),
    Feature("weight", "kg", "demographic", 20, 300, "body weight"),
    Feature("HR", "/min", "vital", 0, 300, "heart rate"),
    Feature("SysBP", "mmHg", "vital", 0, 300, "systolic arterial blood pressure"),
    Feature("DiaBP", "mmHg", "vital", 0, 250, "diastolic arterial blood pressure"),
    Feature("MeanBP", "mmHg", "vital", 0, 250, "mean arterial blood pressure"),
    Feature("RR", "/min", "vital", 0, 80, "respiratory rate"),
    Feature("Temp_C", "degC", "vital", 25, 45, "body temperature"),
    Feature("Potassium", "mmol/L", "lab", 1, 15, "serum potassium"),
    Feature("Sodium", "mmol/L", "lab", 95, 180, "serum sodium"),
    Feature("Chloride", "mmol/L", "lab", 60, 160, "serum chloride"),
    Feature("Glucose", "mg/dL", "lab", 1, 2000, "serum glucose"),
    Feature("Calcium", "mg/dL", "lab", 2, 20, "serum total calcium"),
    Feature("HCO3", "mmol/L", "lab", 2, 60, "serum bicarbonate"),
    Feature("paO2", "mmHg", "lab", 10, 800, "arterial partial pressure of oxygen"),
    Feature("paCO2", "mmHg", "lab", 5, 200, "arterial partial pressure of CO2"),
    Feature("Arterial_pH", "pH", "lab", 6.5, 8.0, "arterial blood pH"),
)
FEATURES: tuple[str, ...] = tuple(f.name for f in FEATURE_TABLE)
FEATURE_BY_NAME: Mapping[str, Feature] = {f.name: f for f in FEATURE_TABLE}

# The features a Pulse patient can be initialised with (docs/explanation/method.md: X_0).
INIT_FEATURES: tuple[str, ...] = ("age", "sex", "weight", "HR", "SysBP", "DiaBP", "RR")

# Outcomes under test: 6 vitals, 8 labs and arterial pH (docs/explanation/method.md).
OUTCOMES: tuple[str, ...] = (
    "HR",
    "SysBP",
    "DiaBP",
    "MeanBP",
    "RR",
    "Temp_C",
    "Potassium",
    "Sodium",
    "Chloride",
    "Glucose",
    "Calcium",
    "HCO3",
    "paO2",
    "paCO2",
    "Arterial_pH",
)

TRAJECTORY_COLUMNS: tuple[str, ...] = (STAY_ID, TIME, *FEATURES, *DOSES)
# Optional trajectory column: the patient a stay belongs to (MIMIC-III SUBJECT_ID), one per
# stay. Stays of one patient are kept on one side of the D0 / D split and spread over the
# X_0 draws (split.py, runs/plan.py); without it every stay is its own patient.
SUBJECT_ID = "subject_id"

# "implausible": the twin answered, but a value breaks the trajectory contract's range
# (FEATURE_TABLE lo/hi); set by the runner, never trusted from a twin. Counts as failed.
TWIN_STATUSES: tuple[str, ...] = (
    "ok", "init_failed", "irreversible", "timeout", "error", "implausible",
)


@dataclass(frozen=True)
class TwinNodes:
    """Twin runs in prefix-tree form: one row per (node = a_1:s, X_0).

    values: (n_nodes, m, F) features at hour s = len(node) (NaN where the run
    failed at or before hour s); x0: (m, F) real X_0 rows of the initial stays.
    """

    index: dict[tuple[int, ...], int]
    values: np.ndarray
    x0: np.ndarray


class ContractError(ValueError):
    """Input that breaks a data contract; the message names file, column and problem."""


def _where(source: str | Path | None) -> str:
    return f"{source}: " if source else ""


def require_columns(
    df: pd.DataFrame, columns: Iterable[str], source: str | Path | None = None
) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ContractError(
            f"{_where(source)}missing column(s) {', '.join(missing)}; "
            f"found {', '.join(map(str, df.columns[:30]))}"
        )


def validate_trajectories(
    df: pd.DataFrame, source: str | Path | None = None, t_max: int = T_MAX
) -> pd.DataFrame:
    """Check the trajectory contract and return a canonically ordered copy.

    Contract: one row per (stay_id, t), t = 0..t_max for every stay, every
    feature finite and inside its plausible range, doses finite and >= 0 for
    t < t_max (the dose in the last row is never used and may be missing).
    """
    import pandas as pd

    where = _where(source)
    require_columns(df, TRAJECTORY_COLUMNS, source)
    if df.empty:
        raise ContractError(f"{where}no trajectories (empty table)")
    keep = [*TRAJECTORY_COLUMNS, *([SUBJECT_ID] if SUBJECT_ID in df.columns else [])]
    out = df.loc[:, keep].copy()
    for col in (*FEATURES, *DOSES):
        if not pd.api.types.is_numeric_dtype(out[col]):
            raise ContractError(f"{where}column {col} is not numeric (dtype {out[col].dtype})")
        out[col] = out[col].astype("float64")
    out[STAY_ID] = out[STAY_ID].astype("int64")
    out[TIME] = out[TIME].astype("int64")
    if SUBJECT_ID in out:
        subj = pd.to_numeric(out[SUBJECT_ID], errors="coerce")
        if subj.isna().any() or (subj != np.round(subj)).any():
            raise ContractError(f"{where}column {SUBJECT_ID} must be an integer in every row")
        out[SUBJECT_ID] = subj.astype("int64")
        per_stay = out.groupby(STAY_ID)[SUBJECT_ID].nunique()
        if (per_stay > 1).any():
            raise ContractError(f"{where}column {SUBJECT_ID}: stay_id {per_stay.idxmax()} has "
                                "more than one subject")
    dup = out.duplicated([STAY_ID, TIME])
    if dup.any():
        # read the two int columns separately: a row of the mixed frame would be float
        stay, hour = int(out.loc[dup, STAY_ID].iloc[0]), int(out.loc[dup, TIME].iloc[0])
        raise ContractError(
            f"{where}duplicated (stay_id, t): stay_id {stay} has t = {hour} "
            f"more than once ({int(dup.sum())} duplicated rows)"
        )
    bad_t = ~out[TIME].between(0, t_max)
    if bad_t.any():
        raise ContractError(
            f"{where}column t has values outside 0..{t_max}: "
            f"{[int(v) for v in sorted(out.loc[bad_t, TIME].unique())[:5]]}"
        )
    counts = out.groupby(STAY_ID)[TIME].count()
    short = counts[counts != t_max + 1]
    if len(short):
        raise ContractError(
            f"{where}every stay needs hours t = 0..{t_max}; {len(short)} stay(s) do not, "
            f"e.g. stay_id {short.index[0]} has {short.iloc[0]} row(s)"
        )
    for feat in FEATURE_TABLE:
        col = out[feat.name]
        if col.isna().any():
            stay = out.loc[col.isna(), STAY_ID].iloc[0]
            raise ContractError(
                f"{where}column {feat.name} has {int(col.isna().sum())} missing value(s), "
                f"e.g. stay_id {stay}"
            )
        bad = ~col.between(feat.lo, feat.hi)
        if bad.any():
            i = bad.idxmax()
            raise ContractError(
                f"{where}column {feat.name} ({feat.unit}) has {int(bad.sum())} value(s) outside "
                f"the plausible range [{feat.lo}, {feat.hi}], e.g. {col[i]:g} for stay_id "
                f"{out.at[i, STAY_ID]} at t = {out.at[i, TIME]}"
                + (" (Fahrenheit in a Celsius column?)" if feat.name == "Temp_C" else "")
            )
    if not out["sex"].isin([0.0, 1.0]).all():
        raise ContractError(f"{where}column sex must be 0 (male) or 1 (female)")
    used = out[TIME] < t_max
    for dose in DOSES:
        col = out.loc[used, dose]
        if col.isna().any():
            stay = out.loc[used & out[dose].isna(), STAY_ID].iloc[0]
            raise ContractError(
                f"{where}column {dose} has missing values before t = {t_max}, e.g. stay_id {stay}"
            )
        if (col < 0).any() or not np.isfinite(col).all():
            i = col[(col < 0) | ~np.isfinite(col)].index[0]
            raise ContractError(
                f"{where}column {dose} must be finite and >= 0; found {col[i]:g} for stay_id "
                f"{out.at[i, STAY_ID]} at t = {out.at[i, TIME]}"
            )
    return out.sort_values([STAY_ID, TIME], kind="stable").reset_index(drop=True)


def to_array(df: pd.DataFrame, columns: Iterable[str], t_max: int = T_MAX) -> np.ndarray:
    """Long (stay, t) table sorted by stay then t -> array (n_stays, t_max + 1, n_columns)."""
    cols = list(columns)
    values = df[cols].to_numpy(dtype="float64")
    n = len(df) // (t_max + 1)
    return values.reshape(n, t_max + 1, len(cols))


def mark_implausible(
    features: np.ndarray, status: np.ndarray, message: np.ndarray
) -> int:
    """Fail, in place, every run whose twin returned a value outside its feature's range.

    features: (n, t, len(FEATURES)) hourly values, NaN after a run's last hour; status,
    message: (n,) object arrays. The range is the one every observed trajectory must lie in
    (FEATURE_TABLE lo/hi, the same contract as :func:`validate_trajectories`), so a twin is
    held to what the data it is compared with may contain. A run whose hour h has a finite
    value outside the range (e.g. HR 1e300 or -500), or an infinite one, gets status
    ``implausible``, a message naming hour, feature, value and range, and NaN from hour h
    on (hours before it are kept, as for any failure). Returns the number of runs marked.
    """
    lo = np.array([f.lo for f in FEATURE_TABLE])
    hi = np.array([f.hi for f in FEATURE_TABLE])
    with np.errstate(invalid="ignore"):
        bad = (features < lo) | (features > hi)  # NaN compares False: a missing hour is fine
    runs = np.flatnonzero(bad.any(axis=(1, 2)))
    for i in runs:
        h, j = (int(v) for v in np.argwhere(bad[i])[0])
        feat = FEATURE_TABLE[j]
        status[i] = "implausible"
        message[i] = (
            f"hour {h + 1}: {feat.name} = {features[i, h, j]:g} {feat.unit} outside the "
            f"plausible range [{feat.lo:g}, {feat.hi:g}]"
        )
        features[i, h:] = np.nan
    return len(runs)
