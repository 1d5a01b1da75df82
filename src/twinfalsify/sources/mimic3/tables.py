"""Locate MIMIC tables on disk and expose them to DuckDB, plus the package's data tables.

MIMIC-III is shipped by PhysioNet as upper-case ``TABLE.csv.gz`` files (the full
database) or lower-case files (some mirrors); users also convert to Parquet.
Every table is opened lazily as a DuckDB view, so CHARTEVENTS (~330 M rows in
the full database) is only ever scanned by SQL filtered to the item ids and
hours needed, never loaded whole into pandas.

The extraction's queries are written against MIMIC-III v1.4's tables and columns (the view
names and columns below). A :class:`Layout` says where a release keeps each table and how
its columns give those: ``MIMIC3`` reads the files as they are; MIMIC-IV's layout
(``twinfalsify.sources.mimic4``) maps its ``hosp/`` and ``icu/`` tables onto the same views,
so both releases run the same cohort code.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path

import duckdb
import pandas as pd

from twinfalsify.schema import ContractError

ENV_VAR = "TWINFALSIFY_MIMIC3_DIR"
SUFFIXES = (".csv.gz", ".csv", ".parquet")

# Tables the extraction reads, with the columns it uses (checked on open, so a
# wrong file fails with a clear message rather than a DuckDB binder error).
REQUIRED_COLUMNS: dict[str, tuple[str, ...]] = {
    "PATIENTS": ("SUBJECT_ID", "GENDER", "DOB", "DOD"),
    "ADMISSIONS": ("SUBJECT_ID", "HADM_ID", "ADMITTIME", "DISCHTIME", "DEATHTIME",
                   "HOSPITAL_EXPIRE_FLAG"),
    "ICUSTAYS": ("SUBJECT_ID", "HADM_ID", "ICUSTAY_ID", "DBSOURCE", "INTIME", "OUTTIME"),
    "CHARTEVENTS": ("SUBJECT_ID", "HADM_ID", "ICUSTAY_ID", "ITEMID", "CHARTTIME", "VALUE",
                    "VALUENUM", "ERROR"),
    "LABEVENTS": ("SUBJECT_ID", "HADM_ID", "ITEMID", "CHARTTIME", "VALUE", "VALUENUM"),
    "PRESCRIPTIONS": ("SUBJECT_ID", "HADM_ID", "ICUSTAY_ID", "STARTDATE", "DRUG", "ROUTE"),
    "MICROBIOLOGYEVENTS": ("SUBJECT_ID", "HADM_ID", "CHARTDATE", "CHARTTIME", "SPEC_TYPE_DESC"),
    "INPUTEVENTS_MV": ("ICUSTAY_ID", "STARTTIME", "ENDTIME", "ITEMID", "AMOUNT", "RATE",
                       "RATEUOM", "STATUSDESCRIPTION", "PATIENTWEIGHT"),
    "INPUTEVENTS_CV": ("ICUSTAY_ID", "CHARTTIME", "ITEMID", "AMOUNT", "RATE", "RATEUOM"),
}
# Tables read only by some options (sofa = ai_clinician: urine output).
OPTIONAL_COLUMNS: dict[str, tuple[str, ...]] = {
    "OUTPUTEVENTS": ("ICUSTAY_ID", "CHARTTIME", "ITEMID", "VALUE"),
}


@dataclass(frozen=True)
class Layout:
    """Where a MIMIC release keeps the tables the extraction reads, and how their columns
    give MIMIC-III v1.4's (the names the extraction's queries use).

    ``files``: view -> file stems tried, relative to the folder (each with every suffix of
    ``SUFFIXES``); a view without stems is empty (e.g. INPUTEVENTS_CV: MIMIC-IV has no
    CareVue). ``select``: view -> SELECT list over the file's columns giving the view's
    columns (absent: the file as it is). ``columns``: the file's columns the view needs,
    checked on open. ``age``: ``"dob"`` (age = INTIME - DOB) or ``"anchor"`` (MIMIC-IV:
    anchor_age + year of INTIME - anchor_year; PATIENTS gives ANCHOR_AGE, ANCHOR_YEAR)."""

    name: str  # in messages: "MIMIC-III", "MIMIC-IV"
    kind: str  # the config's source kind, e.g. "mimic3"
    env_var: str
    files: Mapping[str, tuple[str, ...]]
    columns: Mapping[str, tuple[str, ...]]
    select: Mapping[str, str] = field(default_factory=dict)
    age: str = "dob"
    example: str = "PATIENTS.csv.gz, ICUSTAYS.csv.gz, CHARTEVENTS.csv.gz, ..."

    @property
    def config_key(self) -> str:
        return f"source.{self.kind}"


MIMIC3 = Layout(
    name="MIMIC-III", kind="mimic3", env_var=ENV_VAR,
    files={t: (t.upper(), t.lower()) for t in (*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS)},
    columns={**REQUIRED_COLUMNS, **OPTIONAL_COLUMNS})


def resolve_dir(configured: str | os.PathLike[str] | None, layout: Layout = MIMIC3) -> Path:
    """The release's folder: its environment variable (``TWINFALSIFY_MIMIC3_DIR`` for
    MIMIC-III) if set, else ``configured``.

    Raises ContractError naming the folder and the environment variable when
    neither is given or the folder does not exist.
    """
    env_var = layout.env_var
    env = os.environ.get(env_var)
    chosen = env if env else configured
    origin = f"environment variable {env_var}" if env else f"config ({layout.kind} path)"
    if not chosen:
        raise ContractError(
            f"no {layout.name} folder given: set the config path or the environment variable "
            f"{env_var}"
        )
    path = Path(chosen).expanduser()
    if not path.is_dir():
        raise ContractError(
            f"{layout.name} folder {path} (from {origin}) does not exist or is not a folder; "
            f"point the config or {env_var} at the folder holding {layout.example}"
        )
    return path


def resolve_mimic3_dir(configured: str | os.PathLike[str] | None) -> Path:
    """The MIMIC-III folder: env var ``TWINFALSIFY_MIMIC3_DIR`` if set, else ``configured``."""
    return resolve_dir(configured, MIMIC3)


def candidate_names(table: str, layout: Layout = MIMIC3) -> list[str]:
    """Paths (relative to the folder) tried for ``table``, in order: each stem of the layout
    (MIMIC-III: upper then lower case) with csv.gz, csv, parquet."""
    return [f"{base}{suf}" for base in layout.files.get(table, ()) for suf in SUFFIXES]


def find_table(folder: Path, table: str, layout: Layout = MIMIC3) -> Path:
    """Path of ``table`` inside ``folder``; ContractError naming folder and names tried."""
    for name in candidate_names(table, layout):
        p = folder / name
        if p.is_file():
            return p
    raise ContractError(
        f"{layout.name} table {table} not found in {folder}; tried "
        f"{', '.join(candidate_names(table, layout))}"
    )


def table_reader(path: Path) -> str:
    """The DuckDB table function reading ``path`` (Parquet, or CSV with every column text)."""
    lit = "'" + str(path).replace("'", "''") + "'"
    if path.name.endswith(".parquet"):
        return f"read_parquet({lit})"
    # all_varchar: types are cast explicitly in the queries, so type sniffing on a
    # sample cannot mis-type a column (e.g. VALUE holding numbers then text).
    return f"read_csv({lit}, header = true, all_varchar = true, quote = '\"', escape = '\"')"


def _unreadable(path: Path, exc: Exception, layout: Layout = MIMIC3) -> ContractError:
    """One line naming the file, from a DuckDB error (its first line, without the class)."""
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return ContractError(f"{path}: cannot be read as a {layout.name} table ({msg}); the file "
                         "may be truncated or corrupt: download or export it again")


def connect(folder: Path, tables: tuple[str, ...] | None = None, threads: int = 1,
            optional: tuple[str, ...] = (), *, memory_limit: str | None = None,
            temp_directory: str | os.PathLike[str] | None = None,
            layout: Layout = MIMIC3) -> duckdb.DuckDBPyConnection:
    """DuckDB connection with one view per MIMIC table (MIMIC-III's upper-case view names and
    columns, whatever the ``layout``): ``tables`` (default: every table of REQUIRED_COLUMNS)
    plus ``optional`` ones (OPTIONAL_COLUMNS).

    ``memory_limit`` (DuckDB syntax, e.g. ``"4GB"``; default DuckDB's, 80 % of RAM) caps
    DuckDB's buffers; beyond it DuckDB spills to ``temp_directory`` (default: DuckDB's).
    Each file is checked on open, cheaply (its header and first row): an unreadable file
    (empty, not gzip, truncated within the first block), a missing column or a table with a
    header and no rows raises ContractError naming the file. Damage further into a large
    file only shows when a query reaches it: ``diagnose`` then names the file."""
    con = duckdb.connect(database=":memory:")
    con.execute(f"SET threads = {int(threads)}")
    con.execute("SET enable_progress_bar = false")  # it would write to the rule's stderr
    _settings(con, memory_limit, temp_directory, layout)
    for table in (*(tables or tuple(REQUIRED_COLUMNS)), *optional):
        try:
            _open_view(con, folder, table, layout)
        except BaseException:
            con.close()
            raise
    return con


def _open_view(con: duckdb.DuckDBPyConnection, folder: Path, table: str, layout: Layout) -> None:
    """Create the view ``table`` from its file under ``layout``, after checking the file."""
    needed = {**REQUIRED_COLUMNS, **OPTIONAL_COLUMNS}[table]
    if not layout.files.get(table):  # the release has no such table: an empty view
        cols = ", ".join(f'CAST(NULL AS VARCHAR) AS "{c}"' for c in needed)
        con.execute(f'CREATE VIEW "{table}" AS SELECT {cols} LIMIT 0')
        return
    path = find_table(folder, table, layout)
    try:
        con.execute(f'CREATE VIEW "_file_{table}" AS SELECT * FROM {table_reader(path)}')
        cols = {c.upper() for c in
                con.execute(f'SELECT * FROM "_file_{table}" LIMIT 0').df().columns}
        empty = con.execute(f'SELECT 1 FROM "_file_{table}" LIMIT 1').fetchone() is None
    except duckdb.Error as exc:
        raise _unreadable(path, exc, layout) from None
    missing = [c for c in layout.columns.get(table, ()) if c.upper() not in cols]
    if missing:
        raise ContractError(
            f"{path}: missing {layout.name} column(s) {', '.join(missing)} "
            f"(found {', '.join(sorted(cols))})"
        )
    if empty:
        raise ContractError(f"{path}: header only, no rows: every {layout.name} table the "
                            "extraction reads has rows; the file may be cut short")
    select = layout.select.get(table, "*")
    con.execute(f'CREATE VIEW "{table}" AS SELECT {select} FROM "_file_{table}"')


def _settings(con: duckdb.DuckDBPyConnection, memory_limit: str | None,
              temp_directory: str | os.PathLike[str] | None, layout: Layout = MIMIC3) -> None:
    """Apply the config's DuckDB memory limit and temporary folder; ContractError naming the
    config key when DuckDB refuses a value or the folder cannot be made."""
    if memory_limit is not None:
        try:
            con.execute("SET memory_limit = ?", [str(memory_limit)])
        except duckdb.Error as exc:
            con.close()
            first = str(exc).strip().splitlines()[0]
            raise ContractError(f"config key {layout.config_key}.memory_limit: {memory_limit!r} is "
                                f"not a DuckDB memory size such as '4GB' ({first})") from None
    if temp_directory is not None:
        path = Path(temp_directory).expanduser()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            con.close()
            raise ContractError(f"config key {layout.config_key}.temp_directory: cannot create "
                                f"{path} ({exc.strerror})") from None
        con.execute("SET temp_directory = ?", [str(path)])


# ---------------------------------------------------------------- staging

# Tables the extraction scans more than once. ``staged`` copies each once into a Parquet file
# of the columns the extraction reads (REQUIRED_COLUMNS / OPTIONAL_COLUMNS), and for
# CHARTEVENTS and LABEVENTS only the rows of ITEMIDs some query can select (``read_items``),
# then points the view at it: the queries run unchanged on the same values (no cast is
# applied while staging), but the gzip CSV (33 GB of CHARTEVENTS text in full MIMIC-III, of
# which ~ 85 % are items never read) is decompressed and parsed once instead of once per query.
STAGED = ("CHARTEVENTS", "LABEVENTS", "INPUTEVENTS_MV", "INPUTEVENTS_CV", "OUTPUTEVENTS")


# GCS verbal charts that mean "intubated" (scored 0 by AI-Clinician): the one item list written
# in code rather than in a data table; cohort selects them, staging must keep them.
INTUBATED_VERBAL = ((723, "%ET/Trach%"), (223900, "No Response-ETT"))


def read_items() -> dict[str, tuple[int, ...]]:
    """Per item-filtered staged table, every ITEMID an extraction query may select: every
    ``itemid`` of every package data table (items.csv, cultures.csv, heights.csv, ...:
    a data table added later is covered without a change here; items of another table's
    source only make the staged copy a little larger) and the intubated-verbal GCS items,
    the one item list written in the code. A query selecting an ITEMID outside these would
    see no rows for it: items belong in a data table."""
    ids: set[int] = {int(i) for i, _ in INTUBATED_VERBAL}
    folder = resources.files("twinfalsify") / "data" / "mimic3"
    for f in sorted(folder.iterdir(), key=lambda f: f.name):
        if f.name.endswith(".csv"):
            df = data_table(f.name)
            if "itemid" in df.columns:
                ids |= set(pd.to_numeric(df["itemid"], errors="coerce").dropna().astype(int))
    items = tuple(sorted(ids))
    return {"CHARTEVENTS": items, "LABEVENTS": items}


def stage(con: duckdb.DuckDBPyConnection, into: Path) -> dict[str, int]:
    """Copy the ``STAGED`` tables open in ``con`` to Parquet files in ``into`` (needed
    columns; CHARTEVENTS / LABEVENTS: the rows of ``read_items``, and rows whose ITEMID is
    not an integer, so that a bad ITEMID still fails the query that casts it) and point
    their views at the copies. Returns the rows staged per table."""
    open_views = {r[0] for r in con.execute(
        "SELECT view_name FROM duckdb_views() WHERE NOT internal").fetchall()}
    items = read_items()
    needed = {**REQUIRED_COLUMNS, **OPTIONAL_COLUMNS}
    out = {}
    for table in STAGED:
        if table not in open_views:
            continue
        cols = ", ".join(f'"{c}"' for c in needed[table])
        where = "TRUE"
        if table in items:
            ids = ", ".join(map(str, items[table]))
            where = (f"TRY_CAST(ITEMID AS BIGINT) IN ({ids}) "
                     "OR TRY_CAST(ITEMID AS BIGINT) IS NULL")
        lit = "'" + str(into / f"{table}.parquet").replace("'", "''") + "'"
        con.execute(f'COPY (SELECT {cols} FROM "{table}" WHERE {where}) TO {lit} '
                    "(FORMAT parquet, COMPRESSION zstd)")
        con.execute(f'CREATE OR REPLACE VIEW "{table}" AS SELECT * FROM read_parquet({lit})')
        out[table] = con.execute(f'SELECT count(*) FROM "{table}"').fetchone()[0]
    return out


@contextmanager
def staged(con: duckdb.DuckDBPyConnection,
           temp_directory: str | os.PathLike[str] | None = None) -> Iterator[dict[str, int]]:
    """``stage`` into a fresh folder under ``temp_directory`` (default: the system's
    temporary folder), removed on exit; yields the rows staged per table."""
    parent = Path(temp_directory).expanduser() if temp_directory is not None else None
    with tempfile.TemporaryDirectory(prefix="twinfalsify-mimic3-", dir=parent) as d:
        yield stage(con, Path(d))


def diagnose(folder: Path, tables: tuple[str, ...], exc: Exception,
             layout: Layout = MIMIC3) -> ContractError:
    """After a DuckDB error in a query: scan each table in full (only on this failure path)
    and name the first that cannot be read; else name the folder and the error."""
    for table in tables:
        if not layout.files.get(table):
            continue
        path = find_table(folder, table, layout)
        con = duckdb.connect(database=":memory:")
        try:
            con.execute(f"SELECT count(*) FROM {table_reader(path)}").fetchone()
        except duckdb.Error as exc2:
            return _unreadable(path, exc2, layout)
        finally:
            con.close()
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return ContractError(f"{layout.name} tables in {folder}: query failed ({first})")


# ---------------------------------------------------------------- package data tables

def _data_path(name: str) -> Path:
    return Path(str(resources.files("twinfalsify") / "data" / "mimic3" / name))


@cache
def data_table(name: str) -> pd.DataFrame:
    """One of the versioned CSV tables in ``twinfalsify/data/mimic3`` (``#`` lines are comments)."""
    path = _data_path(name)
    if not path.is_file():
        raise ContractError(f"package data table {path} is missing")
    df = pd.read_csv(path, comment="#")
    if "meaning" not in df.columns:
        raise ContractError(f"{path}: every data table needs a 'meaning' column")
    return df


def data_version(name: str) -> str:
    """The version declared in the first comment line of a data table."""
    first = _data_path(name).read_text().splitlines()[0]
    if not first.startswith("# version:"):
        raise ContractError(f"{_data_path(name)}: first line must be '# version: ...'")
    return first.split(":", 1)[1].split(".", 1)[0].strip()
