"""Calibration harness: building blocks checked against independent computations,
and a tiny end-to-end run with known answers."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from twinfalsify import calibration as cal
from twinfalsify.falsify import adaptive_test
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.runs import plan as tp
from twinfalsify.schema import OUTCOMES, ContractError
from twinfalsify.twins.builtin import BiasedTwin

TINY = dict(
    replicates=4,
    chunks=2,
    n_stays=1000,
    d0_fraction=0.2,
    min_support=10,
    runs_per_sequence=150,
    methods={"hoeffding": {}, "bootstrap": {"n_resamples": 50}, "betting": {}, "bernstein": {}},
    bias_sizes=[0.0, 8.0],
    coverage_per_replicate=2,
    coverage_population=15_000,
    coverage_min_inside=100,
    adaptive=True,
    adaptive_batch_size=25,
)


@pytest.fixture(scope="module")
def tiny_cfg() -> cal.CalibrationConfig:
    return cal.CalibrationConfig.from_dict(TINY)


@pytest.fixture(scope="module")
def tiny_run(tiny_cfg):
    return cal.run_replicates(tiny_cfg, list(range(tiny_cfg.replicates)))


def test_shifted_nodes_equal_the_biased_twin(tiny_cfg):
    """Deriving a biased twin from the oracle's runs = running BiasedTwin(shift=...) itself."""
    rep = cal.build_replicate(tiny_cfg, tiny_cfg.replicate_seed(0))
    bias, feats = 0.7, ("HR", "Sodium", "Arterial_pH")
    derived = cal.shifted_nodes(rep, bias, feats)
    twin = BiasedTwin(rep.world, shift={k: bias * rep.outcome_sd[k] for k in feats})
    runs = tp.run_shard(twin, rep.plan, 0, rep.x0, rep.actions, log=io.StringIO())
    direct = tp.load_nodes(runs, rep.plan, rep.x0)
    assert derived.index == direct.index
    np.testing.assert_allclose(derived.values, direct.values, rtol=0, atol=1e-9)
    assert not np.allclose(derived.values, rep.nodes.values)  # the shift did something
    assert cal.shifted_nodes(rep, 0.0, feats) is rep.nodes


def test_welch_pvalues_match_scipy_per_hypothesis():
    rng = np.random.default_rng(3)
    follow = [rng.normal(0, 1, n) for n in (5, 30, 1, 12, 40)]
    twin = [rng.normal(0.5, 2, n) for n in (8, 25, 10, 0, 40)]
    twin[4] = np.full(40, 0.3)
    follow[4] = np.full(40, 0.3)  # both constant and equal: undefined -> 1
    s = HypothesisSamples(
        y_lo=np.full(5, -10.0), y_up=np.full(5, 10.0), n=np.array([9, 40, 3, 20, 50]),
        follow=Ragged.from_groups(follow), twin=Ragged.from_groups(twin),
    )  # fmt: skip
    p = cal.welch_pvalues(s)
    for h in (0, 1):
        want = stats.ttest_ind(twin[h], follow[h], equal_var=False).pvalue
        assert p[h] == pytest.approx(want, rel=1e-9)
    assert p[2] == 1 and p[3] == 1 and p[4] == 1  # < 2 values, or zero variance


def test_summarise_rates_and_clopper_pearson_intervals():
    tests = pd.DataFrame({
        "replicate": np.arange(20), "bias": 0.0, "method": "hoeffding", "kind": "causal",
        "n_tests": 10, "n_testable": 10, "n_rejected": [1] * 3 + [0] * 17,
    })  # fmt: skip
    tests["any_rejected"] = tests["n_rejected"] > 0
    row = cal.summarise(tests).iloc[0]
    ci = stats.binomtest(3, 20).proportion_ci(0.95, method="exact")
    assert row["any_rejection_rate"] == pytest.approx(0.15)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx((ci.low, ci.high))
    assert row["mean_share_rejected"] == pytest.approx(0.015)
    assert row["valid"]  # CI [0.03, 0.38] reaches below 0.05
    tests["n_rejected"] = [1] * 12 + [0] * 8  # 60 %: whole CI above 0.05 -> fails
    tests["any_rejected"] = tests["n_rejected"] > 0
    assert not cal.summarise(tests).iloc[0]["valid"]


def test_dominance_compares_paired_rates():
    rows = []
    for method, rej in (("betting", [2, 5]), ("hoeffding", [1, 6])):
        for bias, k in zip((1.0, 2.0), rej, strict=True):
            rows.append(dict(method=method, kind="manski", bias=bias, mean_rejections=float(k),
                             any_rejection_rate=1.0))  # fmt: skip
    dom = cal.dominance(pd.DataFrame(rows))
    assert dom.set_index("bias")["at_least_as_often"].to_dict() == {1.0: True, 2.0: False}


def test_chunks_partition_the_replicates_and_seeds_do_not_depend_on_chunking(tiny_cfg):
    got = sorted(r for c in range(tiny_cfg.chunks) for r in cal.chunk_replicates(tiny_cfg, c))
    assert got == list(range(tiny_cfg.replicates))
    other = cal.CalibrationConfig.from_dict({**TINY, "chunks": 3})
    assert [other.replicate_seed(r) for r in range(4)] == [
        tiny_cfg.replicate_seed(r) for r in range(4)
    ]
    assert len({tiny_cfg.replicate_seed(r) for r in range(100)}) == 100
    with pytest.raises(ContractError, match="chunk 2 out of range"):
        cal.chunk_replicates(tiny_cfg, 2)


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"bogus": 1}, "unknown key"),
        ({"bias_sizes": [1.0, 2.0]}, "bias_sizes must include 0"),
        ({"bias_features": ["HR", "Spleen"]}, "Spleen"),
        ({"adaptive_batch_size": 0}, "adaptive_batch_size"),
        ({"adaptive_curtail": 1.0}, "adaptive_curtail"),
        ({"adaptive_curtail": -0.1}, "adaptive_curtail"),
        ({"adaptive_curtail": "0.01"}, "adaptive_curtail"),
        ({"adaptive_combine": "sum"}, "adaptive_combine must be one of union"),
        ({"adaptive_combine": "product"}, "combine: product was removed: it can exceed its level"),
        ({"adaptive": "yes"}, "adaptive must be true or false"),
        ({"d0_fraction": 1.5}, "d0_fraction"),
    ],
)
def test_bad_config_names_file_and_key(tmp_path, patch, message):
    import yaml

    path = tmp_path / "calibration.yaml"
    path.write_text(yaml.safe_dump({**TINY, **patch}))
    with pytest.raises(ContractError, match=message) as err:
        cal.load_config(str(path))
    assert str(path) in str(err.value)


def test_tiny_run_tables_and_known_answers(tiny_run, tiny_cfg):
    tests, cov, wid = tiny_run["tests"], tiny_run["coverage"], tiny_run["widths"]
    assert tuple(tests.columns) == cal.TEST_COLUMNS
    assert tuple(cov.columns) == cal.COVERAGE_COLUMNS
    assert tuple(wid.columns) == cal.WIDTH_COLUMNS
    methods = set(tiny_cfg.methods) | {cal.NAIVE, cal.ADAPTIVE}
    # every replicate x bias x method x kind present exactly once
    assert len(tests) == 4 * 2 * len(methods) * 2
    assert not tests.duplicated(["replicate", "bias", "method", "kind"]).any()
    summary = cal.summarise(tests)
    assert summary["any_rejection_rate"].between(0, 1).all()
    oracle = summary[(summary["bias"] == 0) & summary["method"].isin(cal.EXACT_METHODS)]
    assert cal.ADAPTIVE in set(oracle["method"])
    assert (oracle["mean_rejections"] == 0).all()  # no exact method rejects the oracle
    # a huge bias (8 SDs on every outcome) is found by every method on the Manski family
    huge = summary[(summary["bias"] == 8.0) & (summary["kind"] == "manski")]
    assert set(huge["method"]) == methods
    assert (huge["any_rejection_rate"] == 1).all()
    # the pitfall: the naive comparison rejects the correct (oracle) twin under confounding
    naive = summary[(summary["method"] == cal.NAIVE) & (summary["bias"] == 0)]
    assert naive["mean_rejections"].sum() > 0
    # coverage: the theorem holds for the population bounds (up to MC error)
    assert len(cov) >= 4 and cov["covered_mc"].all()
    assert (cov["q_lo_pop"] <= cov["q_up_pop"]).all()
    # widths: conditioning on B never widens the bound vs Manski here, both in (0, 1)
    w = wid.groupby("kind")["mean_width_ratio"].mean()
    assert 0 < w["causal"] < w["manski"] < 1


def test_markdown_summary_reports_the_tables(tiny_run, tiny_cfg):
    summary = cal.summarise(tiny_run["tests"])
    md = cal.markdown_summary(
        tiny_cfg, summary, cal.dominance(summary), tiny_run["coverage"], tiny_run["widths"],
        tiny_run["timing"], tiny_run["adaptive"],
    )  # fmt: skip
    assert "Family-wise error of the oracle twin" in md
    assert "## Adaptive twin runs (betting_sequential, batches of 25)" in md
    assert "| betting_sequential | causal |" in md
    assert "Exact methods failing calibration: none." in md
    assert "Betting rejects at least as often as Hoeffding" in md
    for m in cal.EXACT_METHODS:
        assert f"| {m} | causal |" in md
    assert set(OUTCOMES) >= set(tiny_cfg.bias_features)


@pytest.mark.parametrize(("curtail", "combine"), [(0.0, "union"), (0.2, "union")])
def test_run_adaptive_equals_adaptive_test(tiny_cfg, curtail, combine):
    """The shared observational state per replicate changes nothing: same outcome as
    ``sequential.adaptive_test`` called afresh, for the oracle and a biased twin (with the
    harness's ``adaptive_curtail`` passed through)."""
    tiny_cfg = replace(tiny_cfg, adaptive_curtail=curtail, adaptive_combine=combine)
    rep = cal.build_replicate(tiny_cfg, tiny_cfg.replicate_seed(1))
    base = cal.adaptive_state(tiny_cfg, rep)
    for bias in (0.0, 1.5):  # 0 first: a mutated shared state would show at 1.5
        nodes = cal.shifted_nodes(rep, bias, tiny_cfg.bias_features)
        got = cal.run_adaptive(tiny_cfg, rep, nodes, base)
        want = adaptive_test(rep.hyps, rep.obs, nodes, rep.states, batch_size=25,
                             alpha=tiny_cfg.alpha, correction=tiny_cfg.correction, seed=rep.seed,
                             curtail=curtail, combine=combine)
        for f in ("p_lo", "p_up", "stop_batch", "runs_used", "runs_per_hypothesis", "decision",
                  "nhat", "rejected_lo", "rejected_up"):  # fmt: skip
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f)
        assert (got.twin_hours_adaptive, got.twin_hours_fixed) == (
            want.twin_hours_adaptive, want.twin_hours_fixed)
        assert want.twin_hours_fixed == len(rep.nodes.index) * tiny_cfg.runs_per_sequence
    assert (base.stop_batch[rep.obs.n > 0] == -1).all()  # the shared state was not mutated


def test_tiny_run_adaptive_rows(tiny_run, tiny_cfg):
    """Adaptive rows present per replicate, kind and bias; the oracle is never rejected;
    a huge bias is; twin-hours are those of the runs revealed (ratio in (0, 1])."""
    tests, ad = tiny_run["tests"], tiny_run["adaptive"]
    seq = tests[tests["method"] == cal.ADAPTIVE]
    assert len(seq) == tiny_cfg.replicates * 2 * 2  # replicate x bias x kind
    assert (seq[seq["bias"] == 0]["n_rejected"] == 0).all()
    huge = seq[(seq["bias"] == 8.0) & (seq["kind"] == "manski")]
    assert huge["any_rejected"].all()
    assert tuple(ad.columns) == cal.ADAPTIVE_COLUMNS
    assert len(ad) == tiny_cfg.replicates * 2 and not ad.duplicated(["replicate", "bias"]).any()
    assert ((ad["hours_ratio"] > 0) & (ad["hours_ratio"] <= 1)).all()
    ratio = ad["twin_hours_adaptive"] / ad["twin_hours_fixed"]
    np.testing.assert_allclose(ad["hours_ratio"], ratio)
    assert (ad["twin_hours_fixed"] == ad["n_nodes"] * tiny_cfg.runs_per_sequence).all()
    # without B_0 skipping twin-hours are whole batches per node (budget 150 = 6 x 25);
    # skipping X_0 outside every running B_0 only removes runs; the paper's scheme costs most
    assert (ad["twin_hours_all_x0"] % tiny_cfg.adaptive_batch_size == 0).all()
    assert (ad["twin_hours_adaptive"] <= ad["twin_hours_all_x0"]).all()
    # (no strict saving asserted here: a node used by a running Manski hypothesis, B_0 = all,
    # needs every X_0, which in this tiny run is every node; test_sequential covers skipping)
    assert (ad["twin_hours_paper"] >= ad["twin_hours_fixed"]).all()
    # rejections per replicate and bias agree between the two tables (both kinds)
    per = seq.groupby(["replicate", "bias"])["n_rejected"].sum()
    assert (ad.set_index(["replicate", "bias"])["n_rejected"] == per).all()
    # kept <= both counts; kept rejections of the fixed betting test are most of them
    assert (ad["n_kept_betting"] <= ad["n_rejected_betting"]).all()
    assert (ad["n_kept_betting"] <= ad["n_rejected"]).all()
    asum = cal.adaptive_summary(ad).set_index("bias")
    assert np.isnan(asum.loc[0.0, "kept_share_betting"])  # nothing to keep at the oracle
    assert asum.loc[0.0, "target_rejections"] is pd.NA
    want = ad[ad.bias == 8.0]
    assert asum.loc[8.0, "kept_share_betting"] == pytest.approx(
        want["n_kept_betting"].sum() / want["n_rejected_betting"].sum())
    assert asum.loc[8.0, "hours_ratio"] == pytest.approx(
        want["twin_hours_adaptive"].sum() / want["twin_hours_fixed"].sum())
    table = cal.attach_hours(cal.summarise(tests), asum.reset_index())
    rows = table[table["method"] == cal.ADAPTIVE]
    assert rows["hours_ratio"].notna().all() and table[table["method"] != cal.ADAPTIVE][
        "hours_ratio"].isna().all()


def test_adaptive_summary_kept_share_and_target_known_answer():
    """Pooled ratios and the target, worked by hand on two replicates."""
    ad = pd.DataFrame([
        (0, 1.0, 25, 400, 10, 300, 4000, 0.075, 9, 10, 9, 4, 4, 0, 0.1, 600, 8000),
        (1, 1.0, 25, 400, 10, 500, 4000, 0.125, 10, 10, 9, 4, 3, 2, 0.2, 1000, 8000),
        (0, 2.0, 25, 400, 10, 400, 4000, 0.1, 3, 4, 3, 0, 0, 0, 0.1, 800, 8000),
        (1, 2.0, 25, 400, 10, 400, 4000, 0.1, 1, 1, 1, 0, 0, 0, 0.1, 800, 8000),
    ], columns=list(cal.ADAPTIVE_COLUMNS))  # fmt: skip
    s = cal.adaptive_summary(ad).set_index("bias")
    assert s.loc[1.0, "hours_ratio"] == pytest.approx(800 / 8000)  # pooled: met at exactly 1/10
    assert s.loc[1.0, "hours_ratio_max"] == pytest.approx(0.125)
    assert s.loc[1.0, "hours_ratio_all_x0"] == pytest.approx(1600 / 8000)
    assert s.loc[1.0, "hours_ratio_paper"] == pytest.approx(800 / 16000)
    assert s.loc[1.0, "kept_share_betting"] == pytest.approx(18 / 20)
    assert s.loc[1.0, "kept_share_hoeffding"] == pytest.approx(7 / 8)
    assert s.loc[1.0, "target_hours"] and s.loc[1.0, "target_rejections"]  # 0.9 >= 0.9
    assert s.loc[2.0, "kept_share_betting"] == pytest.approx(4 / 5)
    assert not s.loc[2.0, "target_rejections"]
    assert np.isnan(s.loc[2.0, "kept_share_hoeffding"])
    md = "\n".join(cal.adaptive_markdown(s.reset_index()))
    assert "met at bias level(s): 1." in md
