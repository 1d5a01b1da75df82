"""Hypotheses a method refuses are reported as untestable for that method, not as tested."""

from __future__ import annotations

import pandas as pd

from twinfalsify import summary


def _results() -> pd.DataFrame:
    # two hypotheses (hyp_id 0, 1) x two sides x two methods; n, nhat per hypothesis
    rows = []
    for method in ("hoeffding", "bootstrap"):
        for hyp, (n, nhat) in enumerate([(40, 50), (150, 300)]):
            for side in ("lo", "up"):
                rows.append({"hyp_id": hyp, "kind": "causal", "outcome": "HR", "t": 1,
                             "side": side, "method": method, "n": n, "nhat": nhat,
                             "rejected": False})
    return pd.DataFrame(rows)


def test_the_bootstrap_below_min_n_is_untestable_not_tested():
    res = _results()
    refused = summary.refused(res, {"hoeffding": {}, "bootstrap": {}})
    # the bootstrap refuses hypothesis 0 (n = 40 < min_n = 100), hoeffding tests it
    assert refused.tolist() == [False] * 4 + [True, True, False, False]
    assert summary.refused(res, {"bootstrap": {"min_n": 10}}).sum() == 0
    runs = pd.DataFrame({"init_stay_id": [1], "t": [1], "status": ["ok"], "clamped": [""]})
    d = pd.DataFrame({"stay_id": [1, 2]})
    hyps = pd.DataFrame({"hyp_id": [0, 1], "kind": ["causal", "causal"]})
    tabs = summary.study_summary("s", d, d, hyps, {"tw": {"runs": runs, "results": res}},
                                 methods={"hoeffding": {}, "bootstrap": {}})
    rej = tabs["rejections"].set_index("method")
    assert rej.loc["bootstrap", ["hypotheses", "untestable", "tested"]].tolist() == [4, 2, 2]
    assert rej.loc["hoeffding", ["hypotheses", "untestable", "tested"]].tolist() == [4, 0, 4]
    assert "| tw | bootstrap | causal | 4 | 0 | 2 | 2 |" in summary.summary_markdown("s", tabs)


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
