"""Damaged MIMIC-III files: one line naming the file, a non-zero exit, no traceback.

Cases: a truncated .csv.gz (damage in the first block, and deep in a large file), an empty
.csv.gz, a header-only table, garbage after the gzip stream."""

from __future__ import annotations

import gzip
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.paths import FIXTURES, ROOT

from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3 import cohort, extract_mimic3
from twinfalsify.sources.mimic3.tables import REQUIRED_COLUMNS, diagnose

FIX = FIXTURES / "mimic3"


def _copy(tmp: Path) -> Path:
    for f in FIX.glob("*.csv"):
        shutil.copy(f, tmp / f.name)
    return tmp


def _gz(path: Path, extra: bytes = b"", cut: float | None = None) -> Path:
    """path (CSV) -> path.gz: optionally cut to a fraction of its bytes or with bytes
    appended after the gzip stream; the CSV is removed so the .gz is the table read."""
    out = path.with_name(path.name + ".gz")
    with open(path, "rb") as src, gzip.open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    data = out.read_bytes()
    if cut is not None:
        data = data[: int(len(data) * cut)]
    out.write_bytes(data + extra)
    path.unlink()
    return out


def _big(path: Path, copies: int) -> None:
    """Repeat the data rows of a CSV ``copies`` times (a file larger than DuckDB's first
    read, so damage at its end only shows when a query scans that far)."""
    lines = path.read_text().splitlines(keepends=True)
    path.write_text(lines[0] + "".join(lines[1:]) * copies)


def _truncated_small(d):
    return _gz(d / "CHARTEVENTS.csv", cut=0.5)


def _truncated_large(d):
    _big(d / "CHARTEVENTS.csv", 400)
    return _gz(d / "CHARTEVENTS.csv", cut=0.97)


def _empty_gz(d):
    out = d / "LABEVENTS.csv.gz"
    out.write_bytes(b"")
    (d / "LABEVENTS.csv").unlink()
    return out


def _header_only(d):
    p = d / "ICUSTAYS.csv"
    p.write_text(p.read_text().splitlines()[0] + "\n")
    return p


def _garbage_after_gzip(d):
    return _gz(d / "PRESCRIPTIONS.csv", extra=b"\x00garbage after the gzip stream\n" * 50)


CASES = {"truncated": _truncated_small, "truncated_large": _truncated_large,
         "empty_gz": _empty_gz, "header_only": _header_only, "garbage": _garbage_after_gzip}


@pytest.mark.parametrize("case", list(CASES))
def test_damaged_table_named_in_one_line(tmp_path, case):
    bad = CASES[case](_copy(tmp_path))
    with pytest.raises(ContractError) as e:
        extract_mimic3(tmp_path)
    msg = str(e.value)
    assert str(bad) in msg and "\n" not in msg


def test_error_deep_in_a_file_is_traced_to_the_file(tmp_path, monkeypatch):
    """Damage beyond what the open-time check reads surfaces as a DuckDB error inside a
    query; the extraction then scans each table and names the damaged one."""
    import duckdb

    bad = _truncated_small(_copy(tmp_path))
    msg = str(diagnose(tmp_path, tuple(REQUIRED_COLUMNS), duckdb.IOException("boom")))
    assert str(bad) in msg and "\n" not in msg

    def fail(*a, **k):
        raise duckdb.IOException("IO Error: Unexpected end of GZIP stream")

    good = _copy(tmp_path / "good") if (tmp_path / "good").mkdir() is None else None
    monkeypatch.setattr(cohort, "_extract", fail)
    with pytest.raises(ContractError, match=r"MIMIC-III tables in .*good: query failed"):
        extract_mimic3(good)


def test_cli_exits_nonzero_with_one_line(tmp_path):
    bad = _header_only(_copy(tmp_path))
    r = subprocess.run([sys.executable, "-m", "twinfalsify.sources.mimic3", str(tmp_path),
                        str(tmp_path / "out")], capture_output=True, text=True,
                       env={"PYTHONPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "Traceback" not in r.stderr
