"""A MEDS dataset on disk: its folder checked (parse time, from Parquet footers only) and its
events opened in DuckDB as one view, read by streaming scans.

The layout (MEDS 0.3): ``data/**/*.parquet`` (the event shards: ``subject_id`` int64,
``time`` timestamp, ``code`` string, ``numeric_value`` float, any further columns),
``metadata/dataset.json`` (name, version, ETL), optionally ``metadata/codes.parquet`` and
``metadata/subject_splits.parquet``. Every broken rule stops with one line naming the file
(:class:`~twinfalsify.schema.ContractError`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from twinfalsify.schema import ContractError

# column -> (what the rule says, a check of the Arrow type)
CORE_COLUMNS: dict[str, tuple[str, Any]] = {
    "subject_id": ("an integer", pa.types.is_integer),
    "time": ("a timestamp", pa.types.is_timestamp),
    "code": ("a string", lambda t: pa.types.is_string(t) or pa.types.is_large_string(t)
             or pa.types.is_dictionary(t)),
    "numeric_value": ("a number", lambda t: pa.types.is_floating(t) or pa.types.is_integer(t)),
}
OPTIONAL_TYPES: dict[str, tuple[str, Any]] = {
    "text_value": ("a string", lambda t: pa.types.is_string(t) or pa.types.is_large_string(t)),
    "unit": ("a string", lambda t: pa.types.is_string(t) or pa.types.is_large_string(t)),
}


@dataclass(frozen=True)
class MedsDataset:
    """A checked MEDS folder: its shards (by name), metadata and the optional columns every
    shard has (``columns``)."""

    path: Path
    shards: tuple[Path, ...]
    metadata: dict[str, Any]
    columns: frozenset[str]
    n_rows: int

    @property
    def label(self) -> str:
        m = self.metadata
        return (f"{m.get('dataset_name', '?')} {m.get('dataset_version', '?')} "
                f"(ETL {m.get('etl_name', '?')} {m.get('etl_version', '?')}, MEDS "
                f"{m.get('meds_version', '?')})")

    def scan(self) -> str:
        """The DuckDB table function reading every shard (column names unified)."""
        files = ", ".join("'" + str(p).replace("'", "''") + "'" for p in self.shards)
        return f"read_parquet([{files}], union_by_name = true)"


def open_dataset(path: str | Path) -> MedsDataset:
    """Check a MEDS folder from its footers: ``metadata/dataset.json`` readable, at least one
    shard under ``data/``, every shard non-empty with the core columns in MEDS types."""
    root = Path(path)
    if not root.is_dir():
        raise ContractError(f"source.meds.path: {root} is not a folder")
    meta_file = root / "metadata" / "dataset.json"
    if not meta_file.is_file():
        raise ContractError(f"{root}: no metadata/dataset.json (rule: a MEDS dataset names "
                            "its data and ETL in metadata/dataset.json)")
    try:
        meta = json.loads(meta_file.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ContractError(f"{meta_file}: not JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise ContractError(f"{meta_file}: expected a JSON object, got {type(meta).__name__}")
    shards = tuple(sorted((root / "data").rglob("*.parquet"))) if (root / "data").is_dir() \
        else ()
    if not shards:
        raise ContractError(f"{root}: no data/**/*.parquet shard (rule: MEDS events live in "
                            "Parquet shards under data/)")
    optional = set(OPTIONAL_TYPES)
    n_rows = 0
    for shard in shards:
        try:
            f = pq.ParquetFile(shard)
        except Exception as exc:  # noqa: BLE001 - re-raised with the file named
            first = str(exc).splitlines()[0] if str(exc) else ""
            raise ContractError(f"{shard}: not a Parquet file ({type(exc).__name__}: "
                                f"{first})") from None
        schema = f.schema_arrow
        for col, (what, ok) in CORE_COLUMNS.items():
            if col not in schema.names:
                raise ContractError(f"{shard}: no column {col!r} (rule: every MEDS shard has "
                                    f"{', '.join(CORE_COLUMNS)})")
            typ = schema.field(col).type
            if not ok(typ):
                raise ContractError(f"{shard}: column {col!r} is {typ}, not {what} (rule: "
                                    "MEDS types subject_id int64, time timestamp, code "
                                    "string, numeric_value float32)")
        for col, (what, ok) in OPTIONAL_TYPES.items():
            if col in schema.names and not ok(schema.field(col).type):
                raise ContractError(f"{shard}: column {col!r} is {schema.field(col).type}, "
                                    f"not {what}")
        optional &= set(schema.names)
        if f.metadata.num_rows == 0:
            raise ContractError(f"{shard}: an empty shard (no rows; rule: every shard holds "
                                "events; remove it or re-run the ETL)")
        n_rows += f.metadata.num_rows
    cols = frozenset(optional)
    return MedsDataset(root, shards, meta, cols, n_rows)


def connect(ds: MedsDataset, threads: int = 1, memory_limit: str | None = None,
            temp_directory: str | Path | None = None) -> duckdb.DuckDBPyConnection:
    """A DuckDB connection with the view ``events`` over every shard."""
    con = duckdb.connect(database=":memory:")
    con.execute(f"SET threads = {int(threads)}")
    if memory_limit:
        con.execute(f"SET memory_limit = '{memory_limit}'")
    if temp_directory:
        Path(temp_directory).mkdir(parents=True, exist_ok=True)
        con.execute(f"SET temp_directory = '{Path(temp_directory)}'")
    con.execute("SET preserve_insertion_order = false")
    con.execute(f"CREATE VIEW events AS SELECT * FROM {ds.scan()}")
    return con
