"""MEDS label tables (as ACES writes them): the cohort read from one, and written as one.

A label table is Parquet with ``subject_id`` (integer), ``prediction_time`` (timestamp) and
optionally ``boolean_value`` (and the other ``*_value`` columns); a file or a folder of files.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from twinfalsify.schema import ContractError

LABEL_COLUMNS = ("subject_id", "prediction_time", "boolean_value")


def label_files(path: str | Path | None) -> tuple[Path, ...]:
    """The label table's files, checked from their footers (parse time)."""
    if path is None:
        raise ContractError("source.meds.labels: cohort labels needs the path of a MEDS label "
                            "table (subject_id, prediction_time[, boolean_value])")
    p = Path(path)
    if not p.exists():
        raise ContractError(f"source.meds.labels: {p} does not exist")
    files = (p,) if p.is_file() else tuple(sorted(p.rglob("*.parquet")))
    if not files:
        raise ContractError(f"source.meds.labels: folder {p} holds no .parquet file")
    for f in files:
        try:
            sch = pq.read_schema(f)
        except Exception as exc:  # noqa: BLE001 - re-raised with the file named
            raise ContractError(f"{f}: not a Parquet label table ({type(exc).__name__})") \
                from None
        for col, ok, what in (("subject_id", pa.types.is_integer, "an integer"),
                              ("prediction_time", pa.types.is_timestamp, "a timestamp")):
            if col not in sch.names:
                raise ContractError(f"{f}: no column {col!r} (rule: a MEDS label table has "
                                    "subject_id, prediction_time[, boolean_value])")
            if not ok(sch.field(col).type):
                raise ContractError(f"{f}: column {col!r} is {sch.field(col).type}, not {what}")
        if "boolean_value" in sch.names and not pa.types.is_boolean(
                sch.field("boolean_value").type):
            raise ContractError(f"{f}: column 'boolean_value' is "
                                f"{sch.field('boolean_value').type}, not a boolean")
    return files


def read_labels(path: str | Path | None) -> pd.DataFrame:
    """subject_id, prediction_time[, boolean_value] of every row of the label table."""
    frames = []
    for f in label_files(path):
        names = pq.read_schema(f).names
        frames.append(pd.read_parquet(f, columns=[c for c in LABEL_COLUMNS if c in names]))
    lab = pd.concat(frames, ignore_index=True)
    lab["prediction_time"] = pd.to_datetime(lab["prediction_time"]).astype("datetime64[ns]")
    if lab["subject_id"].isna().any() or lab["prediction_time"].isna().any():
        raise ContractError(f"{path}: a label row without subject_id or prediction_time")
    return lab


def cohort_labels(anchors: pd.DataFrame, stay_ids) -> pd.DataFrame:
    """The cohort as a MEDS label table: one row per trajectory (``anchors``: stay_id,
    subject_id, t0), ``prediction_time`` = its t = 0, ``boolean_value`` true, and the
    ``stay_id`` (an extra column MEDS tools ignore), sorted by subject and time."""
    a = anchors[anchors["stay_id"].isin(list(stay_ids))]
    out = pd.DataFrame({"subject_id": a["subject_id"].astype("int64").to_numpy(),
                        "prediction_time": pd.to_datetime(a["t0"]).astype(
                            "datetime64[us]").to_numpy(),
                        "boolean_value": True,
                        "stay_id": a["stay_id"].astype("int64").to_numpy()})
    return out.sort_values(["subject_id", "prediction_time"], kind="stable").reset_index(
        drop=True)


def write_labels(labels: pd.DataFrame, path: str | Path) -> None:
    """Write a label table with MEDS's label schema types (int64, timestamp[us], bool)."""
    schema = pa.schema([("subject_id", pa.int64()), ("prediction_time", pa.timestamp("us")),
                        ("boolean_value", pa.bool_()), ("stay_id", pa.int64())])
    table = pa.Table.from_pandas(labels, schema=schema, preserve_index=False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(path).with_suffix(".tmp")
    pq.write_table(table, tmp)
    tmp.replace(path)
