"""Protocol v1: client-side validation, the serve helpers, and the documented example.

A tiny deterministic in-test Twin is served through ``serve_forever`` both in
process (StringIO) and as a real subprocess driven by the runner; its answers
must equal the same Twin's vectorised in-process simulation exactly.
"""

from __future__ import annotations

import io
import json
import os
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers.paths import ROOT

from twinfalsify.runs.protocol import (
    ProtocolError,
    check_hello,
    check_result,
    decode,
    encode,
    serve_forever,
)
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.runs.serve import handlers
from twinfalsify.schema import FEATURE_BY_NAME, FEATURES
from twinfalsify.twins.base import SimResult

SRC = ROOT / "src"
ENV = {"PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
UNITS = {name: f.unit for name, f in FEATURE_BY_NAME.items()}
HR = FEATURES.index("HR")


class ArithmeticTwin:
    """Deterministic test twin: x_h = x0 + 0.02 cum_iv - 30 cum_vaso + 0.001 (seed mod 1000) h.

    HR above 110 is clamped to 110 at initialisation (and reported); a run
    whose cumulative vasopressor exceeds 0.5 ug/kg/min-hours at hour s becomes
    irreversible during hour s (hours before s are returned, NaN after).
    """

    name = "arithmetic"

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        n, t, _ = doses.shape
        base = x0[list(FEATURES)].to_numpy(float).copy()
        clamped = np.full(n, "{}", dtype=object)
        for i in np.flatnonzero(base[:, HR] > 110):
            clamped[i] = json.dumps({"HR": [base[i, HR], 110.0]})
            base[i, HR] = 110.0
        hours = np.arange(1, t + 1)
        cum_iv, cum_vaso = np.cumsum(doses[..., 0], 1), np.cumsum(doses[..., 1], 1)
        noise = 0.001 * (seeds.astype(np.int64) % 1000)[:, None] * hours[None, :]
        shift = 0.02 * cum_iv - 30.0 * cum_vaso + noise
        feats = base[:, None, :] + shift[..., None]
        status = np.full(n, "ok", dtype=object)
        message = np.full(n, "", dtype=object)
        dead = cum_vaso > 0.5
        for i in np.flatnonzero(dead.any(axis=1)):
            s = int(np.argmax(dead[i]))
            feats[i, s:] = np.nan
            status[i], message[i] = "irreversible", f"irreversible during hour {s + 1}"
        return SimResult(feats, status, message, clamped)


def sample_inputs(n: int = 9, t: int = 3):
    rng = np.random.default_rng(11)
    x0 = pd.DataFrame({f: rng.uniform(60, 130, n).round(2) for f in FEATURES})
    doses = np.stack([rng.choice([0.0, 20.0, 100.0], (n, t)),
                      rng.choice([0.0, 0.1, 0.3], (n, t))], axis=2)
    seeds = rng.integers(0, 2**63, n, dtype=np.uint64) * np.uint64(2)  # > 2^53 on purpose
    return x0, doses, seeds


# -- validation helpers ------------------------------------------------------

def good_hello(**over):
    msg = {"op": "hello", "ok": True, "name": "t", "version": "1", "protocol": 1,
           "features": [{"name": f, "unit": UNITS[f]} for f in FEATURES],
           "capabilities": {"save_restore": True}}
    return {**msg, **over}


def test_check_hello_accepts_and_fills_defaults():
    out = check_hello(good_hello(), FEATURES, UNITS)
    assert out["capabilities"] == {"save_restore": True, "max_hours": None}
    assert out["declared_units"]["Glucose"] == "mg/dL"
    extra = good_hello(features=[*good_hello()["features"], {"name": "lactate", "unit": "mmol/L"}])
    assert "lactate" in check_hello(extra, FEATURES, UNITS)["declared_units"]


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ({"protocol": 2}, "speaks protocol 2"),
        ({"ok": False, "message": "no licence"}, "no licence"),
        ({"name": 3}, "'name' must be a string"),
        ({"features": [{"name": "HR"}]}, "'features' must be a list"),
        ({"features": [{"name": f, "unit": UNITS[f]} for f in FEATURES if f != "Sodium"]},
         "does not declare required feature(s) Sodium"),
        ({"features": [{"name": f, "unit": "mg/dL" if f == "Potassium" else UNITS[f]}
                       for f in FEATURES]}, "Potassium in 'mg/dL' (expected 'mmol/L')"),
        ({"capabilities": {"save_restore": "yes"}}, "save_restore"),
        ({"capabilities": {"max_hours": 0}}, "max_hours"),
        ({"op": "result"}, "expected a hello answer"),
    ],
)
def test_check_hello_rejects(override, fragment):
    with pytest.raises(ProtocolError) as err:
        check_hello(good_hello(**override), FEATURES, UNITS)
    assert fragment in str(err.value)


def result(n_hours=2, **over):
    rows = [{f: float(i + h) for i, f in enumerate(FEATURES)} for h in range(n_hours)]
    msg = {"op": "result", "id": "4.1", "status": "ok", "message": "", "hours": rows,
           "clamped": {}}
    return {**msg, **over}


def test_check_result_places_values_in_column_order():
    out = check_result(result(), "4.1", 2, FEATURES, FEATURES, FEATURES)
    assert out.status == "ok" and out.clamped == "{}"
    np.testing.assert_array_equal(out.values, np.arange(18)[None, :] + np.array([[0], [1]]))
    # a study asking for two features still stores everything declared, in column order
    part = check_result(result(n_hours=1), "4.1", 1, ("HR",), FEATURES, ("Sodium", "HR"))
    np.testing.assert_array_equal(part.values, [[FEATURES.index("Sodium"), HR]])
    fail = check_result(result(n_hours=1, status="irreversible", clamped={"HR": [130, 110]}),
                        "4.1", 3, FEATURES, FEATURES, FEATURES)
    assert fail.values.shape == (1, 18) and fail.clamped == '{"HR": [130, 110]}'


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ({"id": "4.0"}, "does not match request id '4.1'"),
        ({"op": "error", "message": "boom"}, "expected op 'result', got 'error': boom"),
        ({"status": "timeout"}, "status 'timeout' is not one of"),
        ({"message": 5}, "'message' must be a string"),
        ({"hours": {"HR": 1}}, "'hours' must be a list"),
        ({"hours": result(3)["hours"]}, "3 hours returned, more than the 2"),
        ({"hours": result(1)["hours"]}, "status ok but only 1 of 2 hours"),
        ({"hours": [{**h, "lactate": 1.0} for h in result()["hours"]]}, "unknown feature(s) lac"),
        ({"hours": [{k: v for k, v in h.items() if k != "paO2"} for h in result()["hours"]]},
         "hour 1 lacks feature(s) paO2"),
        ({"hours": [{**h, "HR": "fast"} for h in result()["hours"]]}, "HR is not a finite"),
        ({"hours": [{**h, "HR": True} for h in result()["hours"]]}, "HR is not a finite"),
        ({"hours": [{**h, "HR": float("nan")} for h in result()["hours"]]}, "not a finite"),
        ({"hours": [7, 8]}, "hour 1 must be an object"),
        ({"clamped": {"HR": 110}}, "'clamped' must be an object"),
    ],
)
def test_check_result_rejects(override, fragment):
    with pytest.raises(ProtocolError) as err:
        check_result(result(**override), "4.1", 2, FEATURES, FEATURES, FEATURES)
    assert fragment in str(err.value)


def test_encode_decode_round_trip_and_errors():
    msg = {"op": "simulate", "seed": 2**64 - 1, "doses": [[1.5, 0.0]]}
    line = encode(msg)
    assert line.endswith("\n") and "\n" not in line[:-1]
    assert decode(line) == msg
    with pytest.raises(ValueError):
        encode({"op": "x", "v": float("nan")})
    with pytest.raises(ProtocolError, match="not JSON"):
        decode("hello there")
    with pytest.raises(ProtocolError, match="no 'op'"):
        decode("[1, 2]")


# -- the documented example session ------------------------------------------

def test_example_session_in_docs_follows_the_rules():
    text = (ROOT / "docs" / "reference" / "twin-protocol.md").read_text()
    block = text.split("```jsonl\n", 1)[1].split("```", 1)[0]
    lines = [ln for ln in block.splitlines() if ln.strip()]
    sent = [json.loads(ln[3:]) for ln in lines if ln.startswith("-> ")]
    got = [json.loads(ln[3:]) for ln in lines if ln.startswith("<- ")]
    assert len(sent) == len(got) == 4
    required = ("HR", "SysBP")
    hello = check_hello(got[0], required, UNITS)
    for request, answer in zip(sent[1:3], got[1:3], strict=True):
        assert request["op"] == "simulate" and len(request["doses"]) == request["hours"]
        checked = check_result(answer, request["id"], request["hours"], required,
                               hello["declared_units"], FEATURES)
        assert checked.status in ("ok", "irreversible")
    assert sent[3] == {"op": "shutdown"} and got[3] == {"op": "bye"}
    for status in ("ok", "init_failed", "irreversible", "timeout", "error"):
        assert f"`{status}`" in text


# -- serving an in-process Twin ------------------------------------------------

def run_requests(twin, requests: list[dict]) -> list[dict]:
    stdin = io.StringIO("".join(encode(r) for r in requests))
    stdout = io.StringIO()
    assert serve_forever(*handlers(twin), stdin=stdin, stdout=stdout) == 0
    return [decode(ln) for ln in stdout.getvalue().splitlines()]


def test_serve_handlers_in_process():
    x0, doses, seeds = sample_inputs(2, t=2)
    req = {"op": "simulate", "id": "a", "x0": x0.iloc[0].to_dict(), "doses": doses[0].tolist(),
           "hours": 2, "seed": int(seeds[0])}
    bad = {**req, "id": "b", "x0": {"HR": 80.0}}
    answers = run_requests(ArithmeticTwin(), [
        {"op": "hello", "protocol": 1}, req, bad, {"op": "nonsense"}, {"op": "shutdown"},
        {"op": "hello"},  # after shutdown: never read
    ])
    assert [a["op"] for a in answers] == ["hello", "result", "result", "error", "bye"]
    check_hello(answers[0], FEATURES, UNITS)
    ok = check_result(answers[1], "a", 2, FEATURES, FEATURES, FEATURES)
    direct = ArithmeticTwin().simulate(x0.iloc[:1], doses[:1], seeds[:1])
    np.testing.assert_array_equal(ok.values, direct.features[0])
    assert answers[2]["status"] == "error" and "lacks feature(s) age" in answers[2]["message"]


def test_served_twin_subprocess_equals_in_process(tmp_path):
    """The runner + a served Twin reproduce the Twin's vectorised output exactly."""
    script = tmp_path / "arith_twin.py"
    source = (Path(__file__).read_text().split("class ArithmeticTwin", 1)[1]
              .split("\ndef sample_inputs", 1)[0])
    script.write_text(textwrap.dedent("""\
        import json, sys
        import numpy as np, pandas as pd
        from twinfalsify.schema import FEATURES
        from twinfalsify.twins.base import SimResult
        from twinfalsify.runs.protocol import serve_forever
        from twinfalsify.runs.serve import handlers
        HR = FEATURES.index("HR")
        class ArithmeticTwin""") + source + textwrap.dedent("""
        sys.exit(serve_forever(*handlers(ArithmeticTwin())))
        """))
    x0, doses, seeds = sample_inputs(9, t=3)
    x0.loc[0, "HR"] = 125.0
    doses[1, :, 1] = 0.3  # irreversible during hour 2
    direct = ArithmeticTwin().simulate(x0, doses, seeds)
    served = simulate_via_protocol([sys.executable, str(script)], x0, doses, seeds, workers=2,
                                   env=ENV, progress=False)
    np.testing.assert_array_equal(served.features, direct.features)
    np.testing.assert_array_equal(served.status, direct.status)
    assert served.status[1] == "irreversible" and not np.isnan(served.features[1, 0]).any()
    assert [json.loads(c) for c in served.clamped] == [json.loads(c) for c in direct.clamped]
    assert json.loads(served.clamped[0]) == {"HR": [125.0, 110.0]}
    np.testing.assert_array_equal(served.message, direct.message)


def test_serve_builtin_twin_subprocess_equals_in_process(tmp_path):
    """``python -m twinfalsify.runs.serve`` with 2 workers == the builtin twin in process."""
    from twinfalsify.runs import registry

    (tmp_path / "twin_context.json").write_text(
        json.dumps({"source": {"kind": "synthetic", "synthetic": {}}})
    )
    spec = {"kind": "biased", "shift": {"HR": 5.0}}
    twin = registry.make_twin("biased", spec, tmp_path)
    rng = np.random.default_rng(3)
    mid = {"age": 60, "sex": 1, "weight": 80, "HR": 95, "SysBP": 115, "DiaBP": 60,
           "MeanBP": 78, "RR": 20, "Temp_C": 37.2, "Potassium": 4.0, "Sodium": 139,
           "Chloride": 104, "Glucose": 130, "Calcium": 8.3, "HCO3": 24, "paO2": 100,
           "paCO2": 40, "Arterial_pH": 7.38}
    n = 16
    x0 = pd.DataFrame({f: mid[f] + (0.0 if f == "sex" else rng.normal(0, 1, n))
                       for f in FEATURES})
    doses = np.stack([rng.choice([0.0, 50.0, 400.0], (n, 4)),
                      rng.choice([0.0, 0.1, 0.5], (n, 4))], axis=2)
    seeds = (np.arange(n) // 4).astype(np.uint64)  # 4 sequences per X_0 draw
    direct = twin.simulate(x0, doses, seeds)
    cmd = [sys.executable, "-m", "twinfalsify.runs.serve", "biased", "--spec",
           json.dumps(spec), "--context", str(tmp_path)]
    served = simulate_via_protocol(cmd, x0, doses, seeds, workers=2, env=ENV, progress=False)
    np.testing.assert_array_equal(served.status, direct.status)
    np.testing.assert_array_equal(served.features, direct.features)
