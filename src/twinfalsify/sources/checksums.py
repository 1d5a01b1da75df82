"""Which MIMIC files the extraction reads, and whether they are PhysioNet's.

A damaged but readable file (a LABEVENTS cut to half its rows) gives a smaller cohort
without an error; a folder holding two files for one table (``LABEVENTS.csv.gz`` and
``labevents.csv``) leaves the choice to a search order. So:

- :func:`table_files`: the one file per table the extraction reads; two files for one
  table is an error naming both;
- :func:`read_fingerprint`: names, sizes and modification times of those files only (no
  content read: a rule parameter, computed at every start), so an unrelated file added to
  the folder reruns nothing, and a changed table reruns the extraction;
- :func:`verify`: the SHA-256 of each file read, against PhysioNet's published checksums,
  once per :func:`read_fingerprint` (cached): one warning naming each file that differs.

Checksums used, in this order: the file given as ``source.mimic3.checksums``; a
``SHA256SUMS*.txt`` inside the MIMIC-III folder (PhysioNet's download has one); PhysioNet's
list for the MIMIC-III Clinical Database Demo v1.4, shipped with the package
(``data/checksums``), used when the folder's PATIENTS table matches the demo's. The list of
the full MIMIC-III v1.4 is not shipped: keep PhysioNet's SHA256SUMS.txt from your download
in the folder or name it in the config. Lists name the files as PhysioNet ships them; a
``.csv.gz`` copy of a listed ``.csv`` is checked by its decompressed content (case of the
name ignored). A Parquet copy cannot be checked (said once). MIMIC-IV (``layout``
``mimic4.MIMIC4``): its files are found in ``hosp/`` and ``icu/``, and only a list in the folder
or in the config applies (PhysioNet's MIMIC-IV SHA256SUMS.txt names ``hosp/patients.csv.gz``
etc.; the file name is what is matched).
"""

from __future__ import annotations

import gzip
import hashlib
import json
import re
from importlib import resources
from pathlib import Path

from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3.tables import (
    MIMIC3,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    Layout,
    candidate_names,
)

DEMO_SUMS = "mimiciii-demo-1.4.sha256"
_LINE = re.compile(r"^([0-9a-fA-F]{64})\s+\*?(\S.*?)\s*$")
_CHUNK = 1 << 20


def table_files(folder: Path, layout: Layout = MIMIC3) -> dict[str, Path]:
    """Table -> the file the extraction reads, for every table present; ContractError naming
    both files when one table has two (which one is meant cannot be guessed)."""
    out: dict[str, Path] = {}
    for table in (*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS):
        found = [folder / n for n in candidate_names(table, layout) if (folder / n).is_file()]
        # a case-insensitive file system lists one file under both cases: same file
        unique = list({p.resolve(): p for p in found}.values())
        if len(unique) > 1:
            raise ContractError(
                f"{layout.name} table {table} has {len(unique)} files in {folder}: "
                f"{' and '.join(str(p.relative_to(folder)) for p in unique)}; keep one")
        if unique:
            out[table] = unique[0]
    return out


def read_fingerprint(folder: Path, layout: Layout = MIMIC3) -> dict[str, str]:
    """The resolved folder and a fingerprint (names, sizes, mtimes) of the files read."""
    folder = Path(folder).resolve()
    h = hashlib.sha256()
    for table, p in sorted(table_files(folder, layout).items()):
        st = p.stat()
        name = p.relative_to(folder).as_posix()
        h.update(f"{table}\t{name}\t{st.st_size}\t{st.st_mtime_ns}\n".encode())
    return {"dir": str(folder), "files": h.hexdigest()[:16]}


def parse_sums(text: str, origin: str) -> dict[str, str]:
    """``sha256  name`` lines (``#`` comments, blank lines skipped) -> {lower-case name: hex}."""
    sums = {}
    for no, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _LINE.match(line)
        if not m:
            raise ContractError(f"{origin}: line {no} is not 'SHA256  file name': {line[:60]!r}")
        sums[Path(m.group(2)).name.lower()] = m.group(1).lower()
    return sums


def _sha256(path: Path, decompress: bool) -> str:
    h = hashlib.sha256()
    opener = gzip.open if decompress else open
    with opener(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def file_sha256(path: Path, sums: dict[str, str]) -> tuple[str | None, str | None]:
    """(published, actual) SHA-256 of ``path`` under ``sums``' name for it, or (None, None)
    when the list names no form of it (``X.csv.gz`` listed: its bytes; ``X.csv`` listed and
    the file is ``X.csv.gz``: its decompressed content)."""
    name = path.name.lower()
    if name in sums:
        return sums[name], _sha256(path, decompress=False)
    if name.endswith(".csv.gz") and name.removesuffix(".gz") in sums:
        try:
            return sums[name.removesuffix(".gz")], _sha256(path, decompress=True)
        except (OSError, EOFError) as exc:  # not gzip, or cut short
            return sums[name.removesuffix(".gz")], f"unreadable ({exc})"
    return None, None


def choose_sums(folder: Path, configured: str | None, files: dict[str, Path],
                layout: Layout = MIMIC3) -> tuple[dict[str, str], str]:
    """(checksums, where they come from) for ``folder`` (see the module doc); ({}, why) when
    none applies."""
    if configured:
        path = Path(configured).expanduser()
        if not path.is_file():
            raise ContractError(f"{layout.config_key}.checksums: {path} does not exist")
        return parse_sums(path.read_text(), str(path)), str(path)
    inside = sorted(folder.glob("SHA256SUMS*.txt"))
    if inside:
        return parse_sums(inside[0].read_text(), str(inside[0])), str(inside[0])
    if layout is not MIMIC3:
        return {}, (f"no published checksums for this folder (keep PhysioNet's "
                    f"SHA256SUMS.txt of your {layout.name} download in the folder or name it "
                    f"as {layout.config_key}.checksums)")
    shipped = resources.files("twinfalsify") / "data" / "checksums" / DEMO_SUMS
    demo = parse_sums(shipped.read_text(), DEMO_SUMS)
    patients = files.get("PATIENTS")
    if patients is not None:
        published, actual = file_sha256(patients, demo)
        if published is not None and published == actual:
            return demo, f"PhysioNet's list for the MIMIC-III demo v1.4 ({DEMO_SUMS})"
    return {}, ("no published checksums for this folder (full MIMIC-III v1.4: keep "
                "PhysioNet's SHA256SUMS.txt in the folder or name it as "
                "source.mimic3.checksums)")


def verify(folder: Path, configured: str | None = None,
           cache: Path | None = None, layout: Layout = MIMIC3) -> list[str]:
    """Warnings (one line each) for the files the extraction reads that differ from the
    published checksums, or cannot be checked; [] when every file read matches.

    ``cache``: a JSON file remembering the answer for one :func:`read_fingerprint` (and
    checksum source), so the hashing (minutes for the full database) happens once.
    """
    folder = Path(folder)
    files = table_files(folder, layout)
    key = json.dumps({"data": read_fingerprint(folder, layout), "sums": configured},
                     sort_keys=True)
    if cache is not None and cache.is_file():
        try:
            saved = json.loads(cache.read_text())
            if saved.get("key") == key:
                return list(saved["warnings"])
        except (json.JSONDecodeError, KeyError, TypeError):
            pass
    sums, origin = choose_sums(folder, configured, files, layout)
    warnings = []
    if not sums:
        warnings.append(f"{layout.name} files not verified: {origin}")
    else:
        unlisted = []
        for _, path in sorted(files.items()):
            published, actual = file_sha256(path, sums)
            if published is None:
                unlisted.append(path.name)
            elif published != actual:
                warnings.append(
                    f"{layout.name} file {path} differs from the published checksum ({origin}): "
                    f"SHA-256 {actual[:16]}... instead of {published[:16]}...; a damaged or "
                    "edited table changes the cohort without an error")
        if unlisted:
            warnings.append(f"{layout.name} files not in the checksum list ({origin}), not "
                            f"verified: {', '.join(unlisted)}")
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps({"key": key, "warnings": warnings}, indent=1) + "\n")
    return warnings
