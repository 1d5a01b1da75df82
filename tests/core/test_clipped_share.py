"""The summary shows how many twin outputs sit at the bounds [y_lo, y_up].

A twin in the wrong unit (glucose ~120 mg/dL too low, as mmol/L labelled mg/dL would be)
piles up at y_lo, where the clipped tests may fail to reject it: the share must show it,
and the summary must warn.
"""

from __future__ import annotations

import numpy as np
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
