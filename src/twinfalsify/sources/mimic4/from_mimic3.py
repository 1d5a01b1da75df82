"""MIMIC-IV-layout tables made from MIMIC-III's MetaVision stays, to check the mimic4 source.

No MIMIC-IV with chart events is open, but MIMIC-IV's ICU tables are MIMIC-III's MetaVision
tables under other names. :func:`write_pair` reads a MIMIC-III folder (e.g. the open demo)
and writes, from the same rows, two folders:

- ``mimic3/``: the MIMIC-III tables of the patients with a MetaVision ICU stay, as they are;
- ``mimic4/``: the same rows in MIMIC-IV's layout (``hosp/``, ``icu/``, lower-case names,
  ``stay_id``, MIMIC-IV's column names; only the columns MIMIC-III has a source for).

Rows kept in both: ``ICUSTAYS`` of DBSOURCE ``metavision``; their patients' ``PATIENTS``,
``ADMISSIONS``, ``LABEVENTS``, ``PRESCRIPTIONS`` and ``MICROBIOLOGYEVENTS`` rows; the
``CHARTEVENTS``, ``INPUTEVENTS_MV`` and ``OUTPUTEVENTS`` rows of those stays. Each change
MIMIC-IV makes that the extraction reads (``mimic4.DIFFERENCES``), and what the transform
does about it:

- ``patients``: no DOB; ``anchor_year`` = the year of the patient's first admission,
  ``anchor_age`` = anchor_year - year(DOB), 91 for MIMIC-III's shifted ages (over 89);
- ``prescriptions.starttime`` = STARTDATE (a date at 00:00, as MIMIC-III has no time), no
  ICU stay id;
- ``chartevents``: no ERROR column, so MIMIC-III's rows with ERROR = 1 are left out of both
  folders (the MIMIC-III extraction drops them too);
- ``inputevents`` = INPUTEVENTS_MV; INPUTEVENTS_CV (CareVue) has no MIMIC-IV table: the
  ``mimic3/`` copy keeps it whole (its rows belong to CareVue stays, not copied, so no query
  joins them to a kept stay; MIMIC-III's reader needs the table).

Run: ``python -m twinfalsify.sources.mimic4.from_mimic3 MIMIC3_DIR OUT``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import duckdb

from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3.tables import find_table, resolve_mimic3_dir, table_reader

# MIMIC-III table -> (MIMIC-IV path, MIMIC-IV column <- MIMIC-III expression (lower-case
# names: DuckDB matches them without case), rows kept: "stay" | "subject" | "all")
TABLES: dict[str, tuple[str | None, dict[str, str], str]] = {
    "PATIENTS": ("hosp/patients", {
        "subject_id": "subject_id", "gender": "gender",
        "anchor_age": "CASE WHEN age_first > 150 OR anchor_year - birth_year > 89 "
                      "THEN '91' ELSE CAST(anchor_year - birth_year AS VARCHAR) END",
        "anchor_year": "CAST(anchor_year AS VARCHAR)", "dod": "dod"}, "subject"),
    "ADMISSIONS": ("hosp/admissions", {c: c for c in (
        "subject_id", "hadm_id", "admittime", "dischtime", "deathtime", "admission_type",
        "admission_location", "discharge_location", "insurance", "language",
        "marital_status")} | {"race": "ethnicity", "edregtime": "edregtime",
                              "edouttime": "edouttime",
                              "hospital_expire_flag": "hospital_expire_flag"}, "subject"),
    "ICUSTAYS": ("icu/icustays", {
        "subject_id": "subject_id", "hadm_id": "hadm_id", "stay_id": "icustay_id",
        "first_careunit": "first_careunit", "last_careunit": "last_careunit",
        "intime": "intime", "outtime": "outtime", "los": "los"}, "stay"),
    "CHARTEVENTS": ("icu/chartevents", {
        "subject_id": "subject_id", "hadm_id": "hadm_id", "stay_id": "icustay_id",
        "caregiver_id": "cgid", "charttime": "charttime", "storetime": "storetime",
        "itemid": "itemid", "value": "value", "valuenum": "valuenum",
        "valueuom": "valueuom", "warning": "warning"}, "stay"),
    "LABEVENTS": ("hosp/labevents", {
        "labevent_id": "row_id", "subject_id": "subject_id", "hadm_id": "hadm_id",
        "itemid": "itemid", "charttime": "charttime", "value": "value",
        "valuenum": "valuenum", "valueuom": "valueuom", "flag": "flag"}, "subject"),
    "PRESCRIPTIONS": ("hosp/prescriptions", {
        "subject_id": "subject_id", "hadm_id": "hadm_id", "starttime": "startdate",
        "stoptime": "enddate", "drug_type": "drug_type", "drug": "drug",
        "formulary_drug_cd": "formulary_drug_cd", "gsn": "gsn", "ndc": "ndc",
        "prod_strength": "prod_strength", "dose_val_rx": "dose_val_rx",
        "dose_unit_rx": "dose_unit_rx", "form_val_disp": "form_val_disp",
        "form_unit_disp": "form_unit_disp", "route": "route"}, "subject"),
    "MICROBIOLOGYEVENTS": ("hosp/microbiologyevents", {c: c for c in (
        "subject_id", "hadm_id", "chartdate", "charttime", "spec_itemid", "spec_type_desc",
        "org_itemid", "org_name", "ab_itemid", "ab_name", "dilution_text",
        "dilution_comparison", "dilution_value", "interpretation")}
        | {"test_name": "CAST(NULL AS VARCHAR)"}, "subject"),
    "INPUTEVENTS_MV": ("icu/inputevents", {c: c for c in (
        "subject_id", "hadm_id")} | {"stay_id": "icustay_id", "caregiver_id": "cgid"} | {
        c: c for c in (
            "starttime", "endtime", "storetime", "itemid", "amount", "amountuom", "rate",
            "rateuom", "orderid", "linkorderid", "ordercategoryname",
            "secondaryordercategoryname", "ordercomponenttypedescription",
            "ordercategorydescription", "patientweight", "totalamount", "totalamountuom",
            "isopenbag", "continueinnextdept", "statusdescription", "originalamount",
            "originalrate")}, "stay"),
    "OUTPUTEVENTS": ("icu/outputevents", {
        "subject_id": "subject_id", "hadm_id": "hadm_id", "stay_id": "icustay_id",
        "caregiver_id": "cgid", "charttime": "charttime", "storetime": "storetime",
        "itemid": "itemid", "value": "value", "valueuom": "valueuom"}, "stay"),
    "INPUTEVENTS_CV": (None, {}, "all"),
}


def _copy(con: duckdb.DuckDBPyConnection, select: str, path: Path) -> int:
    path.parent.mkdir(parents=True, exist_ok=True)
    lit = "'" + str(path).replace("'", "''") + "'"
    return int(con.execute(f"COPY ({select}) TO {lit} (FORMAT csv, HEADER, "
                           "COMPRESSION gzip)").fetchone()[0])


def write_pair(src: Path, out: Path, dbsource: str = "metavision") -> dict[str, int]:
    """Write ``out/mimic3`` and ``out/mimic4`` from the MIMIC-III folder ``src`` (see the
    module doc); returns the rows written per MIMIC-III table (the same in both folders)."""
    src, out = Path(src), Path(out)
    con = duckdb.connect(database=":memory:")
    try:
        for table in TABLES:
            path = find_table(src, table)
            con.execute(f'CREATE VIEW "src_{table}" AS SELECT * FROM {table_reader(path)}')
        con.execute(f"""CREATE TABLE kept_stays AS SELECT DISTINCT
            TRY_CAST(icustay_id AS BIGINT) AS id FROM "src_ICUSTAYS"
            WHERE lower(dbsource) = '{dbsource}'""")
        con.execute("""CREATE TABLE kept_subjects AS SELECT DISTINCT
            TRY_CAST(subject_id AS BIGINT) AS id FROM "src_ICUSTAYS"
            WHERE TRY_CAST(icustay_id AS BIGINT) IN (SELECT id FROM kept_stays)""")
        if con.execute("SELECT count(*) FROM kept_stays").fetchone()[0] == 0:
            raise ContractError(f"{find_table(src, 'ICUSTAYS')}: no ICU stay with DBSOURCE "
                                f"{dbsource!r}")
        # patients' anchor year: the year of their first admission
        con.execute("""CREATE TABLE anchors AS SELECT TRY_CAST(a.subject_id AS BIGINT) AS sid,
            min(year(TRY_CAST(a.admittime AS TIMESTAMP))) AS anchor_year,
            min(year(TRY_CAST(p.dob AS TIMESTAMP))) AS birth_year,
            min(date_diff('day', TRY_CAST(p.dob AS TIMESTAMP),
                          TRY_CAST(a.admittime AS TIMESTAMP))) / 365.25 AS age_first
            FROM "src_ADMISSIONS" a JOIN "src_PATIENTS" p
              ON TRY_CAST(a.subject_id AS BIGINT) = TRY_CAST(p.subject_id AS BIGINT)
            GROUP BY 1""")
        rows = {}
        for table, (iv_path, cols, keep) in TABLES.items():
            where = {"stay": "TRY_CAST(icustay_id AS BIGINT) IN (SELECT id FROM kept_stays)",
                     "subject": "TRY_CAST(subject_id AS BIGINT) IN "
                                "(SELECT id FROM kept_subjects)",
                     "all": "TRUE"}[keep]
            if table == "CHARTEVENTS":  # MIMIC-IV has no error flag (module doc)
                where += " AND coalesce(TRY_CAST(error AS INTEGER), 0) = 0"
            frm = f'"src_{table}"'
            if table == "PATIENTS":
                frm += (" LEFT JOIN anchors ON TRY_CAST(subject_id AS BIGINT) = anchors.sid")
            n3 = _copy(con, f"SELECT \"src_{table}\".* FROM {frm} WHERE {where}",
                       out / "mimic3" / f"{table}.csv.gz")
            if iv_path is not None:
                sel = ", ".join(f'{expr} AS "{col}"' for col, expr in cols.items())
                n4 = _copy(con, f"SELECT {sel} FROM {frm} WHERE {where}",
                           out / "mimic4" / f"{iv_path}.csv.gz")
                assert n3 == n4, (table, n3, n4)
            rows[table] = n3
    finally:
        con.close()
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mimic3_dir", help="a MIMIC-III v1.4 folder (e.g. the open demo)")
    p.add_argument("out", help="folder to write mimic3/ and mimic4/ into")
    a = p.parse_args(argv)
    try:
        rows = write_pair(resolve_mimic3_dir(a.mimic3_dir), Path(a.out))
    except ContractError as exc:
        raise SystemExit(f"ERROR: {exc}") from None
    for table, n in rows.items():
        print(f"{table}: {n} rows")


if __name__ == "__main__":
    main()
