"""End to end: `snakemake --cores 2` on the tiny test config, outputs, reruns."""

from __future__ import annotations

import re

import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT
from helpers.workflow import run_snakemake

from twinfalsify.twin_tests import STUDY_RESULT_COLUMNS

pytestmark = pytest.mark.slow




@pytest.fixture(scope="module")
def study(test_study):
    return test_study


def test_outputs_exist_with_their_columns(study):
    work, config = study
    cfg = yaml.safe_load(config.read_text())
    r = work / "results" / cfg["study"]
    assert list(pd.read_csv(r / "tables" / "action_space.csv").columns)[:3] == [
        "action",
        "iv_bin",
        "vaso_bin",
    ]
    for twin in cfg["twins"]:
        res = pd.read_parquet(r / "twins" / twin / "results.parquet")
        assert tuple(res.columns) == STUDY_RESULT_COLUMNS
        assert set(res["side"]) == {"lo", "up"} and res["p_value"].between(0, 1).all()
        table = pd.read_csv(r / "twins" / twin / "tables" / "rejections.csv")
        total = table[table["outcome"] == "Total"].iloc[0]
        assert total["causal_rejections"] == res.query("kind == 'causal'")["rejected"].sum()
        assert total["manski_hypotheses"] == (res["kind"] == "manski").sum()
        for ext in ("png", "pdf"):
            assert (r / "twins" / twin / "figures" / f"pvalues.{ext}").stat().st_size > 10_000
    oracle = pd.read_parquet(r / "twins" / "oracle" / "results.parquet")
    biased = pd.read_parquet(r / "twins" / "biased" / "results.parquet")
    assert oracle["rejected"].sum() == 0 and biased["rejected"].sum() > 0


def test_second_run_has_nothing_to_do(study):
    work, config = study
    run = run_snakemake(work, config, "--cores", "2", "--dry-run")
    assert run.returncode == 0
    assert "Nothing to be done" in run.stdout + run.stderr


def test_changing_one_twin_reruns_only_that_twin(study, tmp_path):
    work, config = study
    cfg = yaml.safe_load(config.read_text())
    cfg["twins"]["biased"]["shift"] = {"HR": 10.0}
    changed = tmp_path / "changed.yaml"
    changed.write_text(yaml.safe_dump(cfg))
    run = run_snakemake(work, changed, "--cores", "2", "--dry-run")
    out = run.stdout + run.stderr
    assert run.returncode == 0, out[-2000:]
    rules = set(re.findall(r"rule (\w+):", out)) - {"all"}
    assert rules == {
        "twin_hello", "twin_cost", "twin_shard", "twin_runs", "tests", "rejections_table",
        "table_rejections_tex", "explain_rejections",
        "figure_pvalues", "figure_longitudinal", "figure_histograms", "figure_sample_sizes",
        "figure_propensity", "figure_sensitivity", "summary",
    }
    assert "twin=biased" in out and "twin=oracle" not in out


def test_bad_config_is_refused_with_the_key_named(tmp_path):
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["split"]["d0_fracton"] = cfg["split"].pop("d0_fraction")
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(cfg))
    run = run_snakemake(tmp_path, bad, "--cores", "1", "--dry-run")
    assert run.returncode != 0
    assert "d0_fracton" in run.stderr + run.stdout
