"""The table source: your own hourly trajectories in the trajectory contract.

Checked here: a table exported from the synthetic world reads back as exactly the synthetic
world's trajectories (CSV and Parquet, one file or a folder); every broken rule of the
bad-input corpus (tests/bad_inputs/tables.yaml) stops in one line naming the file, row,
column and rule; the parse-time config check; and, end to end, a study run on the exported
table gives byte-for-byte the synthetic study's results.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers.paths import BAD_INPUTS, ROOT
from helpers.workflow import copy_study, run_snakemake

from twinfalsify.schema import ContractError, validate_trajectories
from twinfalsify.sources.synthetic import generate
from twinfalsify.sources.table import main as table_cli
from twinfalsify.sources.table import read_table, to_table, write_table
from twinfalsify.studyconfig import study_config_error

SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
CASES = yaml.safe_load((BAD_INPUTS / "tables.yaml").read_text())


@pytest.fixture(scope="module")
def small() -> pd.DataFrame:
    """20 stays of the synthetic world as a table (rows by stay, then hour)."""
    return to_table(generate({"n_stays": 20}, seed=3))


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".csv.gz"])
def test_exported_table_reads_back_as_the_synthetic_trajectories(tmp_path, suffix):
    traj = validate_trajectories(generate({"n_stays": 300}, seed=5))
    path = tmp_path / f"t{suffix}"
    write_table(to_table(traj), path)
    back = read_table(path)
    assert (back.pop("subject_id") == back["stay_id"]).all()  # kept: the split uses it
    pd.testing.assert_frame_equal(back, traj)  # every value bit for bit, dtypes, order
    assert (back.to_numpy() == traj.to_numpy()).all()


def test_a_folder_of_files_in_any_row_order_is_one_table(tmp_path):
    traj = validate_trajectories(generate({"n_stays": 60}, seed=1))
    table = to_table(traj).sample(frac=1.0, random_state=0)  # rows shuffled
    write_table(table.iloc[:100], tmp_path / "part-a.csv")
    write_table(table.iloc[100:], tmp_path / "part-b.parquet")
    (tmp_path / "README.txt").write_text("not a table: ignored")
    pd.testing.assert_frame_equal(read_table(tmp_path).drop(columns="subject_id"), traj)


def test_extra_columns_are_ignored_and_the_last_hours_dose_may_be_empty(tmp_path, small):
    table = small.assign(lactate=1.0)
    table.loc[table["t"] == 4, ["iv_fluid", "vasopressor"]] = np.nan
    write_table(table, tmp_path / "t.csv")
    back = read_table(tmp_path / "t.csv")
    assert "lactate" not in back and back["iv_fluid"].isna().sum() == 20


def _edited(table: pd.DataFrame, edit: dict) -> pd.DataFrame:
    df = table.copy()
    (op, arg), = edit.items()
    if op == "drop_column":
        return df.drop(columns=[arg])
    if op == "rename":
        return df.rename(columns=arg)
    if op == "drop_row":
        return df.drop(index=arg - 1)
    if op == "duplicate_row":
        return pd.concat([df, df.iloc[[arg - 1]]], ignore_index=True)
    if op == "add_hour":
        return pd.concat([df, df.iloc[[4]].assign(t=arg)], ignore_index=True)
    if op == "set":
        value = np.nan if arg["value"] is None else arg["value"]
        col = arg["column"]
        if isinstance(value, str) or (isinstance(value, float) and not value.is_integer()):
            df[col] = df[col].astype(object)
        df.loc[arg["row"] - 1, col] = value
        return df
    raise ValueError(op)


@pytest.mark.parametrize("case", sorted(CASES))
def test_broken_table_rule_is_one_line_naming_file_row_column_and_rule(case, tmp_path, small):
    spec = CASES[case]
    path = tmp_path / f"{case}.csv"
    _edited(small, spec["edit"]).to_csv(path, index=False)
    with pytest.raises(ContractError) as err:
        read_table(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(str(path)), msg
    for fragment in spec["expect"]:
        assert fragment.replace("<file>", str(path)) in msg, msg


def test_parquet_rows_are_named_without_csv_lines(tmp_path, small):
    table = small.copy()
    table.loc[2, "vasopressor"] = -0.1
    write_table(table, tmp_path / "t.parquet")
    with pytest.raises(ContractError, match=r"t\.parquet: row 3 \(stay_id 200001, t 2\), "
                                            r"column vasopressor: -0\.1"):
        read_table(tmp_path / "t.parquet")


def test_the_first_offending_row_is_named_in_file_order(tmp_path, small):
    table = small.copy()
    table.loc[[30, 12], "HR"] = 400.0  # rows 31 and 13: row 13 comes first
    write_table(table, tmp_path / "t.csv")
    with pytest.raises(ContractError, match="row 13 "):
        read_table(tmp_path / "t.csv")


def test_check_command_names_the_problem_or_says_ok(tmp_path, small, capsys):
    write_table(small, tmp_path / "good.csv")
    assert table_cli(["check", str(tmp_path / "good.csv")]) == 0
    assert "ok, 20 stays, 100 rows" in capsys.readouterr().out
    write_table(small.drop(columns=["RR"]), tmp_path / "bad.csv")
    with pytest.raises(ContractError, match="missing column"):
        table_cli(["check", str(tmp_path / "bad.csv")])


# ---- the config: checked when the workflow is parsed ----------------------------------


def _config(source: dict) -> dict:
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["source"] = source
    cfg["twins"] = {"fitted": {"kind": "fitted"}}
    return cfg


def test_config_checks_the_table_before_any_work(tmp_path, small):
    write_table(small, tmp_path / "t.csv")
    good = {"kind": "table", "table": {"path": str(tmp_path / "t.csv")}}
    assert study_config_error(_config(good), SCHEMA) is None
    cases = {
        "no path": ({"kind": "table"}, "source.table.path: kind table needs the path"),
        "missing file": ({"kind": "table", "table": {"path": str(tmp_path / "nope.csv")}},
                         "nope.csv does not exist"),
        "empty folder": ({"kind": "table", "table": {"path": str(tmp_path / "empty")}},
                         "holds no table file"),
        "not a table": ({"kind": "table", "table": {"path": str(tmp_path / "x.xlsx")}},
                        "is not a table file"),
        "missing column": ({"kind": "table", "table": {"path": str(tmp_path / "bad.csv")}},
                           "missing column(s) Glucose"),
    }
    (tmp_path / "empty").mkdir()
    (tmp_path / "x.xlsx").write_text("")
    write_table(small.drop(columns=["Glucose"]), tmp_path / "bad.csv")
    for name, (source, fragment) in cases.items():
        msg = study_config_error(_config(source), SCHEMA)
        assert msg and msg.startswith("config key source.table.path: ") and "\n" not in msg, name
        assert fragment in msg, (name, msg)
    # the builtin twins that simulate the synthetic world need it
    cfg = _config({"kind": "table", "table": {"path": str(tmp_path / "t.csv")}})
    cfg["twins"] = {"oracle": {"kind": "oracle"}}
    assert "needs source.kind: synthetic" in study_config_error(cfg, SCHEMA)


# ---- end to end ------------------------------------------------------------------------


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not {"logs", "benchmarks"} & set(p.relative_to(folder).parts)}


@pytest.mark.slow
def test_study_on_the_exported_table_equals_the_synthetic_study_byte_for_byte(
    tmp_path, monkeypatch, test_study
):
    """config/test.yaml's study with the builtin twin a table source can use (fitted), once
    on the synthetic world and once on its trajectories exported as a CSV table: every
    result, table, figure and the summary are equal byte for byte. Apart: what only the
    synthetic world has (its confounding figure, which needs the true interventional law),
    the twin context, which records the source, and the trajectory tables, which carry the
    table's subject_id column and are otherwise equal.

    The synthetic study continues a copy of the shared config/test.yaml study
    (``test_study``: every step before the twins is the same; its two builtin twins, which a
    table source cannot run, are removed from the copy); the table study runs from scratch."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "0")  # PDFs carry no creation time
    base = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    # a served twin on a table source: the tutorial's command twin (test_tutorial_own_twin);
    # served = in-process for builtin twins: test_twin_integration_workflow
    base["twins"] = {"fitted": {"kind": "fitted"}}
    table = tmp_path / "table" / "trajectories.csv"
    write_table(to_table(generate(base["source"]["synthetic"], seed=base["seed"])), table)
    copy_study(test_study[0], tmp_path / "synthetic")
    for twin in yaml.safe_load(test_study[1].read_text())["twins"]:
        shutil.rmtree(tmp_path / "synthetic" / "results" / base["study"] / "twins" / twin)
    trees = {}
    for name, source in (("synthetic", base["source"]),
                         ("table", {"kind": "table", "table": {"path": str(table)}})):
        work = tmp_path / name
        work.mkdir(exist_ok=True)
        config = work / "study.yaml"
        config.write_text(yaml.safe_dump({**base, "source": source}))
        run = run_snakemake(work, config, "--cores", "2")
        assert run.returncode == 0, run.stderr[-3000:]
        trees[name] = _tree(work / "results" / base["study"])
    syn, tab = trees["synthetic"], trees["table"]
    only_synthetic = {k for k in syn if k.startswith("figures/confounding.")}
    assert only_synthetic == {"figures/confounding.png", "figures/confounding.pdf"}
    assert set(tab) == set(syn) - only_synthetic
    differ = sorted(k for k in tab if tab[k] != syn[k])
    # the trajectory tables differ only by the table's subject_id column (one patient per
    # stay, which is what the synthetic source's trajectories mean without it)
    trajectory_tables = ["d.parquet", "d0.parquet", "trajectories.parquet"]
    assert differ == [*trajectory_tables, "twin_context.json"], differ
    for name in trajectory_tables:
        a = pd.read_parquet(tmp_path / "table" / "results" / base["study"] / name)
        b = pd.read_parquet(tmp_path / "synthetic" / "results" / base["study"] / name)
        assert (a.pop("subject_id") == a["stay_id"]).all()
        pd.testing.assert_frame_equal(a, b)
    assert len(tab) > 30 and "twins/fitted/figures/pvalues.pdf" in tab
    assert os.environ["SOURCE_DATE_EPOCH"] == "0"


@pytest.mark.slow
def test_workflow_stops_at_a_broken_table_in_one_line_before_any_other_rule(tmp_path, small):
    table = small.copy()
    table.loc[13, "HR"] = np.nan
    write_table(table, tmp_path / "mine.csv")
    cfg = _config({"kind": "table", "table": {"path": "mine.csv"}})  # relative to the workdir
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(cfg))
    run = run_snakemake(tmp_path, tmp_path / "study.yaml", "--cores", "1")
    assert run.returncode != 0
    line = "mine.csv: row 14 (line 15, stay_id 200003, t 3), column HR: missing value"
    log = (tmp_path / "results" / "test" / "logs" / "trajectories.log").read_text()
    rule = ("(rule: every feature every hour; carry the last value charted at or before the "
            "hour forward, never backward)")
    assert log.strip().splitlines()[-1].endswith(f" ERROR: {line} {rule}")
    # and the run's last line, after Snakemake's own closing lines (the Snakefile's onerror)
    assert run.stderr.strip().splitlines()[-1] == f"ERROR: {line} {rule}", run.stderr[-800:]
    assert "Traceback" not in run.stderr
    # nothing but logs, and the twin's hello (a job with no data inputs, run beside the
    # extraction)
    outputs = [p for p in (tmp_path / "results" / "test").rglob("*")
               if p.is_file() and not {"logs", "benchmarks"} & set(p.parts)
               and p.name != "hello.json"]
    assert outputs == [], outputs


def test_workflow_stops_at_a_table_in_another_unit_before_any_twin_runs(tmp_path, small):
    table = small.copy()
    table["Glucose"] = table["Glucose"] / 18.016  # mmol/L, inside the contract's range
    write_table(table, tmp_path / "mmol.csv")
    cfg = _config({"kind": "table", "table": {"path": "mmol.csv"}})
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(cfg))
    run = run_snakemake(tmp_path, tmp_path / "study.yaml", "--cores", "1")
    assert run.returncode != 0
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("ERROR: mmol.csv: the rows follow the contract, but a feature looks "
                           "like another unit than the contract's: Glucose: data median "), last
    assert last.endswith(", typical 60-350 mg/dL: mmol/L?; convert it "
                         "(docs/reference/table.md)"), last
    assert "Traceback" not in run.stderr
    outputs = [p for p in (tmp_path / "results" / "test").rglob("*")
               if p.is_file() and not {"logs", "benchmarks"} & set(p.parts)
               and p.name != "hello.json"]
    assert outputs == [], outputs


def test_the_table_check_screens_units(tmp_path):
    from twinfalsify.sources.synthetic import generate
    from twinfalsify.sources.table import main, to_table, unit_suspects, write_table

    traj = generate({"n_stays": 60}, seed=5)
    assert unit_suspects(traj) == []
    table = to_table(traj)
    table["Glucose"] = table["Glucose"] / 18.016  # mmol/L, labelled mg/dL by the contract
    path = tmp_path / "mmol.csv"
    write_table(table, path)
    assert main(["check", str(path)]) == 1
    (message,) = unit_suspects(traj.assign(Glucose=traj["Glucose"] / 18.016))
    assert message.startswith("Glucose: data median 7.")
    assert message.endswith(", typical 60-350 mg/dL: mmol/L?")


def test_table_messages_show_what_the_file_holds(tmp_path):
    from twinfalsify.sources.synthetic import generate
    from twinfalsify.sources.table import read_table, to_table, write_table

    table = to_table(generate({"n_stays": 3}, seed=1))
    half = table.astype({"stay_id": float})
    half.loc[0, "stay_id"] = 201204.5
    half.to_csv(tmp_path / "half.csv", index=False)
    with pytest.raises(ContractError, match=r"column stay_id: 201204\.5 is not an integer"):
        read_table(tmp_path / "half.csv")
    table.head(0).to_csv(tmp_path / "header.csv", index=False)
    with pytest.raises(ContractError) as err:
        read_table(tmp_path / "header.csv")
    assert str(err.value) == f"{tmp_path / 'header.csv'}: a header and no rows (rule: at " \
                             "least one stay)"
    table.to_csv(tmp_path / "semi.csv", index=False, sep=";")
    with pytest.raises(ContractError, match="the file is separated by ';', the table "
                                            "contract's CSV by ','"):
        read_table(tmp_path / "semi.csv")
    write_table(table, tmp_path / "good.csv")
    assert len(read_table(tmp_path / "good.csv")) == len(table)
