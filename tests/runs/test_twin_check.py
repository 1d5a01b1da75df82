"""The conformance check (python -m twinfalsify.runs.check) names every fault it must catch.

Each case starts the fault-injecting twin (tests/fakes/faulty_twin.py) with one fault and
asserts that exactly the checks the fault breaks fail, each with its fix, and the rest pass
or are skipped (capabilities not advertised): a check that cannot fail, or one that fails
for the wrong reason, shows here. The clean twin passes every check, also with each
optional capability advertised.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ROOT

from twinfalsify.runs.check import (
    DEFAULT_TIMEOUT_S,
    FIX_LAG,
    FIXES,
    HINT_EXIT,
    HINT_UNFLUSHED,
    Outcome,
    data_reference,
    report,
    run_checks,
    shipped_x0,
)
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURE_TABLE
from twinfalsify.sources.synthetic import generate

ENV = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
X0 = shipped_x0()[:2]  # two patients keep each case to a few seconds

# faulty_twin.py arguments -> {check that must fail: fragment of its detail}
FAULTS: dict[str, tuple[list[str], dict[str, str]]] = {
    "crash": (["--mode", "crash"], {"protocol": "the twin exited during the run (worker "
                                                "exited with code 3",
                                    "simulates": "0 of 6 runs ok"}),
    "close_stdout": (["--mode", "close_stdout"], {
        "protocol": "the twin closed its stdout during the run (worker closed its stdout "
                    "but kept running (killed by the runner)",
        "simulates": "0 of 6 runs ok"}),
    "hang": (["--mode", "hang"], {"time": "without an answer within timeout_s = 2 s",
                                  "simulates": "stopped after 2 of 6 runs"}),
    "garbage": (["--mode", "garbage"], {"protocol": "not JSON: stdout must carry only",
                                        "simulates": "0 of 6"}),
    "malformed": (["--mode", "malformed"], {"protocol": "not JSON", "simulates": "0 of 6"}),
    "wrong_id": (["--mode", "wrong_id"], {"protocol": "does not match request id",
                                          "simulates": "0 of 6"}),
    "wrong_features": (["--mode", "wrong_features"], {"protocol": "unknown feature(s) "
                                                      "heart_rate", "simulates": "0 of 6"}),
    "fewer_hours": (["--mode", "fewer_hours"], {"protocol": "status ok but only 3 of 4 hours",
                                                "simulates": "0 of 6"}),
    "non_numeric": (["--mode", "non_numeric"], {"protocol": "HR is not a finite number",
                                                "simulates": "0 of 6"}),
    "irreversible": (["--mode", "irreversible"], {"simulates": "6 answered 'irreversible"}),
    "init_failed": (["--mode", "init_failed"], {"simulates": "6 answered 'init_failed"}),
    "error": (["--mode", "error"], {"simulates": "6 answered 'error: engine error"}),
    "implausible": (["--mode", "implausible"], {"ranges": "hour 2: HR = 1e+300 outside"}),
    "negative": (["--mode", "negative"], {"ranges": "hour 2: HR = -500 outside [0, 300] /min"}),
    "slow": (["--mode", "slow", "--delay", "1.2"], {"time": "(more than half of it)"}),
    "chatty": (["--mode", "chatty"], {"one answer": "'INFO simulated check.1'"}),
    "silent_unknown": (["--mode", "silent_unknown"], {"one answer": "no answer to an "
                                                      "unknown op"}),
    "nondeterministic": (["--mode", "nondeterministic"],
                         {"deterministic": "same request, same seed: hour 1",
                          "prefix": "2-hour run vs the first 2 hours"}),
    "lookahead": (["--mode", "lookahead"], {"prefix": "2-hour run vs the first 2 hours of a "
                                            "4-hour run: hour 1 HR"}),
    "batch_short": (["--batch", "4", "--mode", "batch_short:%2=0"],
                    {"batch": "results for a batch of 4 requests"}),
    "batch_differs": (["--batch", "4", "--mode", "batch_differs"], {"batch": "run 0: hour 1 HR"}),
    "stale_restore": (["--save-restore", "--mode", "stale_restore"],
                      {"save/restore": "sharing 2 hours with the previous run vs the same run "
                                       "alone: hour 3",
                       "X_0": "the same trajectory from 2 X_0"}),
    "early_truncate": (["--truncate", "--mode", "early_truncate"],
                       {"truncation": "truncated after hour 1, but a continue_while path "
                                      "still holds"}),
    "no_bye": (["--mode", "no_bye"], {"shutdown": "no bye within 5 s"}),
    "bad_hello": (["--mode", "bad_hello"], {"hello": "does not declare required feature(s) HR"}),
    "bad_units": (["--mode", "bad_units"], {"hello": "HR in 'Hz' (expected '/min')"}),
    "bad_protocol": (["--mode", "bad_protocol"], {"hello": "twin speaks protocol 2"}),
    "no_version": (["--mode", "no_version"],
                   {"hello": "hello field 'version' must be a string, got None"}),
    "no_hello": (["--mode", "no_hello"], {"starts": "exited before answering hello"}),
    "max_hours": (["--max-hours", "2"], {"hello": "max_hours 2 < T = 4"}),
    "unflushed": (["--mode", "unflushed"], {"hello": "no hello answer within 4 s; the hello "
                                            "answer came only when stdin was closed: stdout "
                                            "is not flushed"}),
    # wrong twins that speak the protocol perfectly: the behaviour rows name them
    "shifted": (["--mode", "shifted"], {"hour 1": "hour 1 equals X_0 in all 6 ok runs "
                                        "(every physiological feature): hours shifted",
                                        # its answers lag the doses by an hour, too
                                        "doses": "one hour late? (the action at hour 4 "
                                                 "changes nothing)"}),
    "glucose_mmol": (["--mode", "glucose_mmol"], {"units": "Glucose: twin median 8.2, X_0 "
                                                  "148 mg/dL: mmol/L?"}),
    "x0_ignored": (["--mode", "x0_ignored"], {"X_0": "the same trajectory from 2 X_0 that "
                                              "differ in 17 features"}),
    "dose2_ignored": (["--mode", "dose2_ignored"], {}),
    # drug errors: each drug is given alone, so one wrong drug shows
    "vaso_sign": (["--mode", "vaso_sign"], {}),
    "fluid_tiny": (["--mode", "fluid_tiny"], {}),
    "vaso_ignored": (["--mode", "vaso_ignored"], {}),
    "dose_lag": (["--mode", "dose_lag"], {"doses": "a drug given in hour h first changes an "
                                          "output at hour h + 1, never in its own hour (6 "
                                          "runs): doses applied one hour late?"}),
    "batch_leak": (["--batch", "4", "--mode", "batch_leak"], {"batch": "run 1: hour 1 HR"}),
    "nacl_swap": (["--mode", "nacl_swap"], {"units": "Sodium and Chloride swapped? (twin "
                                            "median Sodium 109, typical 120-160; Chloride "
                                            "142, typical 85-125 mmol/L)"}),
    "drift": (["--mode", "drift"], {"drift": "HR: twin median 97.4 at hour 1, 146 at hour 2 "
                                    "(typical 50-140 /min): drifts after hour 1? (and 1 "
                                    "more)"}),
}
# cases that pass with a warning -> {check: fragment of its detail}
WARNINGS: dict[str, dict[str, str]] = {
    "dose2_ignored": {"doses": "the action at hour 2 changes nothing"},
    # the cache ignores doses (and X_0) by design of the fault
    "stale_restore": {"doses": "the actions at hours 1, 2, 3, 4 change nothing"},
    "vaso_sign": {"effects": "the vasopressor lowers MAP (mean -0.005 mmHg over hours 1-4): "
                             "a sign error?"},
    "fluid_tiny": {"effects": "the IV fluid's largest MAP change (1e-05 mmHg) is under 1% of "
                              "the vasopressor's (0.005 mmHg): one drug's dose in the wrong "
                              "unit"},
    "vaso_ignored": {"doses": "the vasopressor changes nothing at any hour: ignored?"},
}


def _check(args: list[str]) -> list[Outcome]:
    return run_checks([*FAULTY_TWIN, *args], ENV, timeout_s=2.0, x0s=X0, startup_timeout_s=4.0)


def test_every_fault_mode_of_the_faulty_twin_has_a_case():
    from fakes.faulty_twin import RUN_MODES, TWIN_MODES

    # legal behaviour (ok, clamp) or a fault already covered (crash_once = crash, once)
    not_faults = {"ok", "clamp", "crash_once"}
    used = {args[k + 1].split(":")[0] for args, _ in FAULTS.values()
            for k, a in enumerate(args) if a == "--mode"}
    assert set(RUN_MODES + TWIN_MODES) - not_faults == used


@pytest.mark.slow  # ~1-3 s per case on an idle machine, more under load
@pytest.mark.parametrize("case", sorted(FAULTS))
def test_the_check_names_the_fault(case):
    args, expect = FAULTS[case]
    outcomes = _check(args)
    failed = {o.name: o for o in outcomes if o.ok is False}
    assert set(failed) == set(expect), report(outcomes)
    for name, fragment in expect.items():
        assert fragment in failed[name].detail, report(outcomes)
        # a twin that exits mid-run is pointed at its stderr, not at the protocol rules
        want = {("crash", "protocol"): HINT_EXIT, ("unflushed", "hello"): HINT_UNFLUSHED,
                ("dose_lag", "doses"): FIX_LAG, ("shifted", "doses"): FIX_LAG}.get(
            (case, name), FIXES[name])
        assert failed[name].fix == want
    warned = {o.name: o for o in outcomes if o.warn}
    assert set(warned) == set(WARNINGS.get(case, {})), report(outcomes)
    for name, fragment in WARNINGS.get(case, {}).items():
        assert fragment in warned[name].detail, report(outcomes)
        assert warned[name].fix == FIXES[name]
    names = dict.fromkeys(o.name for o in outcomes if o.ok is False)
    verdict = report(outcomes).splitlines()[-1]
    assert verdict.startswith(f"{len(failed)} check(s) failed: {', '.join(names)}"
                              if failed else "all checks passed"), verdict
    assert verdict.endswith(f"({len(warned)} warning(s): {', '.join(warned)})"
                            if warned else verdict)


@pytest.mark.slow
@pytest.mark.parametrize("caps", [[], ["--batch", "4"], ["--save-restore"], ["--truncate"],
                                  ["--mode", "clamp"]])
def test_a_conforming_twin_passes_every_check(caps):
    outcomes = _check(caps)
    assert not [o for o in outcomes if o.ok is False or o.warn], report(outcomes)
    passed = {o.name for o in outcomes if o.ok}
    assert {"hello", "protocol", "one answer", "simulates", "ranges", "time", "deterministic",
            "prefix", "shutdown", "hour 1", "X_0", "doses", "effects", "units",
            "drift"} <= passed
    optional = {"--batch": "batch", "--save-restore": "save/restore", "--truncate": "truncation"}
    for flag, name in optional.items():
        assert (name in passed) == (flag in caps), report(outcomes)


def test_shipped_x0_are_inside_the_contract():
    x0s = shipped_x0()
    assert len(x0s) == 4 and len({json.dumps(x, sort_keys=True) for x in x0s}) == 4
    for x0 in x0s:
        for f in FEATURE_TABLE:
            assert f.lo <= x0[f.name] <= f.hi


def test_command_line_exit_codes_and_table(tmp_path):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "twinfalsify.runs.check", *args],
                              capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=300)

    spec = {"kind": "command", "command": ["python", "tests/fakes/faulty_twin.py"],
            "timeout_s": 5}
    good = cli("--spec", json.dumps(spec))
    assert good.returncode == 0, good.stdout + good.stderr
    assert "all checks passed" in good.stdout
    config = tmp_path / "study.yaml"
    config.write_text(json.dumps({"twins": {"mine": {**spec, "command": [
        "python", "tests/fakes/faulty_twin.py", "--mode", "chatty"]}}}))
    bad = cli("--config", str(config), "--twin", "mine")
    assert bad.returncode == 1
    assert "one answer     FAIL  after the answer to check.1: 'INFO simulated check.1'" \
        in bad.stdout
    assert "fix: write exactly one JSON line per request" in bad.stdout
    wrong = cli("--config", str(config), "--twin", "yours")
    assert wrong.returncode == 2
    assert wrong.stderr.strip() == (f"twinfalsify.runs.check: error: {config}: no twin 'yours' "
                                    "under twins (found mine)")
    builtin = cli("--spec", '{"kind": "oracle"}')
    assert builtin.returncode == 2
    assert "the check runs twins of kind command or python" in builtin.stderr


def test_the_template_twin_of_the_tutorial_passes_every_check():
    outcomes = run_checks([sys.executable, str(ROOT / "docs" / "examples" / "template_twin.py")],
                          ENV, timeout_s=30.0, x0s=X0)
    assert not [o for o in outcomes if o.ok is False or o.warn], report(outcomes)
    assert {o.name for o in outcomes if o.ok is None} == {"batch", "save/restore", "truncation"}


def _effects(outcomes: list[Outcome]) -> dict[tuple[str, str], list[float]]:
    """The effects table as {(drug, feature): change per hour}."""
    rows, drug = {}, ""
    for line in next(o for o in outcomes if o.name == "effects").info[1:]:
        if line.startswith("("):
            break
        head, cells = line[:40], line[40:].split()
        drug = head[:34].strip().split(" ")[0] if head[:34].strip() else drug
        rows[(drug, head[34:].strip())] = [float(c) for c in cells]
    return rows


@pytest.mark.slow
def test_the_effects_table_is_each_drug_alone_against_no_drug():
    # the good faulty twin: every output moves by 0.001 (0.01 iv + 10 vaso) from the hour
    # the drug is given (module docstring of faulty_twin.py): 1000 mL/h -> +0.01, 0.5 -> +0.005
    good = _effects(_check([]))
    for feature in ("MAP", "SBP", "HR"):
        assert good[("IV", feature)] == pytest.approx([0.01] * 4, abs=5e-4)
        assert good[("vasopressor", feature)] == pytest.approx([0.005] * 4, abs=5e-4)
    signs = _effects(_check(["--mode", "vaso_sign"]))
    assert signs[("vasopressor", "MAP")] == pytest.approx([-0.005] * 4, abs=5e-4)
    assert signs[("IV", "MAP")] == pytest.approx([0.01] * 4, abs=5e-4)
    # the template twin (noisy, realistic sizes): both drugs raise MAP, the fluid by about
    # 0.02/3 + 2 * 0.01/3 per mL/h, the vasopressor by (25 + 2 * 12) / 3 per ug/kg/min
    template = _effects(run_checks([sys.executable, str(ROOT / "docs" / "examples" /
                                                        "template_twin.py")],
                                   ENV, timeout_s=30.0, x0s=X0))
    assert template[("IV", "MAP")][0] == pytest.approx(1000 * 0.04 / 3, abs=3.0)
    assert template[("vasopressor", "MAP")][0] == pytest.approx(0.5 * 49 / 3, abs=3.0)


def test_the_default_timeout_is_the_studys():
    # a twin the check passes must not be timed out by a study of the same spec
    twin = make_twin("mine", {"kind": "command", "command": ["python", "x.py"]})
    assert DEFAULT_TIMEOUT_S == twin.timeout_s == 600.0


@pytest.mark.slow
def test_units_are_screened_against_the_data_when_given():
    data = generate({"n_stays": 200}, seed=3)
    reference = data_reference(data)
    assert 100 < reference["Glucose"] < 170  # mg/dL, the data's own hour 1
    outcomes = run_checks([*FAULTY_TWIN, "--mode", "glucose_mmol"], ENV, timeout_s=2.0,
                          x0s=X0, reference=reference, startup_timeout_s=4.0)
    units = next(o for o in outcomes if o.name == "units")
    assert units.ok is False
    assert units.detail.startswith("Glucose: twin median 8.2, data ")
    assert units.detail.endswith(" mg/dL: mmol/L?")
    good = run_checks(FAULTY_TWIN, ENV, timeout_s=2.0, x0s=X0, reference=reference,
                      startup_timeout_s=4.0)
    assert next(o for o in good if o.name == "units").ok, report(good)


def test_an_unflushed_twin_is_named_within_seconds_and_a_slow_start_is_not(monkeypatch):
    """With the waits a study uses (hello may take max(timeout_s, the startup timeout)),
    a twin that never flushes stdout is named after FIRST_ANSWER_S, not after its whole
    timeout; a twin that flushes but answers hello after the first-answer deadline passes."""
    import time

    from twinfalsify.runs import check

    start = time.monotonic()
    outcomes = run_checks([*FAULTY_TWIN, "--mode", "unflushed"], ENV, timeout_s=600.0,
                          x0s=X0)
    took = time.monotonic() - start
    hello = next(o for o in outcomes if o.name == "hello")
    assert hello.ok is False and hello.fix == HINT_UNFLUSHED, report(outcomes)
    assert hello.detail.startswith(f"no answer within {check.FIRST_ANSWER_S:g} s: does the "
                                   "twin flush stdout after each line?"), hello.detail
    assert took < check.FIRST_ANSWER_S + 25, took  # seconds, not the 600 s timeout
    monkeypatch.setattr(check, "FIRST_ANSWER_S", 1.0)
    slow = run_checks([*FAULTY_TWIN, "--hello-delay", "2.5"], ENV, timeout_s=2.0, x0s=X0,
                      startup_timeout_s=30.0)
    assert all(o.ok is not False for o in slow), report(slow)
    assert next(o for o in slow if o.name == "hello").ok is True
