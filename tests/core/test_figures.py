"""Figures, tables and the study summary on a small in-process study (fast).

Known answers are recomputed independently (plain loops over trajectories), never read back
from the function under test.
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys

import matplotlib.colors
import matplotlib.image as mpimg
import numpy as np
import pandas as pd
import pytest
from helpers.paths import ROOT
from helpers.studies import build_study

from twinfalsify import figures, summary, tables
from twinfalsify.design import WHOLE_SPACE, action_codes, state_codes
from twinfalsify.falsify import make_methods, run_tests
from twinfalsify.runs import plan as tp
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURES, to_array
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.twin_tests import twin_samples


@pytest.fixture(scope="module")
def st(tmp_path_factory) -> summary.StudyTwin:
    """1,500 stays, biased twin (HR + 25/min): small but with rejections."""
    study = build_study(1500, seed=5, d0_fraction=0.2, min_support=5, runs=300)
    d0_path = tmp_path_factory.mktemp("fig") / "d0.parquet"
    study.d0.to_parquet(d0_path)
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}}, "d0": str(d0_path)}
    twin = make_twin("biased", {"kind": "biased", "shift": {"HR": 25.0}}, ctx)
    runs = pd.concat(
        [tp.run_shard(twin, study.plan, k, study.x0, study.actions, log=io.StringIO())
         for k in range(len(study.plan.shards))], ignore_index=True,
    )  # fmt: skip
    nodes = tp.load_nodes(runs, study.plan, study.x0)
    samples, n_failed = twin_samples(study.hyps, study.obs, nodes, study.states)
    res = run_tests(study.hyps, samples, n_failed, make_methods({"hoeffding": {}}, 0))
    assert res["rejected"].sum() > 0, "fixture must have rejections"
    return summary.StudyTwin(study.hyps, samples, n_failed, res, study.d0, study.d,
                             study.actions, study.states, nodes)  # fmt: skip


def _png_ok(fig, path) -> None:
    figures.save_all(fig, path)
    img = mpimg.imread(path)
    assert img.shape[0] > 300 and img.shape[1] > 300
    assert img[..., :3].std() > 0.02  # not blank


def _brute_enter(d: pd.DataFrame, st, outcome: str, seq, bset):
    """Per trajectory, by loops: N, entering, following (docs/explanation/method.md)."""
    x = to_array(d, FEATURES)
    a = action_codes(d, st.actions)
    codes = state_codes(x, st.states, outcome)
    t = len(seq)
    enter, follow = [], []
    for i in range(len(x)):
        n_match = 0
        while n_match < t and a[i, n_match] == seq[n_match]:
            n_match += 1
        ok = all(bset[s] == WHOLE_SPACE or codes[i, s] == bset[s] for s in range(n_match + 1))
        enter.append(ok)
        follow.append(ok and n_match == t)
    return np.array(enter), np.array(follow), x[:, t, FEATURES.index(outcome)]


def test_longitudinal_frame_matches_results_and_brute_force(st, tmp_path):
    hid = summary.pick_hypothesis(st.results, rejected=True)
    frame = summary.longitudinal_frame(st, hid)
    row = st.results[st.results["hyp_id"] == hid].iloc[0]
    last = frame.iloc[-1]
    assert list(frame["t"]) == list(range(1, int(row["t"]) + 1))
    for col in ("n", "nhat", "n_follow"):
        assert int(last[col]) == int(row[col])
    for col in ("q_lo_hat", "q_up_hat", "q_twin_hat", "q_obs_hat"):
        assert last[col] == pytest.approx(row[col])
    # the unclipped twin mean and shares beyond the bounds: those of the tested samples
    k = int(np.flatnonzero(st.hyps["hyp_id"].to_numpy() == hid)[0])
    raw = st.samples.twin.group(k)
    assert last["twin_mean"] == pytest.approx(np.mean(raw))
    assert last["twin_below"] == pytest.approx(np.mean(raw < st.samples.y_lo[k]))
    assert last["twin_above"] == pytest.approx(np.mean(raw > st.samples.y_up[k]))
    hyp = st.hyps[st.hyps["hyp_id"] == hid].iloc[0]
    x0 = to_array(st.d0, FEATURES)
    a0 = action_codes(st.d0, st.actions)
    c0 = state_codes(x0, st.states, hyp["outcome"])
    for _, r in frame.iterrows():  # every prefix, by loops
        s = int(r["t"])
        enter, follow, y = _brute_enter(st.d, st, hyp["outcome"], hyp["actions"][:s],
                                        hyp["bins"][: s + 1])  # fmt: skip
        assert int(r["n"]) == enter.sum() and int(r["n_follow"]) == follow.sum()
        if s < int(hyp["t"]):  # y range: design rule on D0, recomputed
            sub = [x0[i, s, FEATURES.index(hyp["outcome"])] for i in range(len(x0))
                   if list(a0[i, :s]) == list(hyp["actions"][:s])
                   and all(b in (WHOLE_SPACE, c) for b, c in
                           zip(hyp["bins"][: s + 1], c0[i, : s + 1], strict=True))]  # fmt: skip
            assert r["y_lo"] == pytest.approx(np.quantile(sub, 0.2))
            assert r["y_up"] == pytest.approx(np.quantile(sub, 0.8))
        radius = (r["y_up"] - r["y_lo"]) * np.sqrt(np.log(2 / 0.05) / (2 * r["n"]))
        assert r["r_bound"] == pytest.approx(radius)
    _png_ok(figures.longitudinal(frame), tmp_path / "_tf_long.png")


def test_histogram_data_are_the_followers_and_entering_runs(st, tmp_path):
    hid = summary.pick_hypothesis(st.results, rejected=True, prefer_long=False)
    case = summary.histogram_data(st, hid)
    hyp = st.hyps[st.hyps["hyp_id"] == hid].iloc[0]
    _, follow, y = _brute_enter(st.d, st, hyp["outcome"], hyp["actions"], hyp["bins"])
    np.testing.assert_allclose(np.sort(case["obs"]), np.sort(y[follow]))
    row = st.results[st.results["hyp_id"] == hid].iloc[0]
    assert len(case["twin"]) == row["nhat"] and case["rejected"]
    assert case["q_twin_hat"] == pytest.approx(row["q_twin_hat"])
    other = summary.pick_hypothesis(st.results, rejected=False, exclude=(hid,))
    assert other != hid and not st.results.loc[st.results["hyp_id"] == other, "rejected"].any()
    _png_ok(figures.outcome_histograms([case, summary.histogram_data(st, other)]),
            tmp_path / "_tf_hist.png")  # fmt: skip


def test_pick_hypothesis_known_answer():
    rows = []
    for hid, t, p, rej, n in [(1, 2, 0.001, True, 50), (2, 4, 0.01, True, 40),
                              (3, 4, 0.002, True, 0), (4, 1, 1.0, False, 80),
                              (5, 3, 1.0, False, 90)]:  # fmt: skip
        for side in ("lo", "up"):
            rows.append({"hyp_id": hid, "kind": "causal", "outcome": "HR", "t": t, "side": side,
                         "method": "m", "n": n, "nhat": 30, "p_value": p if side == "lo" else 1.0,
                         "rejected": rej and side == "lo"})  # fmt: skip
    res = pd.DataFrame(rows)
    assert summary.pick_hypothesis(res, rejected=True) == 2  # longest t; 3 is untestable
    assert summary.pick_hypothesis(res, rejected=True, prefer_long=False) == 1
    assert summary.pick_hypothesis(res, rejected=False) == 5  # p = 1, longer t
    none = res.assign(rejected=False)
    assert summary.pick_hypothesis(none, rejected=True) == 2  # falls back to any testable


def test_rejections_latex_matches_results(st):
    table = tables.rejections_table(st.results)
    tex = tables.rejections_latex(table)
    cells = dict(re.findall(r"^([A-Za-z0-9_\\]+) & (\d+ / \d+ & \d+ / \d+) \\\\$", tex, re.M))
    for outcome, part in st.results.groupby("outcome"):
        c = part[part["kind"] == "causal"]
        m = part[part["kind"] == "manski"]
        want = f"{c['rejected'].sum()} / {len(c)} & {m['rejected'].sum()} / {len(m)}"
        assert cells[outcome.replace("_", r"\_")] == want
    causal = st.results[st.results["kind"] == "causal"]
    assert cells["Total"].startswith(f"{causal['rejected'].sum()} / {len(causal)} &")


def test_action_space_grid_keeps_counts():
    rng = np.random.default_rng(0)
    rows = []
    for a in range(25):
        iv, va = divmod(a, 5)
        rows.append({"action": a, "iv_bin": iv, "vaso_bin": va, "iv_range_ml_h": f"r{iv}",
                     "vaso_range_ug_kg_min": f"v{va}",
                     "n_hours": int(rng.integers(0, 500))})  # fmt: skip
    df = pd.DataFrame(rows)
    df["share"] = df["n_hours"] / df["n_hours"].sum()
    grid = tables.action_space_grid(df)
    assert grid.shape == (5, 6)
    for a in range(25):
        iv, va = divmod(a, 5)
        cell = grid.iloc[iv, 1 + va]
        assert cell.endswith(f"({df.loc[a, 'n_hours']})")
        assert cell.startswith(f"{100 * df.loc[a, 'share']:.1f}%")
    assert "\\%" in tables.grid_latex(grid, "x") and "\\toprule" in tables.grid_latex(grid, "x")


def test_clamp_shares_known_answer():
    runs = pd.DataFrame({
        "init_stay_id": [1, 1, 2, 3, 3, 4],
        "clamped": ['{"HR": [130, 110]}', '{"HR": [130, 110]}', "",
                    '{"HR": [40, 50], "age": [90, 65]}', '{"HR": [40, 50], "age": [90, 65]}',
                    "{}"],
    })  # fmt: skip
    out = summary.clamp_shares(runs).set_index("feature")
    assert out.loc["HR", "x0_clamped"] == 2 and out.loc["HR", "share"] == pytest.approx(0.5)
    assert out.loc["age", "x0_clamped"] == 1 and out.loc["age", "share"] == pytest.approx(0.25)
    with pytest.raises(ValueError, match="clamped"):
        summary.clamp_shares(runs.assign(clamped="{not json"))


def test_study_summary_matches_results(st):
    runs = pd.DataFrame({"init_stay_id": [1, 2], "t": [1, 1], "status": ["ok", "timeout"],
                         "clamped": ["", ""]})  # fmt: skip
    tabs = summary.study_summary("s", st.d0, st.d, st.hyps, {"biased": {"runs": runs,
                                                             "results": st.results}})  # fmt: skip
    rej = tabs["rejections"].set_index(["method", "kind"])
    for (m, k), part in st.results.groupby(["method", "kind"]):
        assert rej.loc[(m, k), "rejected"] == part["rejected"].sum()
        assert rej.loc[(m, k), "hypotheses"] == len(part)
    unt = tabs["untestable"].set_index("kind")["untestable"]
    per = st.results.drop_duplicates("hyp_id")
    for k, part in per.groupby("kind"):
        assert unt[k] == ((part["n"] == 0) | (part["nhat"] == 0)).sum()
    assert tabs["cohort"]["count"].tolist() == [1500, 300, 1200]
    assert set(tabs["runs"]["status"]) == {"ok", "timeout"}
    md = summary.summary_markdown("s", tabs)
    assert "| biased | hoeffding | causal |" in md
    assert "<table" in summary.summary_html("s", tabs)


def test_sample_size_figure_has_a_point_per_set_and_no_empty_panel(st, tmp_path):
    """Two panels (n, nhat), one row per outcome present (no empty facet), one point per
    causal parameter set in each, and an x range that is the data's (padded), labelled with
    sizes."""
    few = st.results[st.results["outcome"].isin(["HR", "Sodium", "Glucose"])]  # any subset
    fig = figures.sample_size_strips(few)
    sets = few[few["kind"] == "causal"].drop_duplicates("hyp_id")
    assert len(fig.axes) == 2
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == ["HR", "Sodium", "Glucose"]
    for ax, col in zip(fig.axes, ("n", "nhat"), strict=True):
        xs = np.concatenate([c.get_offsets()[:, 0] for c in ax.collections])
        assert len(xs) == len(sets)
        np.testing.assert_allclose(np.sort(xs), np.sort(np.log10(sets[col] + 1.0)))
        lo, hi = ax.get_xlim()
        span = xs.max() - xs.min()
        assert lo <= xs.min() and hi >= xs.max() and (hi - lo) <= span + 2 * max(0.05, span / 25)
        labels = [int(t.get_text().replace(",", "")) for t in ax.get_xticklabels()]
        assert len(labels) >= 2 and labels == sorted(labels)
        assert all(lo <= np.log10(v + 1) <= hi for v in labels)
    _png_ok(fig, tmp_path / "_tf_n.png")


@pytest.mark.parametrize("lo, hi", [(150, 1000), (-0.1, 500), (0, 20_000), (1100, 1300),
                                    (1180, 1190)])
def test_size_ticks_are_round_sizes_inside_the_range(lo, hi):
    ticks = figures.size_ticks(lo, hi)
    assert 2 <= len(ticks) <= 7 and ticks == sorted(set(ticks))
    assert all(lo <= v <= hi for v in ticks)


def test_propensity_columns_have_their_own_n_range_and_only_panels_with_data(st):
    """The causal column's n axis is over the causal sets' n, not stretched to the Manski
    sets' (all of D); a bound kind without a set of n > 0 gets no column."""
    fig = figures.propensity_scatter(st.results)
    causal = st.results[(st.results["kind"] == "causal") & (st.results["n"] > 0)]["n"]
    manski = st.results[st.results["kind"] == "manski"]["n"]
    ax_c, ax_m = fig.axes
    assert "causal" in ax_c.get_title() and "manski" in ax_m.get_title()
    lo, hi = ax_c.get_xlim()
    assert lo <= causal.min() and hi >= causal.max() and hi < manski.min()
    lo, hi = ax_m.get_xlim()
    assert lo <= manski.min() <= manski.max() <= hi < 1.2 * manski.max()
    for ax in fig.axes:  # every panel has points
        assert sum(len(c.get_offsets()) for c in ax.collections) > 0
    only_causal = st.results.assign(n=np.where(st.results["kind"] == "manski", 0,
                                               st.results["n"]))  # fmt: skip
    fig = figures.propensity_scatter(only_causal)
    assert [ax.get_title().split(":")[0] for ax in fig.axes] == ["hoeffding, causal"]


def test_propensity_and_sensitivity_figures_handle_any_methods(st, tmp_path):
    two = pd.concat([st.results, st.results.assign(method="other")], ignore_index=True)
    fig = figures.propensity_scatter(two)
    assert len(fig.axes) == 4  # (2 methods) x (causal, manski)
    _png_ok(fig, tmp_path / "_tf_prop.png")
    sweep = pd.DataFrame([(d, m, g, 10, max(0, 5 - int(10 * d)), k) for d in (0, 0.2, 0.5)
                          for m in ("a", "b") for g in ("HR", "pH") for k in ("causal", "manski")],
                         columns=["delta", "method", "group", "n_hypotheses", "n_rejected",
                                  "kind"])  # fmt: skip
    _png_ok(figures.sensitivity_lines(sweep), tmp_path / "_tf_sens.png")
    with pytest.raises(ValueError, match="missing columns"):
        figures.sensitivity_lines(sweep.drop(columns="n_rejected"))


def test_confounding_frame_observed_are_the_takers(st, tmp_path):
    world = SyntheticWorld.from_config({"n_stays": 1500})
    frame = summary.confounding_frame(st.d, world, st.actions, "MeanBP", seed=3)
    a1 = action_codes(st.d, st.actions)[:, 0]
    x = to_array(st.d, FEATURES)
    n = len(x)
    for code in np.unique(a1)[:3]:
        obs = frame[(frame["action"] == code) & (frame["which"] == "observed")]["value"]
        want = x[a1 == code, 1, FEATURES.index("MeanBP")]
        np.testing.assert_allclose(np.sort(obs), np.sort(want))
        assert ((frame["action"] == code) & (frame["which"] == "everyone")).sum() == n
    again = summary.confounding_frame(st.d, world, st.actions, "MeanBP", seed=3)
    pd.testing.assert_frame_equal(frame, again)  # seeded: reproducible
    _png_ok(figures.confounding(frame, "MeanBP"), tmp_path / "_tf_conf.png")
    with pytest.raises(ValueError, match="never taken"):
        figures.confounding(frame, "MeanBP", show_action=999)
    with pytest.raises(ValueError, match="unknown feature"):
        summary.confounding_frame(st.d, world, st.actions, "nope")


def test_unit_labels():
    assert figures.unit_label("Glucose") == "Glucose (mg/dL)"
    assert figures.unit_label("sex") == "sex"
    assert json.loads(json.dumps(figures.STYLE)) == figures.STYLE


def test_extend_to_horizon_keeps_the_prefix(st):
    hid = summary.pick_hypothesis(st.results, rejected=True, prefer_long=False)
    ext = summary.extend_to_horizon(st.results, st.hyps, hid)
    h = st.hyps.set_index("hyp_id")
    t = int(h.loc[hid, "t"])
    assert int(h.loc[ext, "t"]) >= t and h.loc[ext, "outcome"] == h.loc[hid, "outcome"]
    assert list(h.loc[ext, "actions"][:t]) == list(h.loc[hid, "actions"])
    assert list(h.loc[ext, "bins"][: t + 1]) == list(h.loc[hid, "bins"])
    longer = [i for i, r in h.iterrows() if r["outcome"] == h.loc[hid, "outcome"]
              and r["kind"] == h.loc[hid, "kind"] and r["t"] > int(h.loc[ext, "t"])
              and list(r["actions"][:t]) == list(h.loc[hid, "actions"])
              and list(r["bins"][: t + 1]) == list(h.loc[hid, "bins"])]  # fmt: skip
    assert not longer  # nothing longer on the same path


def test_pvalue_figures_mark_the_bootstrap_floor_and_keep_the_holm_line():
    """p reported at the floor (every resample separated): finite -log10, a Holm line, a note."""
    rows = []
    for i in range(12):
        for side in ("lo", "up"):
            floor = side == "lo" and i < 5
            rows.append({"hyp_id": i, "kind": "causal", "outcome": "HR", "t": 1, "side": side,
                         "method": "bootstrap", "p_value": 1e-6 if floor else 0.5,
                         "p_floor": floor, "rejected": floor, "correction": "holm"})
    res = pd.DataFrame(rows)
    for fig in (figures.pvalue_boxen(res, method="bootstrap"),
                figures.pvalue_boxen_methods(res)):
        ax = fig.axes[0]
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert any("5 at p = 1e-06: all resamples separated" in t for t in labels), labels
        # the line says what it is: Holm's cut alpha / (m - k), m = 24 p-values, k = 5 rejected
        assert any(t.startswith("Holm threshold, alpha = 0.05: 5 of 12 rejected")
                   for t in labels), labels
        assert not ax.texts  # the note is a legend entry: nothing can hide under the legend
        ys = [ln.get_ydata()[0] for ln in ax.get_lines() if len(ln.get_ydata()) == 2]
        assert any(np.isclose(y, 6.0) for y in ys)  # floor line at -log10(1e-6)
        assert any(np.isclose(y, -np.log10(0.05 / 19)) for y in ys)  # Holm's cut
        assert np.isfinite(ax.get_ylim()).all() and ax.get_ylim()[1] < 50
        # the legend sits above every p-value drawn (headroom), not over the boxes
        fig.canvas.draw()
        box = ax.get_legend().get_window_extent().transformed(ax.transData.inverted())
        assert box.y0 > -np.log10(res["p_value"].min())
        # H_up: nothing rejected, nothing at the floor: only the threshold line
        labels = [t.get_text() for t in fig.axes[1].get_legend().get_texts()]
        assert labels == ["Holm threshold, alpha = 0.05: 0 of 12 rejected"]


def test_pvalue_panels_name_their_side_and_the_shared_axis_names_none():
    """The two panels of a row share one y axis, whose label (drawn once, on the left) must
    hold for both: it says -log10 p, and each panel's title names its side, H_lo / p_lo or
    H_up / p_up."""
    res = pd.DataFrame([{"hyp_id": i, "kind": "causal", "outcome": "HR", "t": 1, "side": side,
                         "method": m, "p_value": 0.5, "p_floor": False, "rejected": False,
                         "correction": "holm", "alpha": 0.05}
                        for i in range(5) for side in ("lo", "up")
                        for m in ("hoeffding", "betting")])  # fmt: skip
    for fig in (figures.pvalue_boxen(res), figures.pvalue_boxen_methods(res)):
        for i, ax in enumerate(fig.axes):
            side = ("lo", "up")[i % 2]
            other = ("lo", "up")[1 - i % 2]
            assert f"H_{{{side}}}" in ax.get_title() and f"p_{{{side}}}" in ax.get_title()
            assert other not in ax.get_title(), ax.get_title()
            assert ax.get_ylabel() == "$-\\log_{10}$ p (dimensionless)"


def _overlaps(fig, a, b) -> bool:
    fig.canvas.draw()
    return a.get_window_extent().overlaps(b.get_window_extent())


def test_propensity_legend_is_outside_every_panel_and_titles_count(st):
    two = pd.concat([st.results, st.results.assign(method="other")], ignore_index=True)
    fig = figures.propensity_scatter(two, twin="biased")
    assert fig.get_suptitle().startswith("twin biased: ")
    assert all(ax.get_legend() is None for ax in fig.axes)
    (leg,) = fig.legends
    assert [t.get_text() for t in leg.get_texts()] == ["not rejected", "rejected, either side"]
    for ax in fig.axes:
        assert not _overlaps(fig, leg, ax), ax.get_title()
        m, k = ax.get_title().split(":")[0].split(", ")
        part = two[(two["method"] == m) & (two["kind"] == k) & (two["n"] > 0)]
        per = part.groupby("hyp_id")["rejected"].any()
        assert ax.get_title().endswith(f"{int(per.sum())} of {len(per)} parameter sets rejected")


def test_sensitivity_small_multiples_one_panel_per_outcome_and_distinct_colours():
    """A totals panel, then one panel per outcome whose lines are that outcome's counts; one
    legend naming each (method, kind) line; methods in clearly different colours."""
    sweep = pd.DataFrame([(d, m, g, 10, max(0, 5 - int(10 * d)) + (g == "HR") + (m == "b"), k)
                          for d in (0, 0.2, 0.5) for m in ("a", "b") for g in ("HR", "Sodium")
                          for k in ("causal", "manski")],
                         columns=["delta", "method", "group", "n_hypotheses", "n_rejected",
                                  "kind"])  # fmt: skip
    fig = figures.sensitivity_lines(sweep, twin="fitted")
    assert fig.get_suptitle().startswith("twin fitted: rejected hypotheses")
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in panels] == ["all outcomes", "HR", "Sodium"]
    (leg,) = fig.legends
    entries = {t.get_text(): h for t, h in zip(leg.get_texts(), leg.legend_handles, strict=True)}
    assert set(entries) == {"a, causal", "a, manski", "b, causal", "b, manski"}
    for ax in panels:
        assert not _overlaps(fig, leg, ax)
        sub = sweep if ax.get_title() == "all outcomes" else sweep[sweep["group"] == ax.get_title()]
        for (m, k), part in sub.groupby(["method", "kind"]):
            want = part.groupby("delta")["n_rejected"].sum().to_numpy()
            key = entries[f"{m}, {k}"]
            lines = [ln for ln in ax.get_lines() if ln.get_color() == key.get_color()
                     and ln.get_linestyle() == key.get_linestyle()]  # fmt: skip
            assert len(lines) == 1, (ax.get_title(), m, k)
            assert list(lines[0].get_ydata()) == list(want), (ax.get_title(), m, k)
        assert ax.get_ylim()[0] <= 0 < 1 <= ax.get_ylim()[1]
        assert all(ln.get_ydata().max() <= ax.get_ylim()[1] for ln in ax.get_lines())
    rgb = [np.array(matplotlib.colors.to_rgb(entries[f"{m}, causal"].get_color())) for m in "ab"]
    assert np.abs(rgb[0] - rgb[1]).sum() > 0.5  # not near-identical


def test_longitudinal_title_names_the_intervals_and_each_methods_rejections():
    frame = pd.DataFrame({"outcome": "Sodium", "t": [1, 2, 3, 4],
                          "actions": [[0], [0, 0], [0, 0, 0], [0, 0, 0, 0]],
                          "bins": [[3, 3], [3, 3, 3], [3] * 4, [3] * 5]})  # fmt: skip
    title = figures.longitudinal_title(
        "fitted", frame, "causal",
        {"hoeffding": [1, 2], "bootstrap": [1, 2, 3, 4], "betting": [1, 2, 3, 4]})
    head, who, line = title.split("\n")
    # in words, no codes: action 0 = no drug, B-set 3 = male, 2nd age quartile, above
    assert head == "twin fitted: Sodium (causal), doses none x 4"
    assert who == "male, 2nd age quartile, Sodium vs D0 median at hours 0-4: +++++"
    assert figures.patients_in_brief("HR", [-1, -1, -1]) == "every patient"
    # IV bin 2 with vasopressor bin 1 (code 2 * 5 + 1), then no drug twice
    assert figures.doses_in_brief([11, 0, 0]) == "IV Q2 + vaso Q1, none x 2"
    assert line == ("Hoeffding intervals drawn; rejected (holm) at t = 1, 2 by hoeffding; "
                    "t = 1, 2, 3, 4 by bootstrap, betting")
    none = figures.longitudinal_title("oracle", frame, "causal", {"hoeffding": []})
    assert none.endswith("Hoeffding intervals drawn; rejected by no method")
    fig = figures.longitudinal(frame.assign(
        q_lo_hat=1.0, q_up_hat=2.0, r_bound=0.1, q_twin_hat=0.5, r_twin=0.1, q_obs_hat=1.5,
        r_obs=0.1, n=10, nhat=10), title=title)
    assert "Hoeffding" in fig.axes[0].get_title()
    assert any("Hoeffding" in t.get_text() for t in fig.axes[0].get_legend().get_texts())
    assert not _overlaps(fig, fig.axes[0].get_legend(), fig.axes[0])  # no interval hidden


def test_the_style_file_is_seaborns_theme():
    """figures.mplstyle gives every rcParam seaborn's set_theme(**STYLE) sets (image.cmap
    aside: no figure draws an image), so figures look the same without importing seaborn."""
    import matplotlib as mpl
    import seaborn as sns
    from matplotlib.colors import to_hex

    def themed(apply) -> dict:
        with mpl.rc_context():
            mpl.rcdefaults()
            before = dict(mpl.rcParams)
            apply()
            return {k: v for k, v in mpl.rcParams.items() if before.get(k) != v}

    want = themed(lambda: sns.set_theme(**figures.STYLE))
    got = themed(figures.apply_style)
    want.pop("image.cmap")
    assert set(got) == set(want)
    for key, value in want.items():
        if key == "axes.prop_cycle":
            assert [to_hex(c) for c in got[key].by_key()["color"]] == \
                [to_hex(c) for c in value.by_key()["color"]]
        elif isinstance(value, float):
            assert got[key] == pytest.approx(value, rel=1e-6), key
        else:
            assert str(got[key]) == str(value), key


def test_a_figure_without_boxen_plots_does_not_import_seaborn():
    code = ("import sys, twinfalsify.figures as f, twinfalsify.summary; "
            "assert 'seaborn' not in sys.modules and 'scipy.stats' not in sys.modules, "
            "sorted(m for m in sys.modules if m.startswith(('seaborn', 'scipy.stats')))[:5]")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.parametrize("correction", ["holm", "by", "bonferroni", "none"])
def test_the_threshold_line_separates_the_corrections_decisions(correction):
    """Every p the correction rejects is <= the drawn cut, every other p is above it, on
    random, tied and all-null families (the decisions of ``multiple_testing.correct``)."""
    from twinfalsify.inference.multiple_testing import correct

    rng = np.random.default_rng(5)
    for trial in range(300):
        m = int(rng.integers(1, 60))
        p = rng.uniform(0, 1, m) ** rng.uniform(1, 12)
        if trial % 3 == 0:
            p = np.round(p, 2)  # ties
        if trial % 10 == 0:
            p = np.ones(m)  # nothing to reject (the oracle)
        alpha = float(rng.choice([0.01, 0.05, 0.2]))
        rej = correct(p, alpha, correction)
        cut = figures.rejection_threshold(p, correction, alpha)
        assert (p[rej] <= cut).all() and (p[~rej] > cut).all(), (correction, m, alpha)
    assert figures.rejection_threshold(np.ones(20), "holm", 0.05) == pytest.approx(0.05 / 20)


def test_an_all_null_panel_shows_the_threshold_from_zero():
    """The oracle: every p = 1. The panel runs from 0 to above the Holm cut alpha / m, with
    the line, instead of a +-0.04 band around the zeros."""
    res = pd.DataFrame([{"hyp_id": i, "kind": "causal", "outcome": "HR", "t": 1, "side": side,
                         "method": "hoeffding", "p_value": 1.0, "p_floor": False,
                         "rejected": False, "correction": "holm", "alpha": 0.05}
                        for i in range(50) for side in ("lo", "up")])  # fmt: skip
    fig = figures.pvalue_boxen_methods(res, title="twin oracle: p-values")
    cut_y = -np.log10(0.05 / 100)
    for ax in fig.axes:
        lo, hi = ax.get_ylim()
        assert -0.5 < lo <= 0 and hi > cut_y
        ys = [ln.get_ydata()[0] for ln in ax.get_lines() if len(ln.get_ydata()) == 2]
        assert any(np.isclose(y, cut_y) for y in ys)
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert labels == ["Holm threshold, alpha = 0.05: 0 of 50 rejected"]


def test_every_twin_figure_names_its_twin_and_its_unit(st):
    """Propensity, sample sizes, histograms and sensitivity say which twin they show; panels
    counting parameter sets say so."""
    fig = figures.sample_size_strips(st.results, twin="biased")
    n_sets = st.results[st.results["kind"] == "causal"]["hyp_id"].nunique()
    assert fig.get_suptitle() == f"twin biased: sample sizes of the {n_sets} causal parameter sets"
    assert fig.axes[0].get_ylabel() == "outcome"
    assert all(f"of {n_sets} sets at 0" in ax.get_title() for ax in fig.axes)
    fig = figures.propensity_scatter(st.results, twin="biased")
    assert fig.get_suptitle().startswith("twin biased: ")
    assert all("parameter sets rejected" in ax.get_title() for ax in fig.axes)
    hid = summary.pick_hypothesis(st.results, rejected=True, prefer_long=False)
    case = summary.histogram_data(st, hid, alpha=0.05)
    fig = figures.outcome_histograms([case], twin="biased", methods=["hoeffding", "betting"],
                                     alpha=0.05)  # fmt: skip
    assert fig.get_suptitle().startswith("twin biased: ")
    top, strip = fig.axes
    assert "min p over hoeffding, betting = " in top.get_title()
    assert strip.get_title() == "Hoeffding intervals (one-sided 0.975, unadjusted)"
