"""Bad-input corpus: every bad input gives one clear line, a non-zero exit, no partial output.

Config cases (tests/bad_inputs/configs.yaml) are checked twice: the one-line message from
``studyconfig.study_config_error`` (the schema, non-finite numbers, and what needs the
library: methods and options, quantile order, figure outcomes, twin specs) names the dotted
key and the problem, and ``snakemake`` itself exits
non-zero on them, naming the key, with nothing written under results/. Data cases call the
library entry points (``validate_trajectories``, ``split_stays``, ``fit_action_bins``,
``build_hypotheses``, the protocol runner) on a small valid input with one defect each.
Run-level twin faults (malformed JSON, wrong feature names, fewer hours) are recorded per run
with status ``error`` and a message: the runner never drops or invents a run.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import pandas as pd
import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import BAD_INPUTS, ENV, ROOT
from helpers.twins import zero_dose_inputs
from helpers.workflow import BASE_CONFIG
from slurm.runs import run

from twinfalsify import design
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.schema import STAY_ID, TIME, ContractError, validate_trajectories
from twinfalsify.sources.synthetic import generate
from twinfalsify.split import split_stays
from twinfalsify.studyconfig import study_config_error

CORPUS = BAD_INPUTS
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
CONFIG_CASES = yaml.safe_load((CORPUS / "configs.yaml").read_text())
FAULTY = FAULTY_TWIN


def edited_config(edit: dict) -> dict:
    cfg = copy.deepcopy(yaml.safe_load(BASE_CONFIG.read_text()))
    for dotted, value in edit.items():
        *parents, last = dotted.split(".")
        node = cfg
        for p in parents:
            node = node[p]
        if value == "DELETE":
            del node[last]
        elif isinstance(value, str) and value.startswith("RENAME:"):
            node[value.removeprefix("RENAME:")] = node.pop(last)
        else:
            node[last] = value
    return cfg


# ---- config cases -------------------------------------------------------------------------


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_config_error_is_one_line_naming_the_key(case):
    spec = CONFIG_CASES[case]
    msg = study_config_error(edited_config(spec["edit"]), SCHEMA)
    assert msg is not None and "\n" not in msg
    assert msg.startswith("config key ")
    for fragment in spec["expect"]:
        assert fragment in msg, msg
    assert study_config_error(edited_config({}), SCHEMA) is None


@pytest.mark.slow
@pytest.mark.parametrize("case", ["misspelt_nested_key", "unknown_outcome", "seed_wrong_type",
                                  "alpha_nan", "reversed_quantiles", "unknown_method_option",
                                  "shift_unknown_feature", "hoeffding_factor_zero",
                                  "command_program_does_not_exist", "command_script_missing",
                                  "seed_too_large", "study_dotdot", "study_dot",
                                  "twin_dotdot", "study_300_characters",
                                  "seed_float_integral"])
def test_snakemake_refuses_bad_config_and_writes_nothing(case, tmp_path):
    spec = CONFIG_CASES[case]
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(edited_config(spec["edit"])))
    done = run(tmp_path, config, "--cores", "1", timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    # one line naming the key path and the problem (common.smk calls io.config_error)
    line = next((ln for ln in out.splitlines() if ln.startswith("invalid config: config key")), "")
    assert line, out[-2000:]
    assert any(f.strip("'") in line for f in spec["expect"]), line
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
def test_cohort_too_small_for_split_fails_in_rule_without_partial_output(tmp_path):
    """20 stays with a 1 % D0 leave D0 empty: the split rule fails, leaving no d0/d file."""
    cfg = edited_config({"source.synthetic.n_stays": 20, "split.d0_fraction": 0.01})
    config = tmp_path / "small.yaml"
    config.write_text(yaml.safe_dump(cfg))
    done = run(tmp_path, config, "--cores", "1", timeout=300)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    log = (tmp_path / "results" / "test" / "logs" / "split.log").read_text().strip()
    last = log.splitlines()[-1]
    assert "ERROR: split: 20 stay(s) with d0_fraction 0.01 leave D0 with 0 stay(s)" in last
    assert "need at least one stay in each of D0 and D" in out
    r = tmp_path / "results" / "test"
    assert (r / "trajectories.parquet").exists()  # the step before it is kept (valid)
    leftovers = [p.name for p in r.iterdir() if p.is_file()]
    assert leftovers == ["trajectories.parquet"], leftovers


# ---- data cases ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def traj() -> pd.DataFrame:
    return validate_trajectories(generate({"n_stays": 40}, seed=3), source="synthetic")


def _set(df, col, value, row=7):
    df = df.copy()
    df[col] = df[col].astype(object) if isinstance(value, str) else df[col]
    df.loc[row, col] = value
    return df


def _fahrenheit(df):
    df = df.copy()
    df.loc[df[STAY_ID] == df[STAY_ID].iloc[0], "Temp_C"] = 98.6
    return df


TRAJECTORY_CASES: dict[str, tuple[Callable[[pd.DataFrame], pd.DataFrame], list[str]]] = {
    "missing_column": (
        lambda d: d.drop(columns=["Glucose"]),
        ["trajectories.parquet: missing column(s) Glucose"],
    ),
    "nan_feature": (
        lambda d: _set(d, "HR", np.nan),
        ["column HR has 1 missing value(s), e.g. stay_id"],
    ),
    "fahrenheit_in_celsius_column": (
        _fahrenheit,
        ["column Temp_C (degC)", "outside the plausible range [25, 45]", "98.6", "Fahrenheit"],
    ),
    "negative_dose": (
        lambda d: _set(d, "iv_fluid", -50.0, row=0),
        ["column iv_fluid must be finite and >= 0; found -50"],
    ),
    "duplicated_stay_rows": (
        lambda d: pd.concat([d, d.iloc[[5]]]),
        ["duplicated (stay_id, t): stay_id 200002 has t = 0 more than once"],
    ),
    "fewer_hours_than_asked": (
        lambda d: d[~((d[STAY_ID] == d[STAY_ID].iloc[0]) & (d[TIME] == 4))],
        ["every stay needs hours t = 0..4", "has 4 row(s)"],
    ),
    "hour_out_of_range": (
        lambda d: _set(d, TIME, 9, row=4),
        ["column t has values outside 0..4: [9]"],
    ),
    "non_numeric_feature": (
        lambda d: _set(d, "Sodium", "140 mmol/L"),
        ["column Sodium is not numeric"],
    ),
    "sex_not_binary": (
        lambda d: _set(d, "sex", 2.0, row=0),
        ["column sex"],
    ),
    "empty_table": (lambda d: d.iloc[:0], ["no trajectories (empty table)"]),
}


@pytest.mark.parametrize("case", sorted(TRAJECTORY_CASES))
def test_bad_trajectory_table_is_refused_in_one_line(case, traj):
    corrupt, fragments = TRAJECTORY_CASES[case]
    with pytest.raises(ContractError) as err:
        validate_trajectories(corrupt(traj), source="data/trajectories.parquet")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("data/trajectories.parquet: ")
    for fragment in fragments:
        assert fragment in msg, msg


def test_empty_cohort_after_split(traj):
    with pytest.raises(ContractError, match=r"leave D0 with 0 stay\(s\)"):
        split_stays(traj, 0.01, seed=1)


def test_d0_too_small_to_form_action_bins(traj):
    d0, _ = split_stays(traj, 0.1, seed=1)  # 4 stays
    with pytest.raises(ContractError) as err:
        design.fit_action_bins(d0, min_nonzero=50)
    assert "design: D0 has" in str(err.value)
    assert "fewer than the 50 needed to form its quartile bins" in str(err.value)


def test_d0_too_small_to_form_any_hypothesis(traj):
    d0, _ = split_stays(traj, 0.1, seed=1)
    actions, states = design.fit_action_bins(d0), design.fit_state_bins(d0)
    with pytest.raises(ContractError, match="no hypothesis could be formed on D0"):
        design.build_hypotheses(d0, actions, states, min_support=10_000)


# ---- twins --------------------------------------------------------------------------------


def test_twin_executable_that_does_not_exist():
    with pytest.raises(FileNotFoundError, match="twin command not found on PATH: 'no-such-twin'"):
        simulate_via_protocol(["no-such-twin"], *zero_dose_inputs(), progress=False)


@pytest.mark.parametrize(
    ("mode", "fragment"),
    [
        ("bad_units", "HR in 'Hz' (expected '/min')"),  # wrong units
        ("bad_hello", "does not declare required feature(s) HR"),  # wrong feature names
        ("bad_protocol", "speaks protocol 2"),
    ],
)
def test_unusable_twin_is_refused_before_any_run(mode, fragment):
    with pytest.raises(ContractError) as err:
        simulate_via_protocol([*FAULTY, f"--mode={mode}"], *zero_dose_inputs(), env=ENV,
                              progress=False)
    assert fragment in str(err.value) and "faulty_twin.py" in str(err.value)


@pytest.mark.parametrize(
    ("mode", "fragment"),
    [("malformed", "JSON"), ("wrong_features", "heart_rate"), ("fewer_hours", "hour")],
)
def test_bad_answers_are_recorded_per_run_not_dropped(mode, fragment):
    res = simulate_via_protocol(
        [*FAULTY, f"--mode={mode}:11"], *zero_dose_inputs(), env=ENV, retries=0, progress=False
    )
    status = list(res.status)
    assert status == ["ok", "error", "ok"], status
    assert fragment.lower() in str(res.message[1]).lower(), res.message[1]
