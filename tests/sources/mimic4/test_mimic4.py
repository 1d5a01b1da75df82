"""The mimic4 source: MIMIC-IV's table layout read by the MIMIC-III cohort code.

MIMIC-IV with chart events is credentialed, so these tests make MIMIC-IV-layout tables from
MIMIC-III MetaVision stays (``sources.mimic4.from_mimic3``: the hand-made fixture always,
the open demo when the shared data is present) and check that ``mimic4`` on them gives the
cohort, the hourly values and the audit table ``mimic3`` gives on the same rows; the only
difference allowed is the one the schema forces on these rows: age, known to the year.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers.paths import FIXTURES, shared_dir
from helpers.workflow import mimic_study_config, run_snakemake

from twinfalsify import schema
from twinfalsify.provenance import code_scope
from twinfalsify.schema import ContractError
from twinfalsify.sources.checksums import read_fingerprint, table_files, verify
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.cohort import _stays
from twinfalsify.sources.mimic3.options import options_from_config
from twinfalsify.sources.mimic3.tables import OPTIONAL_COLUMNS, REQUIRED_COLUMNS, connect
from twinfalsify.sources.mimic4 import DIFFERENCES, MIMIC4, extract_mimic4, resolve_mimic4_dir
from twinfalsify.sources.mimic4.from_mimic3 import write_pair

FIX = FIXTURES / "mimic3-patients"
CAREVUE = {300008, 300009}  # the fixture's CareVue stays (its README)


def _demo() -> Path | None:
    d = shared_dir()
    demo = d / "data" / "mimic-iii-demo" if d else None
    return demo if demo is not None and (demo / "ICUSTAYS.csv.gz").is_file() else None


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("mimic4-fixture")
    write_pair(FIX, out)
    return out


def _csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, dtype=str, keep_default_na=False)


def test_the_layout_covers_every_table_the_extraction_reads():
    assert set(MIMIC4.files) == {*REQUIRED_COLUMNS, *OPTIONAL_COLUMNS}
    assert MIMIC4.files["INPUTEVENTS_CV"] == ()  # no CareVue in MIMIC-IV
    for view, stems in MIMIC4.files.items():
        for stem in stems:
            assert stem == stem.lower()
        if stems:
            assert stems[0].split("/")[0] in ("hosp", "icu"), view
            # every column a view reads is a MIMIC-IV column name (lower case)
            assert all(c == c.lower() for c in MIMIC4.columns[view])
    assert "stay_id" in MIMIC4.columns["ICUSTAYS"]
    assert "dob" not in MIMIC4.columns["PATIENTS"]
    assert {"anchor_age", "anchor_year"} <= set(MIMIC4.columns["PATIENTS"])
    assert "starttime" in MIMIC4.columns["PRESCRIPTIONS"]
    assert {k for k, _ in DIFFERENCES} >= {"layout", "age", "CareVue"}


def test_transform_writes_the_mimic4_layout_from_the_same_rows(pair):
    iv, iii = pair / "mimic4", pair / "mimic3"
    assert sorted(p.relative_to(iv).as_posix() for p in iv.rglob("*.csv.gz")) == sorted(
        f"{stems[0]}.csv.gz" for stems in MIMIC4.files.values() if stems)
    stays = _csv(iv / "icu" / "icustays.csv.gz")
    assert "stay_id" in stays and "icustay_id" not in stays and "dbsource" not in stays
    assert not CAREVUE & set(stays["stay_id"].astype(int))
    assert set(stays["stay_id"].astype(int)) == set(_csv(iii / "ICUSTAYS.csv.gz")["ICUSTAY_ID"]
                                                    .astype(int))
    pat = _csv(iv / "hosp" / "patients.csv.gz")
    assert "dob" not in pat and {"anchor_age", "anchor_year"} <= set(pat)
    rx = _csv(iv / "hosp" / "prescriptions.csv.gz")
    assert "starttime" in rx and "icustay_id" not in rx and "stay_id" not in rx
    for table, stems in MIMIC4.files.items():
        if not stems:
            continue
        a, b = _csv(iii / f"{table}.csv.gz"), _csv(iv / f"{stems[0]}.csv.gz")
        assert len(a) == len(b) > 0, table
        assert all(c == c.lower() for c in b.columns), table


def test_anchor_age_is_the_year_difference(pair):
    pat = _csv(pair / "mimic4" / "hosp" / "patients.csv.gz").set_index("subject_id")
    src = _csv(FIX / "PATIENTS.csv").set_index("SUBJECT_ID")
    adm = _csv(FIX / "ADMISSIONS.csv")
    first = adm.groupby("SUBJECT_ID")["ADMITTIME"].min().str[:4].astype(int)
    for sid, row in pat.iterrows():
        assert int(row["anchor_year"]) == first[sid]
        assert int(row["anchor_age"]) == first[sid] - int(src.loc[sid, "DOB"][:4])


def _compare(a, b) -> dict:
    """Assert ``mimic4`` result ``b`` equals ``mimic3`` result ``a`` except for age (known to
    the year in MIMIC-IV); return the largest age difference and the cohort size."""
    pd.testing.assert_frame_equal(a.consort, b.consort)
    ta, tb = a.trajectories, b.trajectories
    cols = [c for c in ta.columns if c != "age"]
    pd.testing.assert_frame_equal(ta[cols], tb[cols])
    age_diff = (ta["age"] - tb["age"]).abs()
    assert (age_diff < 1).all()
    pd.testing.assert_frame_equal(a.anchors, b.anchors)
    pd.testing.assert_frame_equal(a.missingness, b.missingness)
    pd.testing.assert_frame_equal(a.imputed, b.imputed)
    sa, sb = a.stays.drop(columns="age"), b.stays.drop(columns="age")
    pd.testing.assert_frame_equal(sa, sb)
    assert ((a.stays["age"] - b.stays["age"]).abs() < 1).all()
    return {"max_age_diff": float(age_diff.max()) if len(age_diff) else 0.0,
            "n": int(ta[schema.STAY_ID].nunique())}


@pytest.mark.parametrize("variant,anchor", [("project", "first_vitals"),
                                            ("ai_clinician", "first_vitals"),
                                            ("project", "intime")])
def test_mimic4_gives_the_mimic3_cohort_on_the_same_stays(pair, variant, anchor):
    opts = options_from_config({"cohort_variant": variant})
    a = extract_mimic3(pair / "mimic3", anchor=anchor, options=opts)
    b = extract_mimic4(pair / "mimic4", anchor=anchor, options=opts)
    got = _compare(a, b)
    assert got["n"] >= 8  # the fixture's MetaVision stays that make the cohort
    assert (b.stays["dbsource"] == "metavision").all()


def test_mimic4_unstaged_equals_staged(pair):
    a = extract_mimic4(pair / "mimic4", stage=True)
    b = extract_mimic4(pair / "mimic4", stage=False)
    pd.testing.assert_frame_equal(a.trajectories, b.trajectories)


@pytest.mark.skipif(_demo() is None, reason="shared MIMIC-III demo not found "
                    "(TWINFALSIFY_SHARED or ../shared/data/mimic-iii-demo)")
def test_mimic4_gives_the_mimic3_cohort_on_the_demo_metavision_stays(tmp_path):
    rows = write_pair(_demo(), tmp_path)
    assert rows["ICUSTAYS"] == 77  # the demo's MetaVision stays
    out = {}
    for variant in ("project", "ai_clinician"):
        opts = options_from_config({"cohort_variant": variant})
        a = extract_mimic3(tmp_path / "mimic3", options=opts, threads=2)
        b = extract_mimic4(tmp_path / "mimic4", options=opts, threads=2)
        out[variant] = _compare(a, b)
    assert out["project"]["n"] > 30
    print(json.dumps(out))


def test_age_from_anchor_age_and_year(pair, tmp_path):
    iv = tmp_path / "iv"
    shutil.copytree(pair / "mimic4", iv)
    stays = _csv(iv / "icu" / "icustays.csv.gz")
    pat = _csv(iv / "hosp" / "patients.csv.gz")
    s1 = stays.iloc[0]
    sid = s1["subject_id"]
    year = int(s1["intime"][:4])
    pat.loc[pat["subject_id"] == sid, ["anchor_age", "anchor_year"]] = ["60", str(year - 3)]
    other = pat["subject_id"] != sid
    pat.loc[other, ["anchor_age", "anchor_year"]] = ["91", str(year)]
    with gzip.open(iv / "hosp" / "patients.csv.gz", "wt") as fh:
        pat.to_csv(fh, index=False)
    con = connect(iv, layout=MIMIC4)
    try:
        st = _stays(con, MIMIC4)
    finally:
        con.close()
    ages = st.set_index("subject_id")["age"]
    assert np.allclose(ages.loc[[int(sid)]], 63.0)  # 60 + 3 years after the anchor year
    assert np.allclose(ages.drop(int(sid)), 91.4)  # MIMIC-IV's "over 89" (91) as MIMIC-III's


def test_missing_module_folder_names_what_was_tried(pair, tmp_path):
    iv = tmp_path / "iv"
    shutil.copytree(pair / "mimic4", iv)
    shutil.rmtree(iv / "icu")
    with pytest.raises(ContractError, match=r"MIMIC-IV table ICUSTAYS not found in .*tried "
                                            r"icu/icustays\.csv\.gz"):
        extract_mimic4(iv)


def test_missing_stay_id_column_is_named(pair, tmp_path):
    iv = tmp_path / "iv"
    shutil.copytree(pair / "mimic4", iv)
    stays = _csv(iv / "icu" / "icustays.csv.gz").rename(columns={"stay_id": "icustay_id"})
    with gzip.open(iv / "icu" / "icustays.csv.gz", "wt") as fh:
        stays.to_csv(fh, index=False)
    with pytest.raises(ContractError, match=r"icustays\.csv\.gz: missing MIMIC-IV column\(s\) "
                                            r"stay_id"):
        extract_mimic4(iv)


def test_a_mimic3_folder_is_not_taken_for_mimic4(pair):
    with pytest.raises(ContractError, match="MIMIC-IV table"):
        extract_mimic4(pair / "mimic3")


def test_folder_from_config_or_environment(pair, tmp_path, monkeypatch):
    monkeypatch.delenv("TWINFALSIFY_MIMIC4_DIR", raising=False)
    assert resolve_mimic4_dir(str(pair / "mimic4")) == pair / "mimic4"
    monkeypatch.setenv("TWINFALSIFY_MIMIC4_DIR", str(tmp_path))
    assert resolve_mimic4_dir("/elsewhere") == tmp_path
    monkeypatch.setenv("TWINFALSIFY_MIMIC4_DIR", str(tmp_path / "none"))
    with pytest.raises(ContractError, match="TWINFALSIFY_MIMIC4_DIR.*hosp/patients"):
        resolve_mimic4_dir(None)


def test_checksums_of_a_mimic4_download(pair, tmp_path):
    iv = tmp_path / "iv"
    shutil.copytree(pair / "mimic4", iv)
    files = table_files(iv, MIMIC4)
    assert set(files) == {t for t, s in MIMIC4.files.items() if s}
    assert verify(iv, layout=MIMIC4) == [
        "MIMIC-IV files not verified: no published checksums for this folder (keep "
        "PhysioNet's SHA256SUMS.txt of your MIMIC-IV download in the folder or name it as "
        "source.mimic4.checksums)"]
    # PhysioNet's list names the files with their module folder
    lines = [f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(iv).as_posix()}"
             for p in files.values()]
    (iv / "SHA256SUMS.txt").write_text("\n".join(lines) + "\n")
    assert verify(iv, layout=MIMIC4) == []
    before = read_fingerprint(iv, MIMIC4)
    with gzip.open(files["LABEVENTS"], "ab") as fh:
        fh.write(b"")  # same content, new bytes: a changed file
    (iv / "notes.txt").write_text("unrelated")
    assert read_fingerprint(iv, MIMIC4) != before
    warnings = verify(iv, layout=MIMIC4)
    assert len(warnings) == 1 and "labevents.csv.gz differs" in warnings[0]


def test_a_mimic4_study_counts_the_mimic3_cohort_code_as_its_own():
    _, leave = code_scope({"source": {"kind": "mimic4"}, "testing": {"methods": {}}})
    assert "twinfalsify.sources.mimic3" not in leave
    assert "twinfalsify.sources.mimic4" not in leave
    _, leave3 = code_scope({"source": {"kind": "mimic3"}, "testing": {"methods": {}}})
    assert "twinfalsify.sources.mimic4" in leave3
    assert "twinfalsify.sources.mimic3" not in leave3
    _, leave_syn = code_scope({"source": {"kind": "synthetic"}, "testing": {"methods": {}}})
    assert {"twinfalsify.sources.mimic3", "twinfalsify.sources.mimic4"} <= set(leave_syn)


@pytest.mark.slow
def test_a_mimic4_study_extracts_through_the_workflow(pair, tmp_path):
    cfg = mimic_study_config("m4", "mimic4", str(pair / "mimic4"))
    config = tmp_path / "m4.yaml"
    config.write_text(yaml.safe_dump(cfg))
    target = "results/m4/trajectories.parquet"
    run = run_snakemake(tmp_path, config, "--cores", "1", target)
    assert run.returncode == 0, run.stderr[-3000:]
    got = pd.read_parquet(tmp_path / target)
    want = extract_mimic3(pair / "mimic3").trajectories
    cols = [c for c in want.columns if c != "age"]
    pd.testing.assert_frame_equal(got[cols].reset_index(drop=True),
                                  want[cols].rename_axis(columns=None),
                                  check_dtype=False)
    meta = json.loads((tmp_path / "results" / "m4" / "cohort" / "options.json").read_text())
    assert meta["release"] == "MIMIC-IV"
    consort = pd.read_csv(tmp_path / "results" / "m4" / "cohort" / "consort.csv")
    assert consort["n_stays"].iloc[-1] == got[schema.STAY_ID].nunique()


def test_command_line_extracts_mimic4(pair, tmp_path, capsys):
    from twinfalsify.sources.mimic3.cohort import main

    main([str(pair / "mimic4"), str(tmp_path / "out")], layout=MIMIC4)
    got = pd.read_parquet(tmp_path / "out" / "trajectories.parquet")
    assert got[schema.STAY_ID].nunique() == extract_mimic4(pair / "mimic4").trajectories[
        schema.STAY_ID].nunique()
    with pytest.raises(SystemExit, match="ERROR: MIMIC-IV table PATIENTS not found"):
        main([str(pair / "mimic3"), str(tmp_path / "out2")], layout=MIMIC4)
