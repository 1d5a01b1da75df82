"""The summary shows how many twin outputs sit at the bounds [y_lo, y_up].

A twin in the wrong unit (glucose ~120 mg/dL too low, as mmol/L labelled mg/dL would be)
piles up at y_lo, where the clipped tests may fail to reject it: the share must show it,
and the summary must warn.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from study_helpers import build_study, twin_samples

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
