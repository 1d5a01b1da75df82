"""Batched requests in the twin protocol (capability ``batch``, op ``simulate_batch``).

What must hold: a batch is answered in request order, each result exactly what
a plain ``simulate`` of that request gives; the runner only batches for a twin
that advertises it; every fault during a batch ends, after a one-by-one retry,
with the status and message the run gets without batching; the served builtin
twins give the same bits as the in-process twins whatever the batch size.
"""

from __future__ import annotations

import io
import json
import re
import sys
import time

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV
from helpers.twins import (
    UNITS,
    CountingTwin,
    expected_features,
    make_inputs,
    serve_in_process,
    simulate_request,
    stamps,
    synthetic_context,
)

from twinfalsify.runs import worker as worker_mod
from twinfalsify.runs.protocol import (
    ProtocolError,
    check_hello,
    check_result,
    check_results,
    decode,
    encode,
    serve_forever,
)
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.registry import make_twin
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.runs.serve import BATCH_MAX, handlers
from twinfalsify.schema import FEATURES
from twinfalsify.sources.synthetic import generate

FAULTY = FAULTY_TWIN
pytestmark = pytest.mark.usefixtures("no_leftover_processes")


# -- protocol: hello capability, envelope, serve_forever ----------------------------

def test_check_hello_batch_capability():
    hello = {"op": "hello", "ok": True, "name": "t", "version": "1", "protocol": 1,
             "features": [{"name": f, "unit": UNITS[f]} for f in FEATURES]}
    assert "batch" not in check_hello(hello, FEATURES, UNITS)["capabilities"]  # absent = 1
    ok = check_hello({**hello, "capabilities": {"batch": 250}}, FEATURES, UNITS)
    assert ok["capabilities"]["batch"] == 250
    for bad in (0, -3, 2.5, "10", True, None):
        with pytest.raises(ProtocolError, match="capability 'batch'"):
            check_hello({**hello, "capabilities": {"batch": bad}}, FEATURES, UNITS)


def test_check_results_envelope():
    assert check_results({"op": "results", "results": [1, 2]}, 2) == [1, 2]
    with pytest.raises(ProtocolError, match="expected op 'results'"):
        check_results({"op": "error", "message": "unknown op"}, 1)
    with pytest.raises(ProtocolError, match="'results' must be a list"):
        check_results({"op": "results", "results": {}}, 1)
    with pytest.raises(ProtocolError, match="1 results for a batch of 2"):
        check_results({"op": "results", "results": [{}]}, 2)
    with pytest.raises(ProtocolError, match="must be an object"):
        check_result("x", "a", 1, FEATURES, FEATURES, FEATURES)  # type: ignore[arg-type]


@pytest.mark.parametrize("vectorised", [True, False], ids=["batch_handler", "per_request"])
def test_batch_answer_equals_plain_answers_in_order(vectorised):
    """A batch (mixed lengths, one bad request, one raising run) == the plain answers."""
    reqs = [simulate_request(0, 2, 1), simulate_request(1, 4, 2), simulate_request(2, 2, 13),
            simulate_request(3, 4, 3), {**simulate_request(4, 2, 4), "x0": {"HR": 1.0}},
            simulate_request(5, 1, 5)]
    twin = CountingTwin()
    answers = serve_in_process([{"op": "simulate_batch", "requests": reqs}], batch=vectorised,
                               twin=twin)
    plain = serve_in_process(reqs, batch=False)
    assert len(answers) == 1 and answers[0]["op"] == "results"
    results = answers[0]["results"]
    assert [r["id"] for r in results] == [r["id"] for r in reqs]
    assert results == plain  # same fields, same bits (JSON floats round-trip exactly)
    assert results[2]["status"] == "error" and "seed 13 is unlucky" in results[2]["message"]
    assert results[4]["status"] == "error" and "lacks feature(s) age" in results[4]["message"]
    # the good ones: the formula, worked out here
    for k in (0, 1, 3, 5):
        req, res = reqs[k], results[k]
        assert res["status"] == "ok" and len(res["hours"]) == req["hours"]
        for h, row in enumerate(res["hours"], start=1):
            iv, vaso = req["doses"][h - 1]
            want = req["x0"]["HR"] + (h * (iv / 100 - vaso) + (req["seed"] % 7) / 10)
            assert row["HR"] == want
    if vectorised:
        # one call per length (2 valid runs of 2 h incl. the raiser, 2 of 4 h, 1 of
        # 1 h), then the failed 2-hour group one run at a time (2 calls of 1)
        assert sorted(twin.calls) == sorted([2, 2, 1, 1, 1])


def test_serve_forever_batch_fallbacks():
    reqs = [simulate_request(0, 2, 1), simulate_request(1, 3, 2)]
    plain = serve_in_process(reqs, batch=False)

    def raising(requests):
        raise RuntimeError("vectorised path broken")

    def short(requests):
        return []

    for fn in (raising, short):
        stdout = io.StringIO()
        hello, simulate = handlers(CountingTwin())
        serve_forever(hello, simulate,
                      io.StringIO(encode({"op": "simulate_batch", "requests": reqs})),
                      stdout, simulate_batch=fn)
        assert decode(stdout.getvalue())["results"] == plain
    answers = serve_in_process([{"op": "simulate_batch", "requests": "nope"},
                      {"op": "simulate_batch", "requests": [reqs[0], 7]}], batch=True)
    assert answers[0]["op"] == "error" and "'requests' must be a list" in answers[0]["message"]
    assert answers[1]["results"][0] == plain[0]
    assert answers[1]["results"][1]["status"] == "error"


def test_builtin_handlers_advertise_batch_only_when_asked():
    assert "batch" not in handlers(CountingTwin())[0]()["capabilities"]
    assert handlers(CountingTwin(), batch=BATCH_MAX)[0]()["capabilities"]["batch"] == BATCH_MAX


# -- runner with the faulty twin -----------------------------------------------------

def _batches(messages) -> list[int]:
    return [int(m.group(1)) if (m := re.search(r"batch=(\d+)", msg)) else 0
            for msg in messages]


def test_batches_are_sent_and_results_identical():
    """Same values with and without batching; batches really used, sized as configured."""
    x0, doses, seeds = make_inputs(24)
    seeds = np.repeat(np.arange(200, 206, dtype=np.uint64), 4)  # 6 groups of 4 sequences
    kw = {"env": ENV, "progress": False, "workers": 2}
    plain = simulate_via_protocol(FAULTY, x0, doses, seeds, **kw)
    batched = simulate_via_protocol([*FAULTY, "--batch=8"], x0, doses, seeds, batch_size=5,
                                    **kw)
    np.testing.assert_array_equal(batched.features, plain.features)
    np.testing.assert_array_equal(batched.status, plain.status)
    np.testing.assert_allclose(batched.features, expected_features(x0, doses, seeds), atol=1e-9)
    sizes = _batches(batched.message)
    assert set(_batches(plain.message)) == {0}  # no capability, no batches
    assert max(sizes) == 5  # min(twin's 8, batch_size 5)
    assert sum(s > 0 for s in sizes) >= 24 - 2 - 5  # each worker's first run is plain
    # a seed's runs still go to one worker, in dose order (here, across batches too)
    for seed in np.unique(seeds):
        idx = np.flatnonzero(seeds == seed)
        info = [stamps(batched.message[i]) for i in idx]
        assert len({pid for pid, _, _ in info}) == 1
        by_time = idx[np.argsort([start for _, start, _ in info], kind="stable")]
        assert list(by_time) == sorted(idx, key=lambda i: tuple(doses[i].ravel()))
    # batch_size 1 never batches
    single = simulate_via_protocol([*FAULTY, "--batch=8"], x0, doses, seeds, batch_size=1,
                                   **kw)
    assert set(_batches(single.message)) == {0}
    np.testing.assert_array_equal(single.features, plain.features)


def _strip(message: str) -> str:
    """A message without what legitimately differs between runs (pids, times, batch)."""
    message = re.sub(r"pid[= ]\d+", "pid", message)
    message = re.sub(r" start=[\d.]+ end=[\d.]+", "", message)
    return re.sub(r" batch=\d+", "", message)


def test_mixed_faults_in_batches_match_unbatched():
    """Every fault inside a batch: after the one-by-one retry, the unbatched outcome."""
    plan = {  # seed -> (mode, expected status)
        100: ("ok", "ok"), 101: ("crash", "error"), 102: ("hang", "timeout"),
        103: ("garbage", "error"), 104: ("malformed", "error"), 105: ("wrong_id", "error"),
        106: ("wrong_features", "error"), 107: ("fewer_hours", "error"),
        108: ("non_numeric", "error"), 109: ("irreversible", "irreversible"),
        110: ("init_failed", "init_failed"), 111: ("error", "error"), 112: ("clamp", "ok"),
        113: ("ok", "ok"), 114: ("batch_short", "ok"), 115: ("ok", "ok"),
    }
    x0, doses, seeds = make_inputs(len(plan))
    x0.loc[12, "HR"] = 150.0
    modes = [f"--mode={mode}:{seed}" for seed, (mode, _) in plan.items() if mode != "ok"]
    kw = {"workers": 2, "timeout_s": 0.5, "retries": 1, "env": ENV, "progress": False}
    plain = simulate_via_protocol([*FAULTY, *modes], x0, doses, seeds, **kw)
    batched = simulate_via_protocol([*FAULTY, *modes, "--batch=3"], x0, doses, seeds, **kw)
    assert list(batched.status) == [status for _, status in plan.values()]
    np.testing.assert_array_equal(batched.status, plain.status)
    np.testing.assert_array_equal(batched.features, plain.features)
    np.testing.assert_array_equal(batched.clamped, plain.clamped)
    assert [_strip(m) for m in batched.message] == [_strip(m) for m in plain.message]
    assert "(failed 2 attempt(s))" in batched.message[1]
    assert "no answer within 0.5 s" in batched.message[2]
    assert "does not match request id '5.0'" in batched.message[5]
    assert any(_batches(batched.message))  # good runs outside failed batches were batched


def test_batch_attempt_is_not_counted_against_its_runs(tmp_path):
    """A batch crash is retried one by one with the full attempts (the culprit is unknown).

    crash_once crashes the first time a seed is seen: inside the batch. With
    retries=0 every run still succeeds, because the batch was a free attempt.
    """
    x0, doses, seeds = make_inputs(6)
    seeds = np.full(6, 300, dtype=np.uint64)
    x0.iloc[:] = x0.iloc[0].to_numpy()
    res = simulate_via_protocol([*FAULTY, "--mode=crash_once", f"--state-dir={tmp_path}",
                                 "--batch=10"], x0, doses, seeds, retries=0, env=ENV,
                                progress=False)
    # the first run is plain (starts the worker) and crashes: error, as without batching
    order = sorted(range(6), key=lambda i: tuple(doses[i].ravel()))
    assert res.status[order[0]] == "error" and "exited with code 3" in res.message[order[0]]
    assert all(res.status[i] == "ok" for i in order[1:])
    np.testing.assert_allclose(res.features[order[1:]],
                               expected_features(x0, doses, seeds)[order[1:]], atol=1e-9)


def test_batch_time_limit_scales_with_its_length():
    """4 runs of 0.3 s in one batch take 1.2 s: within 4 x 0.5 s, though over 0.5 s."""
    x0, doses, seeds = make_inputs(5)
    seeds = np.full(5, 400, dtype=np.uint64)
    res = simulate_via_protocol([*FAULTY, "--mode=slow", "--delay=0.3", "--batch=4"], x0,
                                doses, seeds, timeout_s=0.5, retries=0, env=ENV,
                                progress=False)
    assert list(res.status) == ["ok"] * 5
    assert sorted(_batches(res.message)) == [0, 4, 4, 4, 4]


# -- two batches in flight: the next batch is sent before the previous answer is read --

def _in_flight_at_most(monkeypatch) -> list[int]:
    """Patch Worker so that the returned list ends holding the most simulate_batch messages
    a worker had unanswered at once (an answer read closes the oldest)."""
    out = [0]
    open_ = {}

    def post(self, msg, deadline):
        open_[id(self)] = open_.get(id(self), 0) + 1
        out[0] = max(out[0], open_[id(self)])
        return real_post(self, msg, deadline)

    def answer(self, *args, **kwargs):
        if open_.get(id(self)):
            open_[id(self)] -= 1
        return real_answer(self, *args, **kwargs)

    real_post, real_answer = worker_mod.Worker.post, worker_mod.Worker.answer
    monkeypatch.setattr(worker_mod.Worker, "post", post)
    monkeypatch.setattr(worker_mod.Worker, "answer", answer)
    return out


def _turns_and_pipelined(monkeypatch, cmd, n, **kw):
    """The same call taking turns (one batch at a time) and with batches in flight."""
    x0, doses, _ = make_inputs(n)
    seeds = np.arange(500, 500 + n, dtype=np.uint64)  # one run per X_0: runs in seed order
    kw = {"env": ENV, "progress": False, "fail_fast_runs": 0, "max_restarts": 0, **kw}
    with monkeypatch.context() as m:
        m.setattr(worker_mod, "BATCHES_IN_FLIGHT", 1)
        most = _in_flight_at_most(m)
        turns = simulate_via_protocol(cmd, x0, doses, seeds, **kw)
        assert most[0] == 1
    most = _in_flight_at_most(monkeypatch)
    piped = simulate_via_protocol(cmd, x0, doses, seeds, **kw)
    assert most[0] == 2  # really two batches out at once
    return turns, piped


def _same(turns, piped) -> None:
    np.testing.assert_array_equal(piped.status, turns.status)
    np.testing.assert_array_equal(piped.features, turns.features)
    np.testing.assert_array_equal(piped.clamped, turns.clamped)
    assert [_strip(m) for m in piped.message] == [_strip(m) for m in turns.message]


def test_batches_in_flight_give_the_values_of_taking_turns(monkeypatch):
    """Run 0 plain (starts the worker), then batches of 4 sent ahead of their answers."""
    turns, piped = _turns_and_pipelined(monkeypatch, [*FAULTY, "--batch=4", "--no-stamp"],
                                        23, workers=2)
    _same(turns, piped)
    assert (piped.status == "ok").all()


@pytest.mark.parametrize(("modes", "failing"), [
    # seeds 500.. are runs 0..: run 0 plain (starts the worker), batches [1-4] [5-8] [9-11]
    (["--mode=crash:502"], [2]),  # the first batch in flight dies: the second never started
    (["--mode=crash:505"], [5]),  # the second dies after the first was answered
    (["--mode=hang:502"], [2]),  # the first hangs with the second behind it
    (["--mode=wrong_id:502", "--mode=crash:505"], [2, 5]),  # a retry needs a quiet stream
    (["--mode=garbage:503", "--mode=non_numeric:506"], [3, 6]),
], ids=["crash-first", "crash-second", "hang-first", "redo-then-crash", "garbage"])
def test_a_fault_with_two_batches_in_flight_ends_as_taking_turns(monkeypatch, modes, failing):
    turns, piped = _turns_and_pipelined(monkeypatch, [*FAULTY, *modes, "--batch=4"], 12,
                                        timeout_s=0.5, retries=1)
    _same(turns, piped)
    assert [i for i, s in enumerate(piped.status) if s != "ok"] == failing


def test_a_worker_dying_with_two_batches_in_flight_records_every_run_as_failed(monkeypatch):
    """Every run after the first crashes the twin: both batches in flight are lost, and
    each of their runs is retried alone and recorded as failed (none dropped)."""
    crash = "--mode=crash:" + ",".join(str(s) for s in range(501, 512))
    turns, piped = _turns_and_pipelined(monkeypatch, [*FAULTY, crash, "--batch=4"], 12,
                                        retries=1)
    _same(turns, piped)
    assert piped.status[0] == "ok"
    assert list(piped.status[1:]) == ["error"] * 11
    assert all("exited with code 3" in m and "(failed 2 attempt(s))" in m
               for m in piped.message[1:])


def test_a_batch_behind_a_hung_one_waits_no_longer_than_that_batch():
    """A message posted behind a request the twin hangs on is written as far as the pipe
    takes it by the given deadline (the earlier batch's): the rest waits for ``flush``."""
    worker = worker_mod.start_worker([*FAULTY, "--mode=hang:9"], ENV, 10.0)
    try:
        assert worker.post(simulate_request(0, 2, 9), time.monotonic() + 5.0)
        big = {"op": "simulate_batch",
               "requests": [simulate_request(i, 4, 10 + i) for i in range(3000)]}  # ~3 MB
        start = time.monotonic()
        assert not worker.post(big, start + 0.3)
        assert not worker.flush(time.monotonic() + 0.2)
        assert time.monotonic() - start < 2.0
        with pytest.raises(worker_mod.WorkerTimeout):
            worker.answer(0.2)
    finally:
        worker.kill()


def test_protocol_twin_batch_size_option(tmp_path):
    assert ProtocolTwin("f", FAULTY).batch_size == 500
    x0, doses, seeds = make_inputs(6)
    seeds = np.full(6, 7, dtype=np.uint64)
    twin = ProtocolTwin("f", [*FAULTY, "--batch=100"], env=ENV, progress=False, batch_size=2)
    assert twin.hello()["capabilities"]["batch"] == 100
    res = twin.simulate(x0, doses, seeds)
    # the first run plain (it starts the worker), then batches of 2 + 2, the last one plain
    assert sorted(_batches(res.message)) == [0, 0, 2, 2, 2, 2]
    (tmp_path / "twin_context.json").write_text(
        json.dumps({"source": {"kind": "synthetic", "synthetic": {}}}))
    served = make_twin("o", {"kind": "oracle", "protocol": True, "batch_size": 7}, tmp_path)
    assert served.batch_size == 7
    assert "batch_size" not in served.command[served.command.index("--spec") + 1]
    assert make_twin("o", {"kind": "oracle", "protocol": True}, tmp_path).batch_size == 500


# -- served builtin twins: bit-identical to in-process -------------------------------

@pytest.fixture(scope="module")
def context(tmp_path_factory):
    return synthetic_context(tmp_path_factory.mktemp("batchctx"), 400, 200)


@pytest.mark.parametrize("spec", [
    {"kind": "oracle"},
    {"kind": "biased", "shift": {"HR": 15.0}, "dose_effect": {"vasopressor": 2.0}},
    {"kind": "fitted", "inputs": "init", "residual_noise": True},
    {"kind": "fitted", "inputs": "all", "residual_noise": False},
], ids=["oracle", "biased", "fitted-noise", "fitted-all"])  # fmt: skip
def test_served_builtin_batches_bit_identical_to_in_process(context, spec):
    local = make_twin("t", spec, context)
    rng = np.random.default_rng(8)
    pool = generate({"n_stays": 400}, 9)
    starts = pool[pool["t"] == 0][list(FEATURES)].reset_index(drop=True)
    m, n_seq = 40, 6
    x0 = pd.concat([starts.iloc[:m]] * n_seq, ignore_index=True)
    doses = np.full((m * n_seq, 4, 2), np.nan)
    for j in range(n_seq):  # sequences of 1..4 hours sharing prefixes
        hours = 1 + j % 4
        seq = np.stack([rng.choice([0.0, 50.0, 300.0], 4), rng.choice([0.0, 0.1, 0.4], 4)], 1)
        doses[j * m:(j + 1) * m, :hours] = seq[:hours]
    seeds = np.tile(np.arange(1000, 1000 + m, dtype=np.uint64) * np.uint64(2**40), n_seq)
    served = make_twin("t", {**spec, "protocol": True, "workers": 2, "batch_size": 37},
                       context)
    served.progress = False
    got = served.simulate(x0, doses, seeds)
    assert (got.status == "ok").all()
    for j in range(n_seq):  # the in-process twin, one vectorised call per sequence
        rows = slice(j * m, (j + 1) * m)
        hours = int(np.isfinite(doses[j * m, :, 0]).sum())
        want = local.simulate(x0.iloc[rows].reset_index(drop=True), doses[rows, :hours],
                              seeds[rows])
        np.testing.assert_array_equal(got.features[rows, :hours], want.features)
        assert np.isnan(got.features[rows, hours:]).all()
    # and one run alone gives the same bits as inside its batch (row independence)
    one = local.simulate(x0.iloc[[5]].reset_index(drop=True), doses[[5], :1], seeds[[5]])
    np.testing.assert_array_equal(one.features[0], got.features[5, :1])


def test_served_builtin_advertises_batch(context):
    twin = make_twin("o", {"kind": "oracle", "protocol": True}, context)
    assert twin.hello()["capabilities"]["batch"] == BATCH_MAX


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
