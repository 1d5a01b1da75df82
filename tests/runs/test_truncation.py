"""Depth truncation over the protocol: the rule (runs.truncation), a served twin that stops
runs no hypothesis needs any more, and the caller's check of such answers."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.twins import HR, UNITS, serve_in_process, simulate_request

from twinfalsify.runs.protocol import ProtocolError, check_result
from twinfalsify.runs.truncation import hours_needed, parse_paths
from twinfalsify.schema import FEATURES


def _values(*hr: float) -> np.ndarray:
    v = np.zeros((len(hr), len(FEATURES)))
    v[:, HR] = hr
    return v


def test_hours_needed_follows_the_longest_path_still_inside():
    above80, upto80 = ("HR", ">", 80.0), ("HR", "<=", 80.0)
    paths = [[above80, above80, upto80], [upto80]]
    assert hours_needed(paths, _values(90, 95, 70, 60), 4) == 4  # path 0 holds throughout
    assert hours_needed(paths, _values(90, 70, 70, 60), 4) == 2  # path 0 left at hour 2
    assert hours_needed(paths, _values(70, 70, 70, 60), 4) == 2  # path 1 needs hour 2 only
    assert hours_needed([[above80], []], _values(70, 70), 4) == 1
    assert hours_needed([[("HR", "any", 0.0)] * 3], _values(1, 2, 3, 4), 4) == 4
    assert hours_needed([[above80]], _values(90), 4) == 2  # hour 2 not completed yet
    with pytest.raises(ValueError, match="box"):
        parse_paths([[["HR", ">=", 80]]])


def test_served_twin_stops_runs_no_path_needs():
    req = simulate_request(0, 4, seed=1)  # CountingTwin: HR rises with hour, ~50.3 + small shifts
    hr1 = 50.0 + 0.25 * HR
    req["continue_while"] = [[["HR", "<=", hr1 - 10.0]]]  # hour 1 is never inside
    whole = {**simulate_request(1, 4, seed=1), "id": "whole"}
    for batch in (False, True):
        got = {a["id"]: a for a in serve_in_process([req, whole], batch=batch)}
        assert len(got["r0"]["hours"]) == 1 and got["r0"]["truncated"] is True
        assert got["r0"]["status"] == "ok"
        assert len(got["whole"]["hours"]) == 4 and "truncated" not in got["whole"]


def test_caller_rejects_truncation_before_a_needed_hour():
    hours = [{f: 90.0 if f == "HR" else 1.0 for f in FEATURES}]
    msg = {"op": "result", "id": "a", "status": "ok", "message": "", "hours": hours,
           "clamped": {}, "truncated": True}
    ok = check_result(msg, "a", 3, ("HR",), UNITS, FEATURES, [[("HR", "<=", 80.0)]])
    assert ok.values.shape == (1, len(FEATURES))
    with pytest.raises(ProtocolError, match="hour 2 is needed"):
        check_result(msg, "a", 3, ("HR",), UNITS, FEATURES, [[("HR", ">", 80.0)]])
    with pytest.raises(ProtocolError, match="only 1 of 3 hours"):
        check_result(msg, "a", 3, ("HR",), UNITS, FEATURES, None)
