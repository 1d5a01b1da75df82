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
    return r, res, study, samples


def test_a_rejection_is_explained_with_its_numbers(study_dir):
    r, res, study, _ = study_dir
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
    r, res, _, _ = study_dir
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


def test_the_size_of_the_difference_beside_the_data(study_dir):
    """The clipped mean hides how far off a twin is: explain gives the unclipped mean and
    median and the shares beyond each bound, equal to a hand computation on the samples."""
    import numpy as np

    from twinfalsify.twin_tests import outcome_sizes

    r, res, study, samples = study_dir
    sizes = {"b": outcome_sizes(samples).set_index(study.hyps["hyp_id"].to_numpy())}
    hit = res[res["rejected"] & (res["outcome"] == "HR")].sort_values("p_value").iloc[0]
    k = int(np.flatnonzero(study.hyps["hyp_id"].to_numpy() == hit["hyp_id"])[0])
    twin, data = samples.twin.group(k), samples.follow.group(k)
    lo, up = samples.y_lo[k], samples.y_up[k]
    text = explain(r, int(hit["hyp_id"]), sizes=sizes)
    want = (f"  unclipped: twin mean {np.mean(twin):.4g}, median {np.median(twin):.4g} /min, "
            f"{np.mean(twin < lo):.0%} of its outputs below y_lo, {np.mean(twin > up):.0%} "
            f"above y_up (data's followers: mean {np.mean(data):.4g}, median "
            f"{np.median(data):.4g} /min, {np.mean(data < lo):.0%} below y_lo, "
            f"{np.mean(data > up):.0%} above y_up)")
    assert want in text.splitlines(), text
    # HR + 25 /min: the unclipped mean is above y_up, further than the clipped one shows
    assert np.mean(twin) > up >= hit["q_twin_hat"]
    assert np.mean(twin) - np.mean(data) == pytest.approx(25.0, abs=6.0)
    # without the study's stored runs (this folder has results only) no size line
    assert "unclipped:" not in explain(r, int(hit["hyp_id"]))


def test_each_p_value_with_the_threshold_it_was_held_to(study_dir):
    """Holm within (method, kind): rank j of m in ascending p is held to alpha / (m - j + 1)."""
    import numpy as np

    r, res, _, _ = study_dir
    hit = res[~res["rejected"]].sort_values("p_value").iloc[0]  # the first one Holm stops at
    fam = res[(res["method"] == hit["method"]) & (res["kind"] == hit["kind"])]
    m = len(fam)
    j = int(np.flatnonzero(np.argsort(fam["p_value"].to_numpy(), kind="stable")
                           == list(fam.index).index(hit.name))[0]) + 1
    text = explain(r, int(hit["hyp_id"]))
    assert (f"H_{hit['side']}: p = {hit['p_value']:.3g}, not rejected (Holm threshold "
            f"{0.05 / (m - j + 1):.3g} at rank {j} of {m} in its family ({hit['method']}, "
            f"{hit['kind']}), alpha 0.05)") in text, text
    assert hit["p_value"] > 0.05 / (m - j + 1)


@pytest.mark.parametrize("method", ["holm", "bonferroni", "by", "none"])
def test_thresholds_give_the_corrections_decisions(method):
    """Each p-value's threshold and rank reproduce ``correct``: Holm rejects rank j when
    every rank <= j is under its threshold, BY when some rank >= j is, the others alone."""
    import numpy as np

    from twinfalsify.inference.multiple_testing import correct, thresholds

    rng = np.random.default_rng(7)
    for _ in range(50):
        p = np.round(rng.uniform(0, 0.02, size=rng.integers(1, 30)) ** rng.uniform(0.5, 2), 4)
        level, rank = thresholds(p, 0.05, method)
        under = (p <= level)[np.argsort(rank)]  # in rank order
        if method == "holm":
            want = np.cumprod(under).astype(bool)[rank - 1]
        elif method == "by":
            want = np.flip(np.cumsum(np.flip(under)) > 0)[rank - 1]
        else:
            want = p <= level
        assert (want == correct(p, 0.05, method)).all()
