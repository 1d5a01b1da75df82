"""Hypotheses a method refuses are reported as refused for that method, not as tested: in
the results table (column ``refused``), on the console (the tests rule's warning) and in the
summary."""

from __future__ import annotations

from functools import partial

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT
from helpers.workflow import copy_study, run_snakemake

from twinfalsify import summary
from twinfalsify.falsify import make_methods
from twinfalsify.inference import registry


def _results() -> pd.DataFrame:
    # two hypotheses (hyp_id 0, 1) x two sides x two methods; n, nhat per hypothesis
    rows = []
    for method in ("hoeffding", "bootstrap"):
        for hyp, (n, nhat) in enumerate([(40, 50), (150, 300)]):
            for side in ("lo", "up"):
                rows.append({"hyp_id": hyp, "kind": "causal", "outcome": "HR", "t": 1,
                             "side": side, "method": method, "n": n, "nhat": nhat,
                             "rejected": False,
                             "refused": method == "bootstrap" and min(n, nhat) < 100})
    return pd.DataFrame(rows)


def test_the_methods_say_which_hypotheses_they_refuse():
    n, nhat = np.array([40, 150, 0, 300]), np.array([50, 300, 10, 0])
    methods = make_methods({"hoeffding": {}, "bootstrap": {}}, seed=0)
    # the bootstrap refuses n or nhat below its min_n (100 by default), every method n or
    # nhat = 0
    assert registry.refused("bootstrap", methods["bootstrap"], n, nhat).tolist() == [
        True, False, True, True]
    assert registry.refused("hoeffding", methods["hoeffding"], n, nhat).tolist() == [
        False, False, True, True]
    few = make_methods({"bootstrap": {"min_n": 10}}, seed=0)["bootstrap"]
    assert isinstance(few, partial)
    assert registry.refused("bootstrap", few, n, nhat).tolist() == [False, False, True, True]


def test_the_bootstrap_below_min_n_is_refused_not_tested():
    res = _results()
    # the bootstrap refuses hypothesis 0 (n = 40 < min_n = 100), hoeffding tests it
    lines = summary.refusal_lines(res)
    assert lines == ["bootstrap refused 2 of 4 causal hypotheses (too few samples: p = 1 by "
                     "rule, not tested; results column 'refused')"]
    runs = pd.DataFrame({"init_stay_id": [1], "t": [1], "status": ["ok"], "clamped": [""]})
    d = pd.DataFrame({"stay_id": [1, 2]})
    hyps = pd.DataFrame({"hyp_id": [0, 1], "kind": ["causal", "causal"]})
    tabs = summary.study_summary("s", d, d, hyps, {"tw": {"runs": runs, "results": res}})
    rej = tabs["rejections"].set_index("method")
    assert rej.loc["bootstrap", ["hypotheses", "refused", "tested"]].tolist() == [4, 2, 2]
    assert rej.loc["hoeffding", ["hypotheses", "refused", "tested"]].tolist() == [4, 0, 4]
    md = summary.summary_markdown("s", tabs)
    assert "| tw | bootstrap | causal | 4 | 0 | 2 | 2 |" in md
    assert f"- twin tw: {lines[0]}" in md  # a warning too


def test_a_twin_failing_most_patients_is_warned_about():
    stays = [1] * 2 + [2] * 2 + [3] * 2 + [4] * 2
    failing = ["error", "error", "timeout", "error", "error", "error", "ok", "error"]
    runs = pd.DataFrame({"init_stay_id": stays, "status": failing})
    warning = summary.failing_patients(runs, "mine")
    assert warning.startswith("twin mine: 3 of 4 patients (75%) got no ok run (failed runs: "
                              "error 6, timeout 1)")
    half = runs.assign(status=["ok"] * 2 + failing[2:])  # 2 of 4 fail: not most
    assert summary.failing_patients(half, "mine") == ""
    # the summary opens with it
    res = _results()
    d = pd.DataFrame({"stay_id": [1, 2]})
    hyps = pd.DataFrame({"hyp_id": [0, 1], "kind": ["causal", "causal"]})
    runs = runs.assign(t=1, clamped="")
    tabs = summary.study_summary("s", d, d, hyps, {"mine": {"runs": runs, "results": res}})
    md = summary.summary_markdown("s", tabs)
    assert md.split("## Warnings\n\n- ")[1].startswith(warning)


@pytest.mark.slow
def test_the_bootstrap_refusals_reach_the_console_and_the_results_table(tmp_path, test_study):
    """config/test.yaml with ``bootstrap: {}``: too few samples for most hypotheses; the
    console says so per method and results.parquet marks them refused (p = 1 by rule).
    Run on a copy of the finished config/test.yaml study: a testing method changes only
    the tests (the twin's runs are the study's)."""
    work = copy_study(test_study[0], tmp_path / "study")
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["testing"]["methods"]["bootstrap"] = {}
    config = work / "boot.yaml"
    config.write_text(yaml.safe_dump(cfg))
    target = "results/test/twins/oracle/results.parquet"
    done = run_snakemake(work, config, "--cores", "2", target)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "rule twin_shard" not in done.stderr and "rule tests" in done.stderr
    res = pd.read_parquet(work / target)
    boot = res[res["method"] == "bootstrap"]
    assert boot["refused"].sum() > 0
    assert (boot.loc[boot["refused"], "p_value"] == 1.0).all()
    assert not boot.loc[boot["refused"], "rejected"].any()
    hoef = res[res["method"] == "hoeffding"]
    assert hoef["refused"].sum() == ((hoef["n"] == 0) | (hoef["nhat"] == 0)).sum()
    for line in summary.refusal_lines(res):
        assert line in done.stderr
    n_causal = int((boot["kind"] == "causal").sum())
    refused_causal = int(boot.loc[boot["kind"] == "causal", "refused"].sum())
    assert f"bootstrap refused {refused_causal} of {n_causal} causal hypotheses" in done.stderr
