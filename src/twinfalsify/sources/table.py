"""The ``table`` source: a user's own hourly trajectories, from Parquet or CSV files.

A table holds one row per (stay, hour) in the trajectory contract (``schema``): the ids
``stay_id`` and ``subject_id`` (the patient; a patient may have several stays), the hour
``t`` = 0..T, the 18 features in contract units (``schema.FEATURE_TABLE``) and the doses
``iv_fluid`` (mL/h) and ``vasopressor`` (ug/kg/min). The doses of row t are the ones given
during hour t -> t+1, so row 0 holds A_1 and the doses of row T are never used (they may be
empty). Extra columns are ignored.

:func:`read_table` reads a file or a folder of files and checks every rule before any
study work, stopping at the first broken one with one line that names the file, the row,
the column and the rule (:class:`~twinfalsify.schema.ContractError`). Rows are numbered
from 1 as a spreadsheet shows them below the header (CSV: line = row + 1).

``python -m twinfalsify.sources.table check PATH`` runs the same checks on a table;
``... export OUT`` writes the synthetic world's trajectories in this format.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify.schema import (
    DOSES,
    FEATURE_TABLE,
    FEATURES,
    STAY_ID,
    SUBJECT_ID,
    T_MAX,
    TIME,
    ContractError,
    validate_trajectories,
)

ID_COLUMNS = (STAY_ID, SUBJECT_ID, TIME)
TABLE_COLUMNS: tuple[str, ...] = (*ID_COLUMNS, *FEATURES, *DOSES)
SUFFIXES = (".parquet", ".pq", ".csv", ".csv.gz")
_FILE = "__file"  # bookkeeping columns: where a row came from, for error messages
_ROW = "__row"
# Column names EHR extracts often use for the contract's columns: a hint, never a rename.
_ALIASES = {
    STAY_ID: ("icustay_id", "ICUSTAY_ID", "stayid", "patientunitstayid", "admissionid"),
    SUBJECT_ID: ("SUBJECT_ID", "patient_id", "patientid", "uniquepid", "patient"),
    TIME: ("hour", "hours", "time", "charttime", "bloc"),
    "Temp_C": ("Temp", "temperature", "Temp_F"),
    "Arterial_pH": ("pH", "ph"),
    "iv_fluid": ("input_4hourly", "fluid", "fluids", "iv"),
    "vasopressor": ("max_dose_vaso", "norepinephrine", "vaso"),
}
# Likely unit mistakes, said when a value leaves the contract's range.
_UNIT_HINTS = {
    "Temp_C": "Fahrenheit in a Celsius column?",
    "weight": "pounds in a kg column?",
    "Calcium": "mmol/L in a mg/dL column? (mg/dL = 4.008 x mmol/L)",
    "sex": "1 = female, 0 = male",
}


@dataclass(frozen=True)
class TableSource:
    """The files of a table source, in the order they are read."""

    path: Path
    files: tuple[Path, ...]


def is_table_file(path: Path) -> bool:
    return path.name.lower().endswith(SUFFIXES)


def table_files(path: str | Path) -> TableSource:
    """The table files at ``path``: the file itself, or the folder's table files by name.

    Raises ContractError when the path does not exist, a file is not Parquet or CSV, or a
    folder holds no table file (files starting with ``.`` or ``_`` are skipped).
    """
    path = Path(path)
    if not path.exists():
        raise ContractError(f"source.table.path: {path} does not exist")
    if path.is_file():
        if not is_table_file(path):
            raise ContractError(f"source.table.path: {path} is not a table file (expected one "
                                f"of {', '.join(SUFFIXES)})")
        return TableSource(path, (path,))
    files = tuple(sorted(p for p in path.iterdir() if p.is_file() and is_table_file(p)
                         and not p.name.startswith((".", "_"))))
    if not files:
        raise ContractError(f"source.table.path: folder {path} holds no table file "
                            f"({', '.join(SUFFIXES)})")
    return TableSource(path, files)


def _header(file: Path) -> list[str]:
    """The column names of one file, read without its data."""
    try:
        if file.name.lower().endswith((".parquet", ".pq")):
            import pyarrow.parquet as pq

            return list(pq.read_schema(file).names)
        return list(pd.read_csv(file, nrows=0).columns)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ContractError(f"{file}: cannot read the header ({type(exc).__name__}: "
                            f"{str(exc).splitlines()[0] if str(exc) else ''})") from None


def _missing_columns(file: Path, columns: Sequence[str]) -> str | None:
    missing = [c for c in TABLE_COLUMNS if c not in columns]
    if not missing:
        return None
    if len(columns) == 1:
        for sep in (";", "\t", "|"):
            if set(TABLE_COLUMNS) <= {c.strip() for c in str(columns[0]).split(sep)}:
                return (f"{file}: one column {str(columns[0])[:60]!r}...: the file is "
                        f"separated by {sep!r}, the table contract's CSV by ',' (write it "
                        "with commas, e.g. pandas to_csv(path, index=False))")
    hints = [f"{alias!r} -> {c!r}" for c in missing for alias in _ALIASES.get(c, ())
             if alias in columns]
    return (f"{file}: missing column(s) {', '.join(missing)} (rule: every column of the "
            f"trajectory contract)" + (f"; rename {', '.join(hints)}" if hints else "")
            + f"; found {', '.join(map(str, columns[:25]))}"
            + (" ..." if len(columns) > 25 else ""))


def check_headers(path: str | Path) -> TableSource:
    """Parse-time check: the files exist and every one has the contract's columns."""
    source = table_files(path)
    for file in source.files:
        problem = _missing_columns(file, _header(file))
        if problem:
            raise ContractError(problem)
    return source


def _read_one(file: Path) -> pd.DataFrame:
    try:
        if file.name.lower().endswith((".parquet", ".pq")):
            df = pd.read_parquet(file)
        else:
            # pandas' CSV parser reads a float written with repr back as the same double
            df = pd.read_csv(file)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise ContractError(f"{file}: cannot read ({type(exc).__name__}: {first})") from None
    problem = _missing_columns(file, list(df.columns))
    if problem:
        raise ContractError(problem)
    df = df.loc[:, list(TABLE_COLUMNS)].copy()
    df[_FILE] = str(file)
    df[_ROW] = np.arange(1, len(df) + 1)
    return df


def _where(df: pd.DataFrame, i: int, column: str | None = None) -> str:
    """'file: row r (line l, stay_id s, t h), column c' for row label ``i`` of ``df``."""
    file, row = df.at[i, _FILE], int(df.at[i, _ROW])
    line = f"line {row + 1}, " if not file.lower().endswith((".parquet", ".pq")) else ""
    ids = []
    for col in (STAY_ID, TIME):
        v = df.at[i, col]
        if pd.notna(v) and col != column:
            ids.append(f"{col} {int(v) if float(v).is_integer() else repr(float(v))}")
    inside = ", ".join([s for s in (line.rstrip(", "),) if s] + ids)
    return f"{file}: row {row}" + (f" ({inside})" if inside else "") + (
        f", column {column}" if column else "")


def _show(value: object) -> str:
    """A cell for a message: numbers as written (1.5, 200001), anything else quoted."""
    if isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool):
        # repr: the shortest text that reads back as this double (201204.5, not 201204)
        return repr(float(value)) if not float(value).is_integer() else str(int(value))
    return repr(value)


def _first(df: pd.DataFrame, bad: pd.Series | np.ndarray) -> int:
    """Label of the first offending row, in file order."""
    return df.index[np.flatnonzero(np.asarray(bad))[0]]


def _check_ids(df: pd.DataFrame) -> None:
    for col in ID_COLUMNS:
        v = df[col]
        if not pd.api.types.is_numeric_dtype(v):
            num = pd.to_numeric(v, errors="coerce")
            i = _first(df, num.isna() & v.notna())
            raise ContractError(f"{_where(df, i, col)}: {_show(v[i])} is not a number (rule: "
                                f"{col} is an integer)")
        if v.isna().any():
            rule = {SUBJECT_ID: "every stay names its patient (subject_id)",
                    STAY_ID: "every row names its stay", TIME: "every row names its hour"}[col]
            raise ContractError(f"{_where(df, _first(df, v.isna()), col)}: missing value "
                                f"(rule: {rule})")
        frac = v.astype(float) % 1 != 0
        if frac.any():
            i = _first(df, frac)
            raise ContractError(f"{_where(df, i, col)}: {_show(v[i])} is not an integer (rule: "
                                f"{col} is an integer)")
    subjects = df.groupby(STAY_ID)[SUBJECT_ID].transform("nunique")
    if (subjects > 1).any():
        i = _first(df, subjects > 1)
        names = sorted(df.loc[df[STAY_ID] == df.at[i, STAY_ID], SUBJECT_ID].unique())
        raise ContractError(f"{_where(df, i, SUBJECT_ID)}: stay has subject_id "
                            f"{', '.join(str(int(s)) for s in names)} (rule: a stay belongs "
                            "to one patient)")


def _check_hours(df: pd.DataFrame, t_max: int) -> None:
    t = df[TIME]
    bad = ~t.between(0, t_max)
    if bad.any():
        i = _first(df, bad)
        raise ContractError(f"{_where(df, i, TIME)}: hour {int(t[i])} outside 0..{t_max} "
                            f"(rule: hours t = 0..{t_max}, t = 0 the start of the trajectory; "
                            "drop later hours)")
    dup = df.duplicated([STAY_ID, TIME], keep="first")
    if dup.any():
        i = _first(df, dup)
        same = df[(df[STAY_ID] == df.at[i, STAY_ID]) & (df[TIME] == df.at[i, TIME])]
        j = same.index[0]
        raise ContractError(f"{_where(df, i)}: duplicate (stay_id, t), first given at "
                            f"{df.at[j, _FILE]} row {int(df.at[j, _ROW])} (rule: one row per "
                            "stay and hour)")
    counts = df.groupby(STAY_ID)[TIME].transform("size")
    short = counts != t_max + 1
    if short.any():
        i = _first(df, short)
        have = sorted(int(h) for h in df.loc[df[STAY_ID] == df.at[i, STAY_ID], TIME])
        gap = [h for h in range(t_max + 1) if h not in have]
        raise ContractError(f"{_where(df, i, TIME)}: stay has hours {have}, missing "
                            f"{gap} (rule: every hour t = 0..{t_max}, no gaps)")


def _check_values(df: pd.DataFrame, t_max: int) -> None:
    for feat in FEATURE_TABLE:
        col = df[feat.name]
        if not pd.api.types.is_numeric_dtype(col):
            num = pd.to_numeric(col, errors="coerce")
            i = _first(df, num.isna() & col.notna())
            raise ContractError(f"{_where(df, i, feat.name)}: {_show(col[i])} is not a number "
                                f"(rule: {feat.name} in {feat.unit})")
        if col.isna().any():
            raise ContractError(
                f"{_where(df, _first(df, col.isna()), feat.name)}: missing value (rule: every "
                "feature every hour; carry the last value charted at or before the hour "
                "forward, never backward)")
        bad = ~col.between(feat.lo, feat.hi)
        if bad.any():
            i = _first(df, bad)
            hint = _UNIT_HINTS.get(feat.name)
            raise ContractError(
                f"{_where(df, i, feat.name)}: {col[i]:g} outside [{feat.lo:g}, {feat.hi:g}] "
                f"{feat.unit} (rule: {feat.meaning} in {feat.unit})"
                + (f"; {hint}" if hint else ""))
    sex = df["sex"]
    bad = ~sex.isin([0, 1])
    if bad.any():
        i = _first(df, bad)
        raise ContractError(f"{_where(df, i, 'sex')}: {sex[i]:g} (rule: sex is 0 or 1, "
                            "1 = female)")
    varies = df.groupby(STAY_ID)["sex"].transform("nunique") > 1
    if varies.any():
        raise ContractError(f"{_where(df, _first(df, varies), 'sex')}: sex changes within the "
                            "stay (rule: sex is constant over a stay)")
    used = df[TIME] < t_max
    for dose in DOSES:
        col = df[dose]
        if not pd.api.types.is_numeric_dtype(col):
            num = pd.to_numeric(col, errors="coerce")
            i = _first(df, num.isna() & col.notna())
            raise ContractError(f"{_where(df, i, dose)}: {_show(col[i])} is not a number")
        missing = used & col.isna()
        if missing.any():
            i = _first(df, missing)
            hint = ("; a dose labelled by the end of its hour belongs one row up"
                    if int(df.at[i, TIME]) == 0 else "")
            raise ContractError(
                f"{_where(df, i, dose)}: missing dose (rule: row t holds the dose given "
                f"during hour t -> t+1, so rows t = 0..{t_max - 1} need one; 0 = none given)"
                + hint)
        bad = used & ((col < 0) | ~np.isfinite(col.astype(float)))
        if bad.any():
            i = _first(df, bad)
            raise ContractError(f"{_where(df, i, dose)}: {col[i]:g} (rule: a dose is finite "
                                "and >= 0)")


def validate_table(df: pd.DataFrame, t_max: int = T_MAX) -> pd.DataFrame:
    """Check the table rules on rows read by :func:`read_rows`; return the contract frame.

    Order of the rules: ids (numbers, integers, present, one subject per stay), hours
    (0..T, no duplicate, no gap), features (numbers, present, inside the contract's range,
    sex 0/1 and constant), doses (present, finite, >= 0 for t < T). The result keeps the
    contract's columns (``schema.validate_trajectories``, which also sorts by stay and hour).
    """
    if df.empty:
        files = sorted(df[_FILE].unique()) if _FILE in df else []
        raise ContractError(f"{', '.join(files) or 'table'}: no rows (rule: at least one stay)")
    _check_ids(df)
    _check_hours(df, t_max)
    _check_values(df, t_max)
    out = df.drop(columns=[_FILE, _ROW])
    return validate_trajectories(out, source="table", t_max=t_max)


def read_rows(path: str | Path) -> pd.DataFrame:
    """Every row of every table file at ``path``, with the file and row it came from."""
    source = check_headers(path)
    frames = [_read_one(f) for f in source.files]
    if all(f.empty for f in frames):
        raise ContractError(f"{', '.join(map(str, source.files))}: a header and no rows "
                            "(rule: at least one stay)")
    return pd.concat(frames, ignore_index=True) if len(frames) > 1 else frames[0]


def read_table(path: str | Path, t_max: int = T_MAX) -> pd.DataFrame:
    """The trajectories of a table source, checked (ContractError: one line at the first
    broken rule), in the trajectory contract's columns and order."""
    return validate_table(read_rows(path), t_max)


def unit_suspects(trajectories: pd.DataFrame) -> list[str]:
    """One message per feature whose median (all rows) lies outside the range an ICU
    cohort's median typically falls in, naming the unit that would explain it (values
    inside the contract's wide ranges can still be in the wrong unit: glucose in mmol/L)."""
    from twinfalsify.unitscreen import against_typical

    medians = trajectories[list(FEATURES)].median()
    return [m for f in FEATURES for m in [against_typical(f, float(medians[f]))] if m]


def check_units(trajectories: pd.DataFrame, source: str) -> None:
    """Stop (ContractError, one line) when ``unit_suspects`` names a feature: a study on a
    table in another unit would blame the twin for the table's unit."""
    suspects = unit_suspects(trajectories)
    if suspects:
        more = f" (and {len(suspects) - 1} more)" if len(suspects) > 1 else ""
        raise ContractError(f"{source}: the rows follow the contract, but a feature looks like "
                            f"another unit than the contract's: {suspects[0]}{more}; convert "
                            "it (docs/reference/table.md)")


def to_table(trajectories: pd.DataFrame, subject_id: pd.Series | None = None) -> pd.DataFrame:
    """Trajectories (contract frame) as a table: ``subject_id`` added after ``stay_id``
    (default: one patient per stay, subject_id = stay_id)."""
    out = trajectories.loc[:, [STAY_ID, TIME, *FEATURES, *DOSES]].copy()
    subjects = out[STAY_ID] if subject_id is None else subject_id
    out.insert(1, SUBJECT_ID, np.asarray(subjects, dtype="int64"))
    return out


def write_table(table: pd.DataFrame, path: str | Path) -> None:
    """Write a table as Parquet or CSV by the file name (CSV floats round-trip exactly)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.name.lower().endswith((".parquet", ".pq")):
        table.to_parquet(path, index=False)
    elif path.name.lower().endswith((".csv", ".csv.gz")):
        table.to_csv(path, index=False)
    else:
        raise ContractError(f"{path}: not a table file name (expected one of "
                            f"{', '.join(SUFFIXES)})")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m twinfalsify.sources.table",
        description="Check a trajectory table, or export the synthetic world as one.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    check = sub.add_parser("check", help="check a table file or folder against the contract")
    check.add_argument("path")
    export = sub.add_parser("export", help="write the synthetic world's trajectories")
    export.add_argument("out", help="output file (.csv, .csv.gz or .parquet)")
    export.add_argument("--n-stays", type=int, default=1500)
    export.add_argument("--seed", type=int, default=7)
    export.add_argument("--decimals", type=int, default=None,
                        help="round features and doses to this many decimals (smaller file)")
    args = parser.parse_args(argv)
    if args.cmd == "check":
        traj = read_table(args.path)
        suspects = unit_suspects(traj)
        for message in suspects:
            print(f"{args.path}: unit? {message}")
        if suspects:
            print(f"{args.path}: the rows follow the contract, but {len(suspects)} "
                  f"feature(s) look like another unit than the contract's (above)")
            return 1
        print(f"{args.path}: ok, {traj[STAY_ID].nunique()} stays, {len(traj)} rows")
        return 0
    from twinfalsify.sources.synthetic import generate

    traj = generate({"n_stays": args.n_stays}, seed=args.seed)
    if args.decimals is not None:
        cols = [*FEATURES, *DOSES]
        traj[cols] = traj[cols].round(args.decimals)
    write_table(to_table(traj), args.out)
    print(f"{args.out}: {args.n_stays} stays of the synthetic world (seed {args.seed})")
    return 0


if __name__ == "__main__":
    import sys

    from twinfalsify.io import cli_main

    sys.exit(cli_main(lambda: main(), "twinfalsify.sources.table"))
