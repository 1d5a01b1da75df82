"""Batch answers in arrays (capability ``arrays``, ``"answer": "arrays"``).

What must hold: an arrays answer gives, run by run, exactly what the plain answer gives
(status, message, the same bits of every value, ``clamped``); a run that breaks a rule is
named and asked again alone, as a broken result of a plain answer is; a broken envelope
fails the batch; the runner asks for arrays only of a twin that advertises them, and a
served builtin twin's runs are the same bits with and without them.
"""

from __future__ import annotations

import base64
import json
import sys

import numpy as np
import pandas as pd
import pytest
from helpers.twins import (
    UNITS,
    CountingTwin,
    serve_in_process,
    simulate_request,
    synthetic_context,
)

from twinfalsify.runs.protocol import (
    ARRAYS,
    CheckedResult,
    ProtocolError,
    check_array_results,
    check_hello,
    check_result,
)
from twinfalsify.runs.registry import make_twin
from twinfalsify.runs.serve import handlers
from twinfalsify.schema import FEATURES
from twinfalsify.sources.synthetic import generate

pytestmark = pytest.mark.usefixtures("no_leftover_processes")

REQUESTS = [simulate_request(0, 2, 1), simulate_request(1, 4, 2), simulate_request(2, 2, 13),
            simulate_request(3, 4, 3), {**simulate_request(4, 2, 4), "x0": {"HR": 1.0}},
            simulate_request(5, 1, 5)]


def _answers(**extra) -> dict:
    (answer,) = serve_in_process([{"op": "simulate_batch", "requests": REQUESTS, **extra}],
                                 batch=True, twin=CountingTwin())
    return answer


def _check(answer: dict) -> list:
    return check_array_results(answer, [r["id"] for r in REQUESTS],
                               [r["hours"] for r in REQUESTS], FEATURES, FEATURES, FEATURES)


def test_arrays_answer_equals_the_plain_answer_run_by_run():
    """Mixed lengths, a bad request and a raising run: every checked run is the plain
    answer's, value bits included."""
    plain = _answers()["results"]
    arrays = _answers(answer=ARRAYS)
    assert arrays["answer"] == ARRAYS and "results" not in arrays
    checked = _check(arrays)
    for req, want, got in zip(REQUESTS, plain, checked, strict=True):
        ref = check_result(want, req["id"], req["hours"], FEATURES, FEATURES, FEATURES)
        assert isinstance(got, CheckedResult)
        assert (got.status, got.message, got.clamped) == (ref.status, ref.message, ref.clamped)
        assert got.values.tobytes() == ref.values.tobytes()
    assert [c.status for c in checked] == ["ok", "ok", "error", "ok", "error", "ok"]


def test_a_batch_of_failed_runs_only_has_no_features_and_checks():
    """Every run failed before its first hour: no features, no values; each run keeps its
    status and message, as in the plain answer."""
    bad = [{**simulate_request(k, 2, k), "x0": {"HR": 1.0}} for k in range(3)]
    (answer,) = serve_in_process([{"op": "simulate_batch", "requests": bad, "answer": ARRAYS}],
                                 batch=True, twin=CountingTwin())
    assert answer["features"] == [] and answer["hours"] == [0, 0, 0]
    checked = check_array_results(answer, [r["id"] for r in bad], [2, 2, 2], FEATURES,
                                  FEATURES, FEATURES)
    assert all(isinstance(c, CheckedResult) and c.status == "error" and c.values.shape ==
               (0, len(FEATURES)) and "lacks feature(s) age" in c.message for c in checked)


def _corrupt(key: str, i: int, value) -> dict:
    answer = _answers(answer=ARRAYS)
    answer[key] = list(answer[key])
    answer[key][i] = value
    return answer


@pytest.mark.parametrize("key, value, match", [
    ("ids", "r9", "does not match request id"),
    ("status", "fine", "is not one of"),
    ("message", 3, "'message' must be a string"),
    ("clamped", {"HR": 3}, "'clamped' must be an object"),
    ("truncated", True, None),  # "ok" with all its hours: truncated changes nothing
])
def test_a_run_breaking_a_rule_is_named_and_the_others_kept(key, value, match):
    checked = _check(_corrupt(key, 1, value))
    good = _check(_answers(answer=ARRAYS))
    if match is None:
        assert isinstance(checked[1], CheckedResult)
    else:
        assert isinstance(checked[1], ProtocolError) and match in str(checked[1])
    for k in (0, 3, 5):
        assert checked[k].values.tobytes() == good[k].values.tobytes()


def _with_values(answer: dict, edit) -> dict:
    flat = np.frombuffer(base64.b64decode(answer["values"]), "<f8").copy()
    edit(flat)
    return {**answer, "values": base64.b64encode(flat.astype("<f8").tobytes()).decode()}


def test_non_finite_values_and_hours_are_held_to_the_plain_rules():
    answer = _answers(answer=ARRAYS)
    f = len(answer["features"])
    nan_first = _check(_with_values(answer, lambda v: v.__setitem__(f + 3, np.nan)))
    assert isinstance(nan_first[0], ProtocolError)
    assert f"hour 2 feature {answer['features'][3]} is not a finite number" in str(nan_first[0])
    assert isinstance(nan_first[1], CheckedResult)
    # status ok with fewer hours than asked, not allowed to stop early
    short = dict(answer)
    short["hours"] = [answer["hours"][0], *answer["hours"][1:]]
    short["hours"][5] = 0
    short = _with_values(short, lambda v: None)
    raw = np.frombuffer(base64.b64decode(short["values"]), "<f8")
    short["values"] = base64.b64encode(raw[: len(raw) - f].tobytes()).decode()
    checked = _check(short)
    assert isinstance(checked[5], ProtocolError) and "only 0 of 1 hours" in str(checked[5])
    too_many = _check(_corrupt("hours", 5, 2) | {"values": base64.b64encode(
        np.concatenate([np.frombuffer(base64.b64decode(answer["values"]), "<f8"),
                        np.ones(f)]).tobytes()).decode()})
    assert isinstance(too_many[5], ProtocolError) and "more than the 1 asked" in str(too_many[5])


@pytest.mark.parametrize("edit, match", [
    (lambda a: a | {"ids": a["ids"][:-1]}, "'ids' must be a list of 6"),
    (lambda a: a | {"values": "not base64!"}, "must be base64"),
    (lambda a: a | {"values": a["values"][:-12]}, "numbers; the hours and features ask"),
    (lambda a: a | {"features": [*a["features"][:-1], "Lactate"]}, "unknown feature"),
    (lambda a: a | {"features": [*a["features"][:-1], a["features"][0]]}, "distinct"),
    (lambda a: a | {"hours": [*a["hours"][:-1], -1]}, "number of hours"),
    (lambda a: a | {"answer": None}, "with answer 'arrays'"),
])
def test_a_broken_envelope_fails_the_batch(edit, match):
    with pytest.raises(ProtocolError, match=match):
        _check(edit(_answers(answer=ARRAYS)))


def test_the_capability_is_checked_and_advertised_with_batches():
    hello = handlers(CountingTwin(), batch=100)[0]()
    assert hello["capabilities"][ARRAYS] is True
    assert ARRAYS not in handlers(CountingTwin())[0]()["capabilities"]
    base = {"op": "hello", "ok": True, "name": "t", "version": "1", "protocol": 1,
            "features": [{"name": f, "unit": UNITS[f]} for f in FEATURES]}
    for bad in (1, "yes"):
        with pytest.raises(ProtocolError, match="capability 'arrays'"):
            check_hello({**base, "capabilities": {ARRAYS: bad}}, FEATURES, UNITS)


@pytest.fixture(scope="module")
def context(tmp_path_factory):
    return synthetic_context(tmp_path_factory.mktemp("arraysctx"), 300, 150)


def test_served_builtin_runs_equal_with_and_without_arrays(context, tmp_path):
    """The same runs through the served fitted twin: asked in arrays (its hello advertises
    them) and through the recording proxy, which withholds the capability so the answers
    come as JSON numbers: the same bits, and the recording holds plain results."""
    pool = generate({"n_stays": 300}, 9)
    x0 = pool[pool["t"] == 0][list(FEATURES)].reset_index(drop=True).iloc[:60]
    rng = np.random.default_rng(2)
    doses = np.stack([rng.choice([0.0, 50.0, 300.0], (60, 3)),
                      rng.choice([0.0, 0.1, 0.4], (60, 3))], axis=2)
    seeds = np.arange(60, dtype=np.uint64) * np.uint64(2**40)
    spec = {"kind": "fitted", "inputs": "init", "residual_noise": True}
    served = make_twin("f", {**spec, "protocol": True, "batch_size": 25}, context)
    served.progress = False
    assert served.hello()["capabilities"][ARRAYS] is True
    got = served.simulate(x0, doses, seeds)
    serve = [sys.executable, "-m", "twinfalsify.runs.serve", "f", "--spec",
             json.dumps(spec), "--context", str(context)]
    rec = tmp_path / "rec"
    proxied = make_twin("f", {"kind": "command", "batch_size": 25, "command": [
        sys.executable, "-m", "twinfalsify.runs.record", "--out", str(rec), "--", *serve]},
        context)
    proxied.progress = False
    assert ARRAYS not in proxied.hello()["capabilities"]
    plain = proxied.simulate(x0, doses, seeds)
    assert (got.status == "ok").all() and (plain.status == "ok").all()
    assert got.features.tobytes() == plain.features.tobytes()
    lines = [json.loads(x) for f in rec.glob("*.jsonl") for x in f.read_text().splitlines()]
    answers = [x["answer"] for x in lines if "answer" in x]
    assert len(answers) == 60 and all(isinstance(a["hours"], list) for a in answers)
    assert pd.Series([a["status"] for a in answers]).eq("ok").all()
