"""Adaptive shards on a small synthetic study: same decisions as the in-memory procedure,
every simulated run accounted for, twin values equal to the fixed scheme's."""

from __future__ import annotations

import io
import json

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV
from helpers.studies import build_study

from twinfalsify import bounds
from twinfalsify.bounds import twin_runs_indexed
from twinfalsify.design import WHOLE_SPACE
from twinfalsify.falsify import adaptive_test
from twinfalsify.runs import plan as tp
from twinfalsify.runs.adaptive import (
    adaptive_results,
    budget_warning,
    run_adaptive_shard,
    shard_hypotheses,
)
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURES
from twinfalsify.twins.base import SimResult


@pytest.fixture(scope="module")
def study_and_twin(tmp_path_factory):
    study = build_study(1500, 11, d0_fraction=0.2, min_support=5, runs=300)
    tmp = tmp_path_factory.mktemp("adaptive")
    study.d0.to_parquet(tmp / "d0.parquet")
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}},
           "d0": str(tmp / "d0.parquet")}
    twin = make_twin("biased", {"kind": "biased", "shift": {"HR": 25.0}}, ctx)
    runs = pd.concat([tp.run_shard(twin, study.plan, k, study.x0, study.actions,
                                   log=io.StringIO()) for k in range(len(study.plan.shards))],
                     ignore_index=True)
    (tmp / "twin_context.json").write_text(json.dumps(ctx))
    return study, twin, runs, tmp / "twin_context.json"


def test_indexed_twin_side_agrees_with_bounds(study_and_twin):
    study, _, runs, _ = study_and_twin
    nodes = tp.load_nodes(runs, study.plan, study.x0)
    ref = bounds.twin_runs(study.hyps, nodes, study.states).values
    got = twin_runs_indexed(study.hyps, nodes, study.states)
    np.testing.assert_array_equal(got.values.offsets, ref.offsets)
    np.testing.assert_array_equal(got.values.values, ref.values)
    # run positions increase within every hypothesis (X_0 order)
    d = np.diff(got.run)
    starts = got.values.offsets[1:-1]
    inner = np.ones(len(d), bool)
    inner[starts[starts > 0] - 1] = False
    assert np.all(d[inner] > 0)


@pytest.mark.slow
def test_adaptive_shards_reproduce_the_in_memory_procedure(study_and_twin):
    combine = "union"
    study, twin, runs, _ = study_and_twin
    nodes = tp.load_nodes(runs, study.plan, study.x0)
    shard_of = np.zeros(len(study.hyps), np.int64)
    for k in range(len(study.plan.shards)):
        shard_of[shard_hypotheses(study.hyps, study.plan, k)] = k
    ref = adaptive_test(study.hyps, study.obs, nodes, study.states, batch_size=40,
                        shards=shard_of, combine=combine)
    decs, rows, hours = [], [], 0
    for k in range(len(study.plan.shards)):
        r, dec, summary = run_adaptive_shard(
            twin, study.plan, k, study.x0, study.actions, study.hyps, study.obs, study.states,
            batch_size=40, combine=combine, log=io.StringIO())
        decs.append(dec)
        rows.append(r)
        hours += summary["twin_hours_adaptive"]
    dec = pd.concat(decs).set_index("hyp_id").loc[study.hyps["hyp_id"]]
    assert len(dec) == len(study.hyps)  # every hypothesis decided by exactly one shard
    rtol = 1e-12
    np.testing.assert_allclose(dec["p_lo"], ref.p_lo, rtol=rtol)
    np.testing.assert_allclose(dec["p_up"], ref.p_up, rtol=rtol)
    np.testing.assert_array_equal(dec["runs_used"], ref.runs_per_hypothesis)
    assert hours == ref.twin_hours_adaptive < ref.twin_hours_fixed
    # every simulated row equals the fixed scheme's row for the same (node, X_0)
    sim = pd.concat(rows, ignore_index=True)
    assert not sim.duplicated(["node", "init_stay_id"]).any()
    assert len(sim) == hours
    both = sim.merge(runs, on=["node", "init_stay_id"], suffixes=("", "_fixed"))
    assert len(both) == len(sim)
    assert (both["status"] == both["status_fixed"]).all()
    np.testing.assert_allclose(both["HR"], both["HR_fixed"], rtol=1e-12)
    # the biased twin is rejected somewhere, and stopping saved runs
    assert (ref.rejected_lo | ref.rejected_up).any()


def test_adaptive_batches_let_a_save_restore_twin_branch_shared_prefixes(study_and_twin,
                                                                          tmp_path):
    """A protocol twin gets each batch in one call, so an engine that keeps the dose prefixes
    of one X_0 at a time (the Pulse worker) simulates exactly the node-runs the summary
    reports, with depth truncation (``--truncate``, as the Pulse worker) or without.
    Simulating each node's runs in a call of its own (a fresh pool each time, the X_0's
    sequences apart) made such an engine simulate shared prefixes again."""
    study = study_and_twin[0]
    got = {}
    for truncate in (False, True):
        log = tmp_path / f"engine-hours-{truncate}.txt"
        twin = ProtocolTwin("faulty", [*FAULTY_TWIN, f"--engine-hours={log}", "--batch=16",
                                       "--wobble=0.05", *(["--truncate"] if truncate else [])],
                            workers=2, env=ENV, progress=False)
        node_runs = requested = 0
        decisions = []
        for k in range(len(study.plan.shards)):
            _, dec, summary = run_adaptive_shard(
                twin, study.plan, k, study.x0, study.actions, study.hyps, study.obs,
                study.states, batch_size=40, correction="by", log=io.StringIO())
            node_runs += summary["twin_hours_adaptive"]
            requested += summary["twin_hours_requested"]
            assert summary["depth_truncation"] is truncate
            decisions.append(dec)
        engine = sum(int(v) for v in log.read_text().split())
        assert requested > node_runs  # sibling sequences share prefixes: the test has teeth
        assert engine == node_runs
        got[truncate] = (node_runs, pd.concat(decisions, ignore_index=True))
    assert got[True][0] < got[False][0]  # runs that left every B-set were cut short
    pd.testing.assert_frame_equal(got[True][1], got[False][1])  # decisions unchanged


def test_a_budget_too_small_to_reject_spends_no_twin_time_and_says_so(study_and_twin):
    """Four runs per sequence cannot reach Holm's level: every parameter set is futile before
    any run, no twin hour is spent, and the shard's log line names the setting to raise. The
    fixture's budget (300) can test, and gets no warning."""
    study, twin = study_and_twin[:2]
    small = build_study(1500, 11, d0_fraction=0.2, min_support=5, runs=4)
    _, dec, summary = run_adaptive_shard(
        twin, small.plan, 0, small.x0, small.actions, small.hyps, small.obs, small.states,
        batch_size=2, log=io.StringIO())
    assert summary["twin_hours_adaptive"] == 0 and (dec["runs_used"] == 0).all()
    assert summary["futile_without_runs"] == summary["parameter_sets"] > 0
    msg = budget_warning(summary)
    assert "no outcome of 4 runs per sequence" in msg and "runs_per_sequence" in msg
    _, _, big = run_adaptive_shard(
        twin, study.plan, 0, study.x0, study.actions, study.hyps, study.obs, study.states,
        batch_size=100, log=io.StringIO())
    assert big["twin_hours_adaptive"] > 0
    assert big["futile_without_runs"] < big["parameter_sets"] and budget_warning(big) is None


def test_simulate_jobs_keeps_one_result_per_job_in_order(study_and_twin):
    """Jobs without rows get empty results in their place; every other job's values are its
    own sequence's, for the rows asked, in-process and through the protocol alike."""
    study, twin, _, _ = study_and_twin
    seeds = study.plan.run_seeds()
    seqs = [tp.parse_node(leaf) for leaf in study.plan.shards[0]][:2]
    jobs = [(seqs[0], np.array([3, 1, 7])), (seqs[1], np.array([], int)), (seqs[1], np.arange(4))]
    served = ProtocolTwin("faulty", FAULTY_TWIN, env=ENV, progress=False)
    for tw in (twin, served):
        got = tp.simulate_jobs(tw, jobs, study.x0, seeds, study.actions, io.StringIO())
        assert [g[0].shape for g in got] == [(3, len(seqs[0]), len(FEATURES)),
                                             (0, len(seqs[1]), len(FEATURES)),
                                             (4, len(seqs[1]), len(FEATURES))]
        for (seq, rows), (feats, status, _, _) in zip(jobs, got, strict=True):
            doses = np.broadcast_to(study.actions.doses(np.asarray(seq)), (rows.size, len(seq), 2))
            want = tw.simulate(study.x0.iloc[rows].reset_index(drop=True), doses.copy(),
                               seeds[rows])
            np.testing.assert_array_equal(feats, want.features)
            assert (status == "ok").all()


def test_depth_truncation_drops_only_hours_no_hypothesis_can_use(study_and_twin):
    """Brute force over hypotheses, runs and hours: node a_1:s of run j is kept iff some
    hypothesis using it has j revealed, X_0 in B_0 and every earlier hour of its path in
    B_s' (or failed: it cannot be shown to have left); and hours are saved."""
    study, twin, runs, ctx = study_and_twin
    nodes = tp.load_nodes(runs, study.plan, study.x0)
    hyps, states = study.hyps, study.states
    # BY: no Holm-aware futility, so more hypotheses run long enough to leave B-sets
    ref = adaptive_test(hyps, study.obs, nodes, states, batch_size=40, correction="by")
    assert ref.twin_hours_adaptive < ref.twin_hours_untruncated  # the test has teeth
    want = np.zeros(nodes.values.shape[:2], bool)
    base0 = states.base_codes(nodes.x0)
    for h, row in enumerate(hyps.itertuples()):
        k = FEATURES.index(row.outcome)
        seq = tuple(int(a) for a in row.actions)
        code0 = base0 + states.above(row.outcome, nodes.x0[:, k], 0)
        for j in range(ref.runs_per_hypothesis[h]):
            if row.bins[0] not in (WHOLE_SPACE, code0[j]):
                continue
            for s in range(1, len(seq) + 1):
                want[nodes.index[seq[:s]], j] = True
                v = nodes.values[nodes.index[seq[:s]], j, k]
                code = base0[j] + states.above(row.outcome, v, s)
                if not np.isnan(v) and row.bins[s] not in (WHOLE_SPACE, code):
                    break  # left B_s: later hours cannot matter to h
    assert ref.twin_hours_adaptive == want.sum()
    np.testing.assert_array_equal(ref.runs_used, want.sum(axis=1))
    # the shards keep exactly these node rows and decide the same: an in-process twin, and
    # the same twin served over the protocol (it advertises truncate: the requests carry
    # box paths, and it stops runs that no longer need hours)
    served = make_twin("biased", {"kind": "biased", "shift": {"HR": 25.0}, "protocol": True,
                                  "workers": 2}, ctx)
    assert served.truncates
    for tw in (twin, served):
        rows, decs = [], []
        for k in range(len(study.plan.shards)):
            r, dec, summary = run_adaptive_shard(
                tw, study.plan, k, study.x0, study.actions, hyps, study.obs, states,
                batch_size=40, correction="by", log=io.StringIO())
            assert summary["depth_truncation"] and summary["twin_hours_adaptive"] == len(r)
            rows.append(r)
            decs.append(dec)
        sim = pd.concat(rows, ignore_index=True)
        assert (sim["status"] == "ok").all()
        got = np.zeros_like(want)
        got[sim["node"].map(lambda n: nodes.index[tp.parse_node(n)]),
            sim["init_stay_id"].map({s: j for j, s in enumerate(study.plan.x0_stay_ids)})] = True
        np.testing.assert_array_equal(got, want)
        dec = pd.concat(decs).set_index("hyp_id").loc[hyps["hyp_id"]]
        np.testing.assert_array_equal(dec["runs_used"], ref.runs_per_hypothesis)
        np.testing.assert_allclose(dec["p_lo"], ref.p_lo, rtol=1e-12)


class _Flaky:
    """The wrapped twin, with every run whose seed is 0 mod 3 failed (status error, no hours)."""

    def __init__(self, twin):
        self.twin, self.name = twin, "flaky"

    def simulate(self, x0, doses, seeds):
        res = self.twin.simulate(x0, doses, seeds)
        bad = np.asarray(seeds, np.uint64) % np.uint64(3) == 0
        res.features[bad] = np.nan
        return SimResult(res.features, np.where(bad, "error", res.status), res.message,
                         res.clamped)


@pytest.mark.slow
def test_failed_runs_are_worst_case_in_the_shards_as_in_memory(study_and_twin):
    """``testing.failed_runs`` reaches the shards: with failing runs, conservative and drop
    shards each reproduce the in-memory procedure, conservative p-values are the larger ones
    (the same runs decide: the stops may differ), and the results table says which was used."""
    study, twin, _, _ = study_and_twin
    flaky = _Flaky(twin)
    fixed = pd.concat([tp.run_shard(flaky, study.plan, k, study.x0, study.actions,
                                    log=io.StringIO()) for k in range(len(study.plan.shards))],
                      ignore_index=True)
    nodes = tp.load_nodes(fixed, study.plan, study.x0)
    shard_of = np.zeros(len(study.hyps), np.int64)
    for k in range(len(study.plan.shards)):
        shard_of[shard_hypotheses(study.hyps, study.plan, k)] = k
    got = {}
    for mode in ("conservative", "drop"):
        ref = adaptive_test(study.hyps, study.obs, nodes, study.states, batch_size=40,
                            shards=shard_of, failed_runs=mode)
        decs = [run_adaptive_shard(flaky, study.plan, k, study.x0, study.actions, study.hyps,
                                   study.obs, study.states, batch_size=40, failed_runs=mode,
                                   log=io.StringIO())[1] for k in range(len(study.plan.shards))]
        dec = pd.concat(decs).set_index("hyp_id").loc[study.hyps["hyp_id"]]
        np.testing.assert_allclose(dec["p_lo"], ref.p_lo, rtol=1e-12)
        np.testing.assert_allclose(dec["p_up"], ref.p_up, rtol=1e-12)
        np.testing.assert_array_equal(dec["runs_used"], ref.runs_per_hypothesis)
        assert dec["n_failed"].sum() > 0
        res = adaptive_results(study.hyps, study.obs, nodes, study.states, dec.reset_index(),
                               failed_runs=mode)
        assert set(res["failed_runs"]) == {mode}
        got[mode] = ref
    cons, drop = got["conservative"], got["drop"]
    assert (cons.p_lo > drop.p_lo * 1.01).any() or (cons.p_up > drop.p_up * 1.01).any()
    n_rejected = {k: (o.rejected_lo | o.rejected_up).sum() for k, o in got.items()}
    assert n_rejected["conservative"] <= n_rejected["drop"]


def test_product_rule_is_refused_by_the_shard(study_and_twin):
    """combine: product was withdrawn (it exceeded its level with shared X_0): a shard asked
    for it stops with the reason before any run, instead of warning and running it."""
    twin = study_and_twin[1]
    small = build_study(1500, 11, d0_fraction=0.2, min_support=5, runs=4)
    log = io.StringIO()
    with pytest.raises(ValueError, match="combine: product was removed: it can exceed its level"):
        run_adaptive_shard(twin, small.plan, 0, small.x0, small.actions, small.hyps, small.obs,
                           small.states, batch_size=2, combine="product", log=log)
    assert "sequence" not in log.getvalue()  # nothing was simulated
