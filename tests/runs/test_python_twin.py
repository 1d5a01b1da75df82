"""``kind: python`` twins: a factory returning the builtin twins' interface, in-process or
served over the protocol (workers > 1), with the same numbers either way."""

from __future__ import annotations

import os

import numpy as np
import pytest
from helpers.paths import FAKES

from twinfalsify.runs.check import command_of, report, run_checks, shipped_x0
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.registry import check_spec, make_twin, python_fingerprint
from twinfalsify.schema import FEATURES, ContractError

SPEC = {"kind": "python", "factory": "py_twin:make", "path": str(FAKES),
        "options": {"hr_step": 3.0}}


def _inputs(n: int = 6, hours: int = 4):
    import pandas as pd

    x0 = pd.DataFrame(shipped_x0() * 2)[list(FEATURES)].iloc[:n]
    rng = np.random.default_rng(0)
    doses = np.stack([rng.choice([0.0, 100.0, 250.0], (n, hours)),
                      rng.choice([0.0, 0.1, 0.3], (n, hours))], axis=-1)
    return x0, doses, np.arange(1, n + 1, dtype=np.uint64)


def test_in_process_and_served_give_byte_identical_results():
    here = make_twin("py", SPEC)
    assert not isinstance(here, ProtocolTwin) and here.name == "py"
    served = make_twin("py", {**SPEC, "workers": 2})
    assert isinstance(served, ProtocolTwin)
    x0, doses, seeds = _inputs()
    a, b = here.simulate(x0, doses, seeds), served.simulate(x0, doses, seeds)
    assert list(b.status) == ["ok"] * len(seeds)
    assert a.features.tobytes() == b.features.tobytes()
    # the factory's options reach the twin: HR drifts 3 /min per hour on top of the doses
    flat = make_twin("py", {**SPEC, "options": {}}).simulate(x0, doses, seeds)
    hr = FEATURES.index("HR")
    assert np.allclose(a.features[:, :, hr] - flat.features[:, :, hr], 3.0 * np.arange(1, 5))


def test_the_fingerprint_follows_the_module_source(tmp_path):
    (tmp_path / "mytwin.py").write_text((FAKES / "py_twin.py").read_text())
    spec = {**SPEC, "factory": "mytwin:make", "path": str(tmp_path)}
    before = python_fingerprint(spec)
    assert len(before) == 16 and python_fingerprint({"kind": "oracle"}) == ""
    (tmp_path / "mytwin.py").write_text((FAKES / "py_twin.py").read_text() + "\n# edited\n")
    assert python_fingerprint(spec) != before


@pytest.mark.parametrize(("spec", "message"), [
    ({"kind": "python", "factory": "py_twin"}, "twins.t.factory: kind python needs "
                                               "'module:callable'"),
    ({"kind": "python", "factory": "no_such_module:make", "path": str(FAKES)},
     "twins.t.factory: cannot find module 'no_such_module'"),
    ({"kind": "oracle", "factory": "py_twin:make"}, "twins.t.factory: only kind python"),
])
def test_bad_python_specs_are_named(spec, message):
    with pytest.raises(ContractError, match="^" + message.replace("(", r"\(")):
        check_spec("t", spec, {"kind": "synthetic"})


def test_a_python_twin_that_returns_no_twin_is_named():
    with pytest.raises(ContractError, match="returned PyTwin|has no callable"):
        make_twin("t", {**SPEC, "factory": "py_twin:PyTwin.simulate"})


@pytest.mark.slow
def test_the_check_runs_a_python_twin_over_the_protocol():
    command, env, timeout = command_of(SPEC, "py")
    env = {**(env or os.environ)}
    outcomes = run_checks(command, env, 30.0, shipped_x0()[:2], startup_timeout_s=30.0)
    assert not [o for o in outcomes if o.ok is False], report(outcomes)
    assert next(o for o in outcomes if o.name == "hello").detail.startswith("py ")
