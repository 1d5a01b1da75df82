"""python -m twinfalsify.explain: one hypothesis in clinical words, with every test's verdict."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from helpers.paths import ROOT
from helpers.studies import build_study, twin_samples

from twinfalsify.design import StateBins
from twinfalsify.explain import explain, subgroup_in_words
from twinfalsify.falsify import make_methods, run_tests
from twinfalsify.runs.registry import make_twin


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory) -> tuple[Path, pd.DataFrame, object]:
    """A results folder as a study writes it: one biased twin (HR + 25 /min)."""
    study = build_study(800, seed=5, d0_fraction=0.3, min_support=5, runs=100)
    r = tmp_path_factory.mktemp("explain") / "results" / "s"
    (r / "design").mkdir(parents=True)
    (r / "twins" / "b").mkdir(parents=True)
    study.hyps.to_parquet(r / "design" / "hypotheses.parquet")
    (r / "design" / "bins.json").write_text(json.dumps(study.states.to_json()))
    (r / "design" / "actions.json").write_text(json.dumps(study.actions.to_json()))
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}}}
    twin = make_twin("b", {"kind": "biased", "shift": {"HR": 25.0}}, ctx)
    samples, n_failed = twin_samples(study, twin)
    res = run_tests(study.hyps, samples, n_failed,
                    make_methods({"hoeffding": {}, "betting": {}}, 0))
    res.to_parquet(r / "twins" / "b" / "results.parquet")
    return r, res, study


def test_a_rejection_is_explained_with_its_numbers(study_dir):
    r, res, study = study_dir
    hit = res[res["rejected"]].sort_values("p_value").iloc[0]
    text = explain(r, int(hit["hyp_id"]))
    h = study.hyps.set_index("hyp_id").loc[int(hit["hyp_id"])]
    assert text.startswith(f"hypothesis {hit['hyp_id']} ({hit['kind']}): the mean {hit['outcome']} "
                           f"at hour {hit['t']}")
    # the doses are those the twin was given: the bins' D0 medians
    doses = study.actions.doses(list(h["actions"]))
    for hour, (iv, vaso) in enumerate(doses, start=1):
        assert f"hour {hour}: IV fluid {iv:.4g} mL/h" in text
        assert f"vasopressor {vaso:.4g} ug/kg/min" in text
    assert f"from n_hat = {hit['nhat']} runs" in text and f"from n = {hit['n']} stays" in text
    # every method and side with its p and decision
    mine = res[res["hyp_id"] == hit["hyp_id"]]
    assert text.count(" H_lo: p = ") + text.count(" H_up: p = ") == len(mine)
    assert text.count("REJECTED") == int(mine["rejected"].sum())
    for m in mine.itertuples():
        assert f"H_{m.side}: p = {m.p_value:.3g}" in text
    # HR + 25: a rejected HR hypothesis has the twin's mean above the data's bounds
    if hit["outcome"] == "HR":
        assert "above the upper bound" in text


def test_the_subgroup_reads_as_patients():
    states = StateBins((50.0, 64.0, 75.0), {"HR": (90.0, 88.5, 87.0, 86.0, 85.0)})
    # female (8), 3rd age quartile (2 * 2), HR above the median at hour 0, below at hour 1
    lines = subgroup_in_words([8 + 4 + 1, 8 + 4 + 0], "HR", states)
    assert lines == ["female, age 64 to < 75 years (3rd age quartile of D0)",
                     "HR at hour 0 above 90 /min (the D0 median at hour 0)",
                     "HR at hour 1 at or below 88.5 /min (the D0 median at hour 1)"]
    assert subgroup_in_words([-1, -1], "HR", states) == [
        "every patient (Manski bounds: no subgroup)"]


def test_the_command_line_names_a_missing_hypothesis(study_dir):
    r, res, _ = study_dir
    env = {"PYTHONPATH": str(ROOT / "src")}
    ok = subprocess.run([sys.executable, "-m", "twinfalsify.explain", str(r),
                         str(int(res["hyp_id"].iloc[0]))], capture_output=True, text=True,
                        env=env, timeout=120)
    assert ok.returncode == 0 and ok.stdout.startswith("hypothesis "), ok.stderr
    bad = subprocess.run([sys.executable, "-m", "twinfalsify.explain", str(r), "999999"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip().startswith(f"twinfalsify.explain: error: {r}/design/"
                                         "hypotheses.parquet: no hypothesis 999999")


def test_rejections_to_explain_takes_the_smallest_p_first():
    from twinfalsify.explain import rejections_to_explain

    res = pd.DataFrame({"hyp_id": [5, 5, 2, 9, 7], "p_value": [0.3, 1e-4, 1e-3, 1e-4, 0.5],
                        "rejected": [False, True, True, True, False]})
    assert rejections_to_explain(res, 2) == ([5, 9], 3)  # equal p: the smaller hyp_id
    assert rejections_to_explain(res, 10) == ([5, 9, 2], 3)
    assert rejections_to_explain(res, 0) == ([], 3)


def test_the_report_page_explains_each_rejection_with_its_figure(test_study):
    """config/test.yaml's biased twin: the page holds the first k = 3 rejections, each as
    ``explain`` words it and with its own bounds figure (a PNG)."""
    import base64
    import html
    import re

    from twinfalsify.explain import rejections_to_explain

    work, _ = test_study
    r = work / "results" / "test"
    res = pd.read_parquet(r / "twins" / "biased" / "results.parquet")
    ids, n_rejected = rejections_to_explain(res, 3)
    assert len(ids) >= 2  # two rejections at least, to show
    page = (r / "twins" / "biased" / "explained.html").read_text()
    assert f"{len(ids)} of {n_rejected} rejected hypotheses" in page
    shown = [int(h) for h in re.findall(r"<h2 id='h(\d+)'>", page)]
    assert shown == ids
    for hyp_id in ids:
        assert f"<pre>{html.escape(explain(r, hyp_id, 'biased'))}</pre>" in page
    pngs = re.findall(r"base64,([A-Za-z0-9+/=]+)'", page)
    assert len(pngs) == len(ids)
    assert all(base64.b64decode(p).startswith(b"\x89PNG") for p in pngs)
    # a twin without rejections says so
    res_o = pd.read_parquet(r / "twins" / "oracle" / "results.parquet")
    page_o = (r / "twins" / "oracle" / "explained.html").read_text()
    if not res_o["rejected"].any():
        assert "No hypothesis was rejected for this twin." in page_o
