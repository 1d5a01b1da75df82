"""The whole MIMIC-III demo study through Snakemake (config/mimic3-demo.yaml), when the open
MIMIC-III Clinical Database Demo is at ../shared/data/mimic-iii-demo; skipped otherwise.

The demo has ~70 stays, so many hypotheses have n = 0 or nhat = 0: the study must finish and
say how many are untestable (p = 1 by rule), not crash. The figure rule is not requested
(it is exercised by tests/workflow/test_workflow.py) to keep this run short.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT, shared_dir
from helpers.workflow import mimic_study_config


def _shared() -> Path:
    p = ROOT.parent / "shared"
    return shared_dir() or p


DEMO = _shared() / "data" / "mimic-iii-demo"


@pytest.mark.slow
@pytest.mark.skipif(not (DEMO / "CHARTEVENTS.csv.gz").is_file(),
                    reason=f"MIMIC-III demo not present at {DEMO}")
def test_demo_study_end_to_end(tmp_path):
    config = tmp_path / "mimic3-demo.yaml"
    shutil.copy(ROOT / "config" / "mimic3-demo.yaml", config)
    cfg = yaml.safe_load(config.read_text())
    r = Path("results") / cfg["study"]
    twins = list(cfg["twins"])
    targets = [str(r / "trajectories.parquet"), str(r / "design" / "hypotheses.parquet")]
    targets += [str(r / "twins" / tw / f) for tw in twins
                for f in ("results.parquet", "tables/rejections.csv")]
    # the config's relative path is resolved from the working directory; the environment
    # variable (which overrides it) points at the demo wherever the checkout is
    env = {**os.environ, "MPLBACKEND": "Agg", "TWINFALSIFY_MIMIC3_DIR": str(DEMO)}
    cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
           str(tmp_path), "--configfile", str(config), "--cores", "2", *targets]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = tmp_path / r

    # cohort report: CONSORT steps shrink monotonically and end at the trajectory count
    consort = pd.read_csv(out / "cohort" / "consort.csv")
    assert consort["step"].iloc[0] == "all_icu_stays" and consort["n_stays"].iloc[0] == 136
    assert (consort["n_stays"].diff().dropna() <= 0).all()
    traj = pd.read_parquet(out / "trajectories.parquet")
    assert traj["stay_id"].nunique() == consort["n_stays"].iloc[-1] > 0
    assert set(pd.read_csv(out / "cohort" / "anchors.csv")["stay_id"]) == set(traj["stay_id"])
    assert (out / "cohort" / "missingness.csv").is_file()
    hyps = pd.read_parquet(out / "design" / "hypotheses.parquet")
    assert len(hyps) > 0

    for tw in twins:
        res = pd.read_parquet(out / "twins" / tw / "results.parquet")
        assert set(res["hyp_id"]) == set(hyps["hyp_id"])
        assert res["p_value"].between(0, 1).all()
        # the tests log states the untestable count, and it is the right count
        per_set = res.groupby("hyp_id")[["n", "nhat"]].first()
        untestable = int(((per_set["n"] == 0) | (per_set["nhat"] == 0)).sum())
        assert untestable > 0  # the demo is too small for every hypothesis
        assert (res.loc[res["hyp_id"].isin(per_set.index[(per_set["n"] == 0)
                                                          | (per_set["nhat"] == 0)]),
                        "p_value"] == 1).all()
        log = (out / "logs" / "twins" / tw / "tests.log").read_text()
        m = re.search(r"(\d+) of (\d+) parameter sets are untestable", log)
        assert m, log[-2000:]
        assert (int(m.group(1)), int(m.group(2))) == (untestable, len(hyps))
        assert (out / "twins" / tw / "tables" / "rejections.csv").is_file()


FIX = ROOT / "tests" / "fixtures" / "mimic3"


def test_data_fingerprint_follows_folder_and_files(tmp_path, monkeypatch):
    from twinfalsify.sources.mimic_rule import data_params

    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(FIX, a)
    shutil.copytree(FIX, b)
    monkeypatch.delenv("TWINFALSIFY_MIMIC3_DIR", raising=False)
    pa, pb = data_params({"path": str(a)}), data_params({"path": str(b)})
    assert pa != pb and str(a) in pa  # same files, another folder
    monkeypatch.setenv("TWINFALSIFY_MIMIC3_DIR", str(b))
    assert data_params({"path": str(a)}) == pb  # the variable overrides the config
    monkeypatch.delenv("TWINFALSIFY_MIMIC3_DIR")
    f = a / "LABEVENTS.csv"
    os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 10**9))
    assert data_params({"path": str(a)}) != pa  # a file changed (mtime)
    assert data_params({"path": str(tmp_path / "nope")}) == "unresolved"


def test_another_mimic3_dir_reruns_the_extraction(tmp_path):
    """With TWINFALSIFY_MIMIC3_DIR pointing elsewhere the trajectories rule must
    run again (before, the old cohort silently stood)."""
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(FIX, a)
    shutil.copytree(FIX, b)
    cfg = mimic_study_config("fp", "mimic3", None)
    config = tmp_path / "fp.yaml"
    config.write_text(yaml.safe_dump(cfg))
    target = "results/fp/trajectories.parquet"

    def snake(folder, *args):
        env = {**os.environ, "TWINFALSIFY_MIMIC3_DIR": str(folder)}
        cmd = [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
               str(tmp_path), "--configfile", str(config), "--cores", "1", *args, target]
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)

    run = snake(a)
    assert run.returncode == 0, run.stderr[-3000:]
    assert (tmp_path / "results/fp/cohort/stays.csv").is_file()
    again = snake(a, "-n")
    assert "Nothing to be done" in again.stdout + again.stderr
    other = snake(b, "-n")
    out = other.stdout + other.stderr
    assert other.returncode == 0 and "rule trajectories" in out, out[-3000:]


@pytest.mark.parametrize("kind", ["mimic3", "mimic4"])
def test_a_missing_mimic_folder_is_refused_when_the_workflow_starts(tmp_path, monkeypatch,
                                                                    kind):
    """The folder is checked at parse time, in one line naming the key: no rule runs."""
    from helpers.workflow import mimic_study_config, run_snakemake

    for var in ("TWINFALSIFY_MIMIC3_DIR", "TWINFALSIFY_MIMIC4_DIR"):
        monkeypatch.delenv(var, raising=False)
    config = tmp_path / "study.yaml"
    config.write_text(yaml.safe_dump(mimic_study_config("gone", kind, str(tmp_path / "nope"))))
    done = run_snakemake(tmp_path, config, "--cores", "1", timeout=300)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    line = next(ln for ln in out.splitlines() if ln.startswith("invalid config:"))
    assert line.startswith(f"invalid config: config key source.{kind}.path: ")
    assert f"{tmp_path / 'nope'}" in line and "does not exist" in line
    assert not (tmp_path / "results").exists()
