"""runs.record + runs.replay: a recorded study replays to exactly what the runner received."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV
from helpers.twins import make_inputs

from twinfalsify.runs.replay import ReplayTwin
from twinfalsify.runs.runner import simulate_via_protocol

pytestmark = pytest.mark.usefixtures("no_leftover_processes")
RECORD = [sys.executable, "-m", "twinfalsify.runs.record"]
REPLAY = [sys.executable, "-m", "twinfalsify.runs.replay"]
# Mixed outcomes: clamps, an init failure, an irreversible hour, plain runs.
TWIN = [*FAULTY_TWIN, "--mode=init_failed:%5=1", "--mode=irreversible:%7=3", "--mode=clamp",
        "--irreversible-hour=3"]


def assert_same(a, b, messages: bool = True) -> None:
    np.testing.assert_array_equal(a.features, b.features)  # NaN-equal, bit for bit
    np.testing.assert_array_equal(a.status, b.status)
    if messages:
        np.testing.assert_array_equal(a.message, b.message)
    assert [json.loads(c) for c in a.clamped] == [json.loads(c) for c in b.clamped]


@pytest.fixture
def recorded(tmp_path):
    x0, doses, seeds = make_inputs(12, t=3)
    real = simulate_via_protocol([*RECORD, "--out", str(tmp_path), "--", *TWIN], x0, doses,
                                 seeds, workers=2, env=ENV, progress=False)
    return tmp_path, (x0, doses, seeds), real


def test_replay_equals_the_recorded_runs(recorded):
    rec, (x0, doses, seeds), real = recorded
    assert len(list(rec.glob("answers-*.jsonl"))) == 2  # one file per worker process
    assert set(real.status) >= {"ok", "init_failed", "irreversible"}
    direct = simulate_via_protocol(TWIN, x0, doses, seeds, env=ENV, progress=False)
    assert_same(real, direct, messages=False)  # the proxy is transparent (messages name pids)
    replayed = simulate_via_protocol([*REPLAY, "--data", str(rec)], x0, doses, seeds,
                                     workers=2, env=ENV, progress=False)
    assert_same(replayed, real)


def test_replay_answers_a_prefix_and_refuses_what_it_lacks(recorded):
    rec, (x0, doses, seeds), real = recorded
    twin = ReplayTwin(rec)
    i = int(np.flatnonzero(real.status == "ok")[0])
    req = {"x0": x0.iloc[i].to_dict(), "doses": doses[i].tolist(), "hours": 2,
           "seed": int(seeds[i])}
    ans = twin.simulate(req)
    assert ans["status"] == "ok" and len(ans["hours"]) == 2
    np.testing.assert_array_equal([list(h.values()) for h in ans["hours"]],
                                  real.features[i, :2])
    # a failure at hour 3 is not part of a 2-hour prefix; it is of the full run
    j = int(np.flatnonzero(real.status == "irreversible")[0])
    reqj = {"x0": x0.iloc[j].to_dict(), "doses": doses[j].tolist(), "seed": int(seeds[j])}
    assert twin.simulate({**reqj, "hours": 2})["status"] == "ok"
    assert twin.simulate({**reqj, "hours": 3})["status"] == "irreversible"
    moved = {**req, "x0": {**req["x0"], "HR": req["x0"]["HR"] + 1e-9}}
    miss = twin.simulate(moved)
    assert miss["status"] == "error" and "record them again" in miss["message"]
    other = twin.simulate({**req, "doses": [[999.0, 0.0]] * 3})
    assert other["status"] == "error" and "it holds doses" in other["message"]


def test_deterministic_recording_ignores_the_seed(tmp_path):
    hello = {"op": "hello", "ok": True, "name": "t", "version": "1", "features": []}
    req = {"op": "simulate", "x0": {"HR": 80.0}, "doses": [[0.0, 0.0]], "hours": 1, "seed": 1}
    ans = {"op": "result", "status": "ok", "message": "", "hours": [{"HR": 81.0}],
           "clamped": {}}
    (tmp_path / "answers-1.jsonl").write_text(
        json.dumps({"hello": hello}) + "\n" + json.dumps({"request": req, "answer": ans}) + "\n")
    twin = ReplayTwin(tmp_path)
    assert twin.deterministic
    assert twin.simulate({**req, "seed": 99})["hours"] == [{"HR": 81.0}]


def test_replay_without_recording_refuses_hello(tmp_path):
    with pytest.raises(Exception, match="no answers"):
        simulate_via_protocol([*REPLAY, "--data", str(tmp_path)], *make_inputs(1), env=ENV,
                              progress=False)
