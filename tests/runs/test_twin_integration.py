"""Twin layer in the study: builtin twins over the protocol, command twins in shards."""

from __future__ import annotations

import io
import json
import sys

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from fakes.faulty_twin import expected
from helpers.paths import TESTS
from helpers.studies import build_study

from twinfalsify.design import ActionBins
from twinfalsify.pulse.replay import RecordedPulse
from twinfalsify.runs import plan as tp
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURES, STAY_ID
from twinfalsify.summary import clamp_shares

PULSE_FIXTURE = TESTS / "fixtures" / "pulse-reference"
SRC = str(TESTS.parent / "src")
ENV = {"PYTHONPATH": SRC}


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    study = build_study(1500, 11, d0_fraction=0.2, min_support=8, runs=20)
    folder = tmp_path_factory.mktemp("ctx")
    study.d0.to_parquet(folder / "d0.parquet")
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 1500}},
           "d0": str(folder / "d0.parquet")}
    (folder / "twin_context.json").write_text(json.dumps(ctx))
    return study, folder / "twin_context.json"


def _all_shards(twin, study) -> pd.DataFrame:
    return pd.concat(
        [tp.run_shard(twin, study.plan, k, study.x0, study.actions, log=io.StringIO())
         for k in range(len(study.plan.shards))],
        ignore_index=True,
    )


@pytest.mark.parametrize("spec", [
    {"kind": "oracle"},
    {"kind": "biased", "shift": {"HR": 15.0}, "dose_effect": {"vasopressor": 2.0}},
    {"kind": "fitted", "inputs": "init", "residual_noise": True},
], ids=["oracle", "biased", "fitted"])  # fmt: skip
def test_protocol_twin_is_bit_identical_to_in_process(small_study, spec):
    study, ctx = small_study
    local = make_twin("t", spec, ctx)
    served = make_twin("t", {**spec, "protocol": True, "workers": 2, "timeout_s": 30}, ctx)
    assert isinstance(served, ProtocolTwin) and served.workers == 2
    assert "twinfalsify.runs.serve" in served.command
    served.progress = False
    a, b = _all_shards(local, study), _all_shards(served, study)
    assert len(a) == len(study.plan.nodes) * len(study.plan.x0_stay_ids)
    if spec["kind"] == "fitted":
        # a linear twin with residual noise leaves the contract's ranges on this small study
        # (paO2 < 0 mmHg): those runs are implausible, the same ones served and in-process
        assert set(a["status"]) <= {"ok", "implausible"}
    else:
        assert (a["status"] == "ok").all()
    # FittedTwin sums its linear predictor in a fixed order, so batching never changes bits
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_protocol_builtin_needs_a_context_file(small_study):
    from twinfalsify.schema import ContractError

    with pytest.raises(ContractError, match="twin context"):
        make_twin("o", {"kind": "oracle", "protocol": True}, {"source": {}})


def _hand_plan(x0_ids: list[int], leaves: list[str], seed: int = 5) -> tp.TwinPlan:
    nodes = sorted({tp.node_name(tp.parse_node(leaf)[:s]) for leaf in leaves
                    for s in range(1, len(tp.parse_node(leaf)) + 1)})
    return tp.TwinPlan(x0_stay_ids=x0_ids, seed=seed, shards=[leaves], nodes=nodes)


@pytest.mark.slow  # three 1 s timeouts plus worker restarts
def test_faulty_command_twin_every_node_accounted(small_study):
    """Crash, hang, garbage, irreversible, init_failed, clamp: each run's nodes get the
    right status; hours completed before a failure stay usable for earlier nodes."""
    study, _ = small_study
    x0 = study.x0.iloc[:7].reset_index(drop=True).copy()
    x0.loc[6, "HR"] = 150.0  # the clamp run
    plan = _hand_plan(x0[STAY_ID].tolist(), ["1-2-3", "1-2-4", "7"])
    seeds = [int(s) for s in plan.run_seeds()]
    modes = ["irreversible", "crash", "hang", "garbage", "init_failed", "ok", "clamp"]
    cmd = [*FAULTY_TWIN, "--irreversible-hour", "2"]
    for mode, seed in zip(modes, seeds, strict=True):
        if mode != "ok":
            cmd += ["--mode", f"{mode}:{seed}"]
    twin = make_twin("faulty", {"kind": "command", "command": cmd, "workers": 2,
                                "timeout_s": 1.0, "retries": 0, "env": ENV}, None)
    twin.progress = False
    runs = tp.run_shard(twin, plan, 0, x0, study.actions, log=io.StringIO())
    assert len(runs) == len(plan.nodes) * 7 and not runs.duplicated(["node", "init_stay_id"]).any()
    st = runs.set_index(["init_stay_id", "node"])["status"]
    ids = plan.x0_stay_ids
    assert st[ids[0], "1"] == "ok" and st[ids[0], "7"] == "ok"  # failure at hour 2 only
    for node in ("1-2", "1-2-3", "1-2-4"):
        assert st[ids[0], node] == "irreversible"
    for i, status in ((1, "error"), (2, "timeout"), (3, "error"), (4, "init_failed")):
        assert (st[ids[i]] == status).all(), (modes[i], st[ids[i]].to_dict())
    assert (st[ids[5]] == "ok").all() and (st[ids[6]] == "ok").all()
    msg = runs.set_index(["init_stay_id", "node"])["message"]
    assert "malformed" in msg[ids[3], "7"] and "exit" in msg[ids[1], "7"]
    # ok values are the faulty twin's exact arithmetic, per node hour
    good = runs[(runs.init_stay_id == ids[5])].set_index("node")
    x0_5 = {f: float(x0.loc[5, f]) for f in FEATURES}
    for node in plan.nodes:
        seq = tp.parse_node(node)
        want = expected(x0_5, study.actions.doses(np.asarray(seq)).tolist(), seeds[5])[-1]
        assert good.loc[node, list(FEATURES)].to_dict() == pytest.approx(want, rel=1e-12)
    shares = clamp_shares(runs)
    assert shares["feature"].tolist() == ["HR"] and shares["x0_clamped"].tolist() == [1]
    assert shares["share"].tolist() == pytest.approx([1 / 7])


def _recorded_setup():
    patients = pd.read_csv(PULSE_FIXTURE / "patients.csv").set_index("patient_id")
    rows = []
    for sid, pid in enumerate(["P1", "P2", "P3"], start=1):
        p = patients.loc[pid]
        row = {f: 0.0 for f in FEATURES}
        row.update(age=float(p.age_yr), sex=1.0 if p.sex == "Female" else 0.0,
                   weight=float(p.weight_kg), HR=float(p.HR_baseline_per_min),
                   SysBP=float(p.SBP_baseline_mmHg), DiaBP=float(p.DBP_baseline_mmHg),
                   RR=float(p.RR_baseline_per_min))
        rows.append({STAY_ID: sid, **row})
    # action code = 5 * IV bin + vasopressor bin; bin medians = the recorded doses
    actions = ActionBins(iv_edges=(100.0, 200.0, 300.0), vaso_edges=(0.15, 0.3, 0.45),
                         iv_medians=(0.0, 140.0, 400.0, 500.0, 600.0),
                         vaso_medians=(0.0, 0.1, 0.23, 0.5, 0.6))
    # S1..S5 of the recording: 0000, (140,0)x4, (0,.23)x4, (400,.5)x4, (0,0)(400,0)(0,.1)(140,.1)
    leaves = ["0-0-0-0", "5-5-5-5", "2-2-2-2", "13-13-13-13", "0-10-1-6"]
    return pd.DataFrame(rows), actions, leaves


def test_recorded_pulse_through_the_shard_runner():
    x0, actions, leaves = _recorded_setup()
    plan = _hand_plan([1, 2, 3], leaves)
    twin = make_twin("recorded-pulse", {
        "kind": "command", "workers": 2, "timeout_s": 30, "retries": 0,
        "command": [sys.executable, "-m", "twinfalsify.pulse.replay",
                    "--data", str(PULSE_FIXTURE)], "env": ENV}, None)  # fmt: skip
    twin.progress = False
    runs = tp.run_shard(twin, plan, 0, x0, actions, log=io.StringIO())
    assert len(runs) == len(plan.nodes) * 3
    st = runs.set_index(["init_stay_id", "node"])["status"]
    # P3 under S4 collapses in hour 4: its first three hours stay usable
    assert [st[3, n] for n in ("13", "13-13", "13-13-13")] == ["ok"] * 3
    assert st[3, "13-13-13-13"] == "irreversible"
    assert (st.drop(index=(3, "13-13-13-13")) == "ok").all()
    # values equal the recording served directly, hour by hour
    ref = RecordedPulse(PULSE_FIXTURE)
    table = runs.set_index(["init_stay_id", "node"])
    for sid in (1, 2):
        x = x0.loc[sid - 1, list(FEATURES)].to_dict()
        for leaf in leaves:
            seq = tp.parse_node(leaf)
            res = ref.simulate({"x0": x, "doses": actions.doses(np.asarray(seq)).tolist(),
                                "hours": len(seq), "seed": 0})
            for s in range(1, len(seq) + 1):
                got = table.loc[(sid, tp.node_name(seq[:s])), list(FEATURES)].to_dict()
                assert got == pytest.approx(res["hours"][s - 1], rel=1e-12)
    assert clamp_shares(runs).empty


def test_clamp_shares_reads_json_and_dicts():
    runs = pd.DataFrame({
        "init_stay_id": [1, 1, 2, 3, 4],
        "clamped": ['{"HR": [131.0, 110.0]}', '{"HR": [131.0, 110.0]}',
                    {"HR": [40, 50], "RR": [30, 20]}, "{}", None],
    })  # fmt: skip
    shares = clamp_shares(runs).set_index("feature")["share"]
    assert shares.to_dict() == {"HR": 0.5, "RR": 0.25}
