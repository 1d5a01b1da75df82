"""MIMIC-III files the extraction reads: one per table, checked against PhysioNet's checksums.

The shipped list of the demo v1.4 is PhysioNet's own: every table the extraction reads from
the open demo matches it except CHARTEVENTS, which the demo copy in use rebuilt (its
README says so); a LABEVENTS cut short, or edited, is named; two files for one table are
an error naming both; an unrelated file in the folder changes no fingerprint.
"""

from __future__ import annotations

import gzip
import hashlib
import shutil
from pathlib import Path

import pytest
from helpers.paths import ROOT, shared_dir

from twinfalsify.schema import ContractError
from twinfalsify.sources import checksums

DEMO = (shared_dir() or ROOT.parent / "shared") / "data" \
    / "mimic-iii-demo"
needs_demo = pytest.mark.skipif(not (DEMO / "PATIENTS.csv.gz").is_file(),
                                reason=f"MIMIC-III demo not present at {DEMO}")


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _folder(tmp_path: Path, tables: dict[str, bytes]) -> Path:
    folder = tmp_path / "mimic"
    folder.mkdir()
    for name, data in tables.items():
        (folder / name).write_bytes(data)
    return folder


def test_two_files_for_one_table_is_an_error_naming_both(tmp_path):
    folder = _folder(tmp_path, {"LABEVENTS.csv.gz": gzip.compress(b"a\n1\n"),
                                "labevents.csv": b"a\n1\n", "PATIENTS.csv": b"p\n"})
    with pytest.raises(ContractError, match="table LABEVENTS has 2 files .*: LABEVENTS.csv.gz "
                                            "and labevents.csv; keep one"):
        checksums.table_files(folder)


def test_gz_copy_of_a_listed_csv_is_checked_by_its_content(tmp_path):
    good, cut = b"row_id,x\n1,2\n3,4\n", b"row_id,x\n1,2\n"
    folder = _folder(tmp_path, {"PATIENTS.csv.gz": gzip.compress(good),
                                "LABEVENTS.csv.gz": gzip.compress(cut),
                                "ICUSTAYS.csv": b"i\n", "NOTES.txt": b"mine"})
    sums = tmp_path / "SHA256SUMS.txt"
    sums.write_text(f"{_sha(good)}  PATIENTS.csv\n{_sha(good)} labevents.csv\n")
    warnings = checksums.verify(folder, str(sums))
    assert len(warnings) == 2, warnings
    assert "LABEVENTS.csv.gz differs from the published checksum" in warnings[0]
    assert "not in the checksum list" in warnings[1] and "ICUSTAYS.csv" in warnings[1]
    assert not any("PATIENTS" in w for w in warnings)


def test_verification_is_cached_by_the_fingerprint_of_the_files_read(tmp_path, monkeypatch):
    folder = _folder(tmp_path, {"PATIENTS.csv": b"p\n1\n"})
    sums = tmp_path / "sums.txt"
    sums.write_text(f"{_sha(b'p' + bytes(1))}  PATIENTS.csv\n")
    cache = tmp_path / "cache.json"
    first = checksums.verify(folder, str(sums), cache)
    assert len(first) == 1 and "differs" in first[0]
    calls = []
    monkeypatch.setattr(checksums, "_sha256", lambda *a, **k: calls.append(a) or "x")
    assert checksums.verify(folder, str(sums), cache) == first and not calls  # cached
    (folder / "README.txt").write_text("an unrelated file")
    assert checksums.verify(folder, str(sums), cache) == first and not calls
    (folder / "PATIENTS.csv").write_bytes(b"p\n1\n2\n")  # the table changed: hashed again
    checksums.verify(folder, str(sums), cache)
    assert calls


def test_unrelated_file_leaves_the_data_fingerprint_alone(tmp_path):
    folder = _folder(tmp_path, {"PATIENTS.csv": b"p\n", "ICUSTAYS.csv": b"i\n"})
    before = checksums.read_fingerprint(folder)
    (folder / "notes.txt").write_text("x")
    (folder / "D_ITEMS.csv").write_text("not read by the extraction")
    assert checksums.read_fingerprint(folder) == before
    (folder / "ICUSTAYS.csv").write_text("i\n2\n")
    assert checksums.read_fingerprint(folder) != before


def test_no_list_for_the_folder_says_so(tmp_path):
    folder = _folder(tmp_path, {"PATIENTS.csv": b"not the demo\n"})
    (warning,) = checksums.verify(folder)
    assert warning.startswith("MIMIC-III files not verified: no published checksums") \
        and "source.mimic3.checksums" in warning
    with pytest.raises(ContractError, match="source.mimic3.checksums: .* does not exist"):
        checksums.verify(folder, str(tmp_path / "missing.txt"))


@needs_demo
def test_the_demo_matches_physionets_list_except_its_rebuilt_chartevents(tmp_path):
    warnings = checksums.verify(DEMO)
    assert len(warnings) == 1, warnings
    assert "CHARTEVENTS.csv.gz differs from the published checksum" in warnings[0]


@needs_demo
def test_a_labevents_cut_to_half_its_rows_is_named_with_the_shipped_list(tmp_path):
    folder = tmp_path / "demo"
    folder.mkdir()
    for f in DEMO.glob("*.csv.gz"):  # no SHA256SUMS*.txt: the shipped demo list applies
        shutil.copyfile(f, folder / f.name)
    lab = folder / "LABEVENTS.csv.gz"
    lines = gzip.decompress(lab.read_bytes()).splitlines(keepends=True)
    lab.write_bytes(gzip.compress(b"".join(lines[: len(lines) // 2])))
    warnings = checksums.verify(folder)
    assert all("MIMIC-III demo v1.4" in w for w in warnings), warnings
    named = [w for w in warnings if "differs" in w]
    assert {Path(w.split()[2]).name for w in named} == {"CHARTEVENTS.csv.gz",
                                                         "LABEVENTS.csv.gz"}
