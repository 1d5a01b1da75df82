"""The summary shows how many twin outputs sit at the bounds [y_lo, y_up].

A twin in the wrong unit (glucose ~120 mg/dL too low, as mmol/L labelled mg/dL would be)
piles up at y_lo, where the clipped tests may fail to reject it: the share must show it,
and the summary must warn.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from helpers.studies import build_study, twin_samples

from twinfalsify import summary
from twinfalsify.runs.registry import make_twin


def _shares(shift: dict[str, float]) -> tuple:
    study = build_study(600, seed=5, d0_fraction=0.3, min_support=5, runs=100)
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}}}
    twin = make_twin("b", {"kind": "biased", "shift": shift}, ctx)
    samples, _ = twin_samples(study, twin)
    return summary.clipped_shares(study.hyps, samples), samples, study.hyps


def test_a_unit_error_shows_as_outputs_at_one_bound():
    clipped, samples, hyps = _shares({"Glucose": -110.0})
    row = clipped.set_index("outcome").loc["Glucose"]
    # nearly every twin output at y_lo, almost none at y_up (the twin's noise reaches y_up
    # for about 1 % of its runs)
    assert row["twin_at_y_lo"] > 0.9 and row["twin_at_y_up"] < 0.03
    # the data sit at each bound about a fifth of the time (0.2 / 0.8 quantiles of D0)
    assert 0.1 < row["data_at_y_lo"] < 0.35 and 0.1 < row["data_at_y_up"] < 0.35
    # the shares are counts of the very samples the tests clip
    mine = hyps["outcome"].to_numpy() == "Glucose"
    gid = samples.twin.group_ids()
    sel = mine[gid]
    assert row["twin_outputs"] == sel.sum()
    hr = clipped.set_index("outcome").loc["HR"]
    assert hr["twin_at_y_lo"] < 0.5 and hr["twin_at_y_up"] < 0.5  # HR is not shifted
    tables = {"clipped": clipped.assign(twin="b")[["twin", *clipped.columns]]}
    (warning,) = summary.clipped_warnings(tables["clipped"])
    assert warning.startswith(f"twin b: {row['twin_at_y_lo']:.0%} of its Glucose outputs are "
                              "at or beyond y_lo (data: ")
    md = summary.summary_markdown("s", tables)
    assert md.index("## Warnings") < md.index("## Outputs at the bounds")
    assert np.isclose(clipped["twin_at_y_lo"].max(), row["twin_at_y_lo"])


def test_the_medians_show_the_size_of_the_error():
    clipped, samples, hyps = _shares({"Glucose": -110.0})
    row = clipped.set_index("outcome").loc["Glucose"]
    mine = hyps["outcome"].to_numpy() == "Glucose"
    twin = samples.twin.values[mine[samples.twin.group_ids()]]
    data = samples.follow.values[mine[samples.follow.group_ids()]]
    assert row["twin_median"] == np.median(twin) and row["data_median"] == np.median(data)
    assert row["data_median"] - row["twin_median"] > 80  # the shift, not the clipped gap
    (warning,) = summary.clipped_warnings(clipped.assign(twin="b"))
    assert warning.endswith(f"(data: {row['data_at_y_lo']:.0%}); its median "
                            f"{row['twin_median']:.4g} against the data's "
                            f"{row['data_median']:.4g} mg/dL: a unit or scale error? The "
                            "tests see only the clipped values")


def test_a_bound_the_data_crowd_more_than_the_twin_is_no_warning():
    row = {"twin": "t", "outcome": "Calcium", "twin_outputs": 100, "twin_at_y_up": 0.1,
           "twin_median": 7.9, "data_outputs": 40, "data_at_y_up": 0.05, "data_median": 7.8}
    both = pd.DataFrame([{**row, "twin_at_y_lo": 0.67, "data_at_y_lo": 0.93},  # data higher
                         {**row, "twin_at_y_lo": 0.67, "data_at_y_lo": 0.30},  # margin < 0.4
                         {**row, "twin_at_y_lo": 0.67, "data_at_y_lo": 0.20}])
    warned = summary.clipped_warnings(both)
    assert len(warned) == 1 and "(data: 20%)" in warned[0]


def test_the_summary_warnings_read_back_and_only_when_written_in_this_run(tmp_path):
    import os

    row = {"twin": "t", "outcome": "Calcium", "twin_outputs": 100, "twin_at_y_up": 0.1,
           "twin_median": 7.9, "data_outputs": 40, "data_at_y_up": 0.05, "data_median": 7.8,
           "twin_at_y_lo": 0.9, "data_at_y_lo": 0.1}
    tables = {"clipped": pd.DataFrame([row, {**row, "twin": "u"}]),
              "failing": pd.DataFrame({"warning": ["twin t: 3 patients fail every run"]}),
              "cohort": pd.DataFrame({"n": [1]})}
    md = tmp_path / "summary.md"
    md.write_text(summary.summary_markdown("s", tables))
    want = summary.summary_warnings(tables)
    assert len(want) == 3 and want[0] == "twin t: 3 patients fail every run"
    assert summary.warnings_in_summary(md) == want
    os.utime(md, (1000.0, 1000.0))  # written before this run started: not this run's
    assert summary.warnings_in_summary(md, since=2000.0) == []
    assert summary.warnings_in_summary(md, since=500.0) == want
    assert summary.warnings_in_summary(tmp_path / "none.md") == []
    md.write_text(summary.summary_markdown("s", {"cohort": tables["cohort"]}))
    assert summary.warnings_in_summary(md) == []


def test_a_studys_warnings_end_its_output(test_study, tmp_path):
    """config/test.yaml's biased twin (HR + 25 /min) piles its HR outputs at y_up: the
    warning is in summary.md, logged by the summary rule, and the run's last lines say it,
    after Snakemake's own closing lines. A run that writes no summary repeats none."""
    from helpers.workflow import copy_study, run_snakemake

    work = copy_study(test_study[0], tmp_path / "study")
    done = run_snakemake(work, work / "test.yaml", "--cores", "2", "--forcerun", "summary")
    assert done.returncode == 0, done.stderr[-3000:]
    warnings = summary.warnings_in_summary(work / "results" / "test" / "summary.md")
    assert any(w.startswith("twin biased: ") and "of its HR outputs are at or beyond y_up"
               in w for w in warnings), warnings
    lines = done.stderr.rstrip().splitlines()
    n = len(warnings)
    assert lines[-n - 1:] == ["The study's warnings (results/test/summary.md):",
                              *[f"WARNING: {w}" for w in warnings]], lines[-8:]
    closing = max(k for k, ln in enumerate(lines) if "steps (100%) done" in ln)
    assert closing < len(lines) - n - 1  # after Snakemake's closing lines
    for w in warnings:  # the summary rule's log lines, before
        assert any(ln.endswith(f"WARNING: {w}") for ln in lines[:closing])
    again = run_snakemake(work, work / "test.yaml", "--cores", "2")
    assert again.returncode == 0 and "WARNING: twin" not in again.stderr
