"""Fail fast, flag implausible values, never leave a stale result.

- the circuit breaker stops a twin that fails every run (a log line on stdout, a crash)
  within ``fail_fast_runs`` runs / ``max_restarts`` restarts, in one line naming the command
  and the first failure;
- a value outside the trajectory contract's range is stored as status ``implausible``
  (counts as failed), for protocol twins and in-process twins alike;
- duplicated YAML keys, too many shards, too many runs per sequence are named;
- the code fingerprint of a rule covers exactly the library modules its script reaches.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV, ROOT
from helpers.twins import study_bits, zero_dose_inputs

from twinfalsify import provenance
from twinfalsify.io import load_yaml_strict
from twinfalsify.runs.plan import run_shard
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.schema import FEATURE_BY_NAME, FEATURES, ContractError, mark_implausible
from twinfalsify.studyconfig import N_ACTIONS, shard_count
from twinfalsify.twins.base import SimResult

HR = FEATURES.index("HR")


def _many(n: int, t: int = 2):
    rng = np.random.default_rng(1)
    x0 = pd.DataFrame({f: rng.uniform(50, 100, n).round(3) for f in FEATURES})
    x0["sex"] = 1.0
    return x0, np.zeros((n, t, 2)), np.arange(100, 100 + n, dtype=np.uint64)


# ---- circuit breaker ----------------------------------------------------------------------


@pytest.mark.parametrize("workers", [1, 2])
def test_stdout_logging_twin_stops_within_k_runs(tmp_path, workers):
    """A twin that logs to stdout fails every run: the shard stops after K runs, not n."""
    log = tmp_path / "requests.log"
    k, n = 8, 200
    cmd = [*FAULTY_TWIN, "--mode=garbage", f"--log-requests={log}"]
    with pytest.raises(ContractError) as err:
        simulate_via_protocol(cmd, *_many(n), env=ENV, workers=workers, retries=2,
                              fail_fast_runs=k, progress=False)
    msg = str(err.value)
    assert "\n" not in msg
    assert f"its first {k} runs, from {k} distinct X_0, all failed" in msg
    assert "faulty_twin.py" in msg and "--mode=garbage" in msg  # the command
    assert "stdout must carry only protocol JSON" in msg and "log line on stdout" in msg
    asked = len(log.read_text().splitlines())
    assert k <= asked <= k + workers, asked  # at most one run in flight per other worker


def test_crashing_twin_stops_after_max_restarts(tmp_path):
    log = tmp_path / "requests.log"
    cmd = [*FAULTY_TWIN, "--mode=crash", f"--log-requests={log}"]
    with pytest.raises(ContractError) as err:
        simulate_via_protocol(cmd, *_many(100), env=ENV, retries=2, fail_fast_runs=0,
                              max_restarts=5, progress=False)
    msg = str(err.value)
    assert "workers restarted 5 times before any run was ok" in msg
    assert "first failure: error: worker exited with code 3" in msg
    # 1 start + 5 restarts answered; the 6th restart trips before its request
    assert len(log.read_text().splitlines()) == 6


def test_breaker_leaves_a_partly_failing_twin_alone():
    """Failures mixed with ok runs (even more than K of them) never trip the breaker."""
    # a hard X_0 after the first ok run: all its runs crash in a row, far more restarts
    # than max_restarts, and each run is recorded (the breaker only guards the start)
    x0, doses, seeds = _many(30)
    crash = ",".join(str(s) for s in seeds[5:20])
    res = simulate_via_protocol([*FAULTY_TWIN, f"--mode=crash:{crash}"], x0, doses, seeds,
                                env=ENV, retries=1, fail_fast_runs=3, max_restarts=2,
                                progress=False)
    assert (res.status == "error").sum() == 15 and (res.status == "ok").sum() == 15
    res = simulate_via_protocol([*FAULTY_TWIN, "--mode=error:%4=1", "--mode=error:%4=2"],
                                *_many(60), env=ENV, retries=0, fail_fast_runs=5,
                                max_restarts=1, progress=False)
    failed = (res.status != "ok").sum()
    assert failed == 30 and (res.status == "ok").sum() == 30


def test_breaker_off_with_zero_records_every_failure():
    res = simulate_via_protocol([*FAULTY_TWIN, "--mode=error"], *_many(30), env=ENV,
                                retries=0, fail_fast_runs=0, progress=False)
    assert list(set(res.status)) == ["error"] and len(res.status) == 30


@pytest.mark.parametrize("key", ["fail_fast_runs", "max_restarts"])
def test_breaker_options_are_checked(key):
    with pytest.raises(ContractError, match=f"{key} must be an integer >= 0, got -1"):
        simulate_via_protocol([*FAULTY_TWIN], *zero_dose_inputs(), env=ENV, progress=False,
                              **{key: -1})


# ---- implausible values -------------------------------------------------------------------


@pytest.mark.parametrize(("mode", "shown"), [("implausible", "1e+300"), ("negative", "-500")])
def test_protocol_twin_value_outside_contract_is_implausible(mode, shown):
    """Served over the protocol: runs whose twin gave HR 1e300 / -500 at hour 2 are
    stored as implausible from node 1-2 on; node 1 (hour 1) and the other runs stay ok."""
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    x0, plan, actions = study_bits()
    seeds = plan.run_seeds()
    twin = ProtocolTwin("faulty", [*FAULTY_TWIN, f"--mode={mode}:%2=0"], env=ENV,
                        progress=False, retries=0)
    runs = run_shard(twin, plan, 0, x0, actions, log=open("/dev/null", "w"))
    spoiled = {int(s) for s, seed in zip(plan.x0_stay_ids, seeds, strict=True) if seed % 2 == 0}
    assert 0 < len(spoiled) < len(seeds)
    for row in runs.itertuples():
        if row.init_stay_id in spoiled and row.t >= 2:
            assert row.status == "implausible" and np.isnan(row.HR)
            assert row.message == f"hour 2: HR = {shown} /min outside the plausible range [0, 300]"
        else:
            assert row.status == "ok" and np.isfinite(row.HR), row


def test_mark_implausible_agrees_with_the_contract_brute_force():
    rng = np.random.default_rng(5)
    n, t = 400, 4
    lo = np.array([FEATURE_BY_NAME[f].lo for f in FEATURES])
    hi = np.array([FEATURE_BY_NAME[f].hi for f in FEATURES])
    feats = rng.uniform(lo, hi, (n, t, len(FEATURES)))
    # spoil 1 % of cells: below, above, infinite; and end some runs early with NaN
    cells = rng.random(feats.shape) < 0.01
    feats[cells] = rng.choice([-1e9, 1e9, np.inf, -np.inf], cells.sum())
    feats[rng.random(n) < 0.2, 3] = np.nan
    status = np.full(n, "ok", dtype=object)
    message = np.full(n, "", dtype=object)
    before = feats.copy()
    marked = mark_implausible(feats, status, message)
    for i in range(n):
        bad_hours = [h for h in range(t) for j in range(len(FEATURES))
                     if not np.isnan(before[i, h, j]) and not lo[j] <= before[i, h, j] <= hi[j]]
        if bad_hours:
            h = min(bad_hours)
            assert status[i] == "implausible" and message[i].startswith(f"hour {h + 1}: ")
            np.testing.assert_array_equal(feats[i, :h], before[i, :h])
            assert np.isnan(feats[i, h:]).all()
        else:
            assert status[i] == "ok" and message[i] == ""
            np.testing.assert_array_equal(feats[i], before[i])
    assert marked == (status == "implausible").sum() > 0


class _WildTwin:
    """In-process twin: HR of X_0 + 1e300 for the second X_0, fine otherwise."""

    name = "wild"

    def simulate(self, x0, doses, seeds):
        n, t = doses.shape[:2]
        feats = np.repeat(x0[list(FEATURES)].to_numpy(float)[:, None, :], t, axis=1)
        feats[1, :, HR] = 1e300
        return SimResult(feats, np.full(n, "ok", dtype=object))


def test_in_process_twin_value_outside_contract_is_implausible():
    x0, plan, actions = study_bits(3)
    runs = run_shard(_WildTwin(), plan, 0, x0, actions, log=open("/dev/null", "w"))
    second = plan.x0_stay_ids[1]
    bad = runs[runs.init_stay_id == second]
    assert set(bad.status) == {"implausible"} and bad.HR.isna().all() and len(bad) == 3
    assert bad.message.iloc[0].startswith("hour 1: HR = 1e+300 /min")
    assert set(runs[runs.init_stay_id != second].status) == {"ok"}


# ---- config: duplicated keys, shard cap, runs per sequence --------------------------------


def test_duplicated_yaml_key_names_key_and_both_lines(tmp_path):
    path = tmp_path / "study.yaml"
    path.write_text("study: x\ntesting:\n  alpha: 0.05\n  correction: holm\n  alpha: 0.5\n")
    with pytest.raises(ContractError) as err:
        load_yaml_strict(path)
    assert str(err.value) == (f"{path}: key 'alpha' is written twice (lines 3 and 5); "
                              "YAML would keep only the last")
    path.write_text("a: {b: 1}\nc: [1, {b: 2}]\n")  # the same key in different maps is fine
    assert load_yaml_strict(path) == {"a": {"b": 1}, "c": [1, {"b": 2}]}


def test_yaml_merge_keys_are_accepted_and_duplicates_still_refused(tmp_path):
    """``<<: *anchor`` merges defaults the mapping may override (YAML's merge rule); a key
    the mapping itself writes twice is still refused, next to a merge key too."""
    path = tmp_path / "study.yaml"
    path.write_text("base: &twin {kind: oracle, timeout_s: 30}\n"
                    "extra: &more {workers: 2}\n"
                    "twins:\n"
                    "  a:\n    <<: *twin\n    timeout_s: 60\n"
                    "  b:\n    <<: [*twin, *more]\n")
    cfg = load_yaml_strict(path)
    assert cfg["twins"] == {"a": {"kind": "oracle", "timeout_s": 60},
                            "b": {"kind": "oracle", "timeout_s": 30, "workers": 2}}
    path.write_text("base: &twin {kind: oracle}\ntwins:\n  a:\n    <<: *twin\n"
                    "    seed: 1\n    seed: 2\n")
    with pytest.raises(ContractError, match=r"key 'seed' is written twice \(lines 5 and 6\)"):
        load_yaml_strict(path)


def test_n_shards_is_capped_at_the_number_of_actions():
    assert shard_count({"twin_runs": {"n_shards": 4}}) == (4, None)
    assert shard_count({"twin_runs": {"n_shards": N_ACTIONS}}) == (N_ACTIONS, None)
    n, warning = shard_count({"twin_runs": {"n_shards": 1000}})
    assert n == N_ACTIONS == 25
    assert warning.startswith("config key twin_runs.n_shards: 1000 asked") and "25" in warning


def test_runs_per_sequence_above_d_warns_once_with_both_numbers(caplog):
    from twinfalsify.runs.plan import plan_twin_runs

    hyps = pd.DataFrame({"actions": [(1, 2), (1, 3)]})
    with caplog.at_level("WARNING", logger="twinfalsify"):
        plan = plan_twin_runs(hyps, np.arange(50), 5000, 2, seed=1)
    assert len(plan.x0_stay_ids) == 50
    lines = [r.getMessage() for r in caplog.records if "runs_per_sequence" in r.getMessage()]
    assert len(lines) == 1 and "5000 asked" in lines[0] and "only 50 stays" in lines[0]
    caplog.clear()
    with caplog.at_level("WARNING", logger="twinfalsify"):
        plan_twin_runs(hyps, np.arange(50), 40, 2, seed=1)
    assert not caplog.records


# ---- code fingerprints --------------------------------------------------------------------


def test_fingerprint_covers_exactly_the_modules_a_script_reaches(tmp_path):
    """bounds.py is reached by the tests rule, not by the split rule; editing it changes
    the first fingerprint only; editing an unrelated module changes neither."""
    import shutil

    src = tmp_path / "src"
    shutil.copytree(ROOT / "src" / "twinfalsify", src / "twinfalsify")
    scripts = ROOT / "scripts"
    reach = {s: provenance.script_modules(scripts / f"{s}.py", src) for s in ("split", "tests")}
    assert "twinfalsify.bounds" in reach["tests"]
    assert "twinfalsify.bounds" not in reach["split"]
    # the costly twin stage does not reach the statistics: a fix there reruns no twin run
    for costly in ("twin_plan", "twin_shard", "twin_runs"):
        assert "twinfalsify.bounds" not in provenance.script_modules(
            scripts / f"{costly}.py", src), costly
    assert {"twinfalsify", "twinfalsify.split", "twinfalsify.schema"} <= reach["split"]
    before = {s: provenance.code_fingerprint(scripts / f"{s}.py", src) for s in reach}
    bounds = src / "twinfalsify" / "bounds.py"
    bounds.write_text(bounds.read_text() + "\n# a fix\n")
    provenance._graph_cached.cache_clear()
    after = {s: provenance.code_fingerprint(scripts / f"{s}.py", src) for s in reach}
    assert after["split"] == before["split"] and after["tests"] != before["tests"]
    # a served twin's module, named as extra, joins the closure
    assert "twinfalsify.runs.serve" not in provenance.script_modules(
        scripts / "twin_shard.py", src)
    assert "twinfalsify.runs.serve" in provenance.script_modules(
        scripts / "twin_shard.py", src, ["twinfalsify.runs.serve"])


# ---- what reruns (snakemake -n on a finished small study) ---------------------------------


# ---- the workflow refuses at parse time, writing nothing ----------------------------------


def _snakemake(tmp_path, text: str, *args: str):
    from slurm.runs import run

    config = tmp_path / "study.yaml"
    config.write_text(text)
    done = run(tmp_path, config, *args, "--cores", "1", timeout=300)
    return done, done.stdout + done.stderr


@pytest.mark.slow
def test_snakemake_refuses_a_duplicated_key(tmp_path):
    text = (ROOT / "config" / "test.yaml").read_text() + "seed: 8\n"
    done, out = _snakemake(tmp_path, text)
    assert done.returncode != 0
    line = next(ln for ln in out.splitlines() if ln.startswith("invalid config: "))
    assert line.endswith("study.yaml: key 'seed' is written twice (lines 3 and 18); YAML "
                         "would keep only the last"), line
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
def test_snakemake_refuses_a_results_path_it_cannot_write(tmp_path):
    (tmp_path / "results").write_text("not a folder")
    done, out = _snakemake(tmp_path, (ROOT / "config" / "test.yaml").read_text())
    assert done.returncode != 0
    assert f"cannot write results under results/test: {tmp_path / 'results'} is a file, " \
           "not a folder" in out, out[-2000:]
    assert (tmp_path / "results").read_text() == "not a folder"


@pytest.mark.slow
def test_snakemake_caps_n_shards_and_says_so(tmp_path):
    import yaml

    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["twin_runs"]["n_shards"] = 1000
    done, out = _snakemake(tmp_path, yaml.safe_dump(cfg), "-n")
    assert done.returncode == 0, out[-2000:]
    assert ("WARNING: config key twin_runs.n_shards: 1000 asked, but a shard holds whole "
            "first-action groups and there are 25 actions: using 25 shards") in out
    assert out.count("rule twin_shard:") == 25 * len(cfg["twins"])


def test_rule_script_os_error_is_one_line(tmp_path, capsys):
    """A rule that cannot write (read-only or full disk, a file where a folder should be)
    ends with one line naming the path, exit 1."""
    from types import SimpleNamespace

    from twinfalsify.io import run_rule, unwritable, write_parquet

    blocker = tmp_path / "results"
    blocker.write_text("x")
    target = blocker / "test" / "d.parquet"
    sm = SimpleNamespace(log=[str(tmp_path / "rule.log")], rule="split")
    with pytest.raises(SystemExit) as ex:
        run_rule(sm, lambda _: write_parquet(pd.DataFrame({"a": [1]}), target))
    assert ex.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"ERROR: {blocker / 'test'}: Not a directory"), err
    assert unwritable(blocker / "test") == (
        f"cannot write results under {blocker / 'test'}: {blocker} is a file, not a folder")
    assert unwritable(tmp_path / "new" / "deeper") is None


def test_twin_context_stays_valid_when_the_study_folder_moves(tmp_path):
    """twin_context.json names D0 relative to its own folder: a moved copy still builds."""
    import json
    import shutil

    from twinfalsify.runs.registry import make_twin
    from twinfalsify.sources.synthetic import generate

    old = tmp_path / "old" / "results" / "s"
    old.mkdir(parents=True)
    generate({"n_stays": 60}, seed=2).to_parquet(old / "d0.parquet")
    (old / "twin_context.json").write_text(json.dumps(
        {"source": {"kind": "synthetic", "synthetic": {"n_stays": 60}}, "d0": "d0.parquet"}))
    new = tmp_path / "elsewhere" / "s"
    shutil.move(old, new)
    twin = make_twin("f", {"kind": "fitted"}, new / "twin_context.json")
    x0, doses, seeds = study_bits(3)[0], np.zeros((3, 2, 2)), np.arange(3, dtype=np.uint64)
    assert np.isfinite(twin.simulate(x0, doses, seeds).features).all()


# ---- a twin's child holding its pipes -----------------------------------------------------

DAEMON_TWIN = [FAULTY_TWIN[0], str(Path(FAULTY_TWIN[1]).with_name("daemon_twin.py"))]


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, killed but not yet reaped by init, counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


def _ended(pids: list[int], within_s: float = 3.0) -> bool:
    """Whether every pid has ended (a SIGKILL takes effect asynchronously: wait a little)."""
    deadline = time.monotonic() + within_s
    while any(_alive(p) for p in pids):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


@pytest.fixture
def child_pids(tmp_path):
    """The pid file of daemon_twin.py; children still alive afterwards are killed."""
    pid_file = tmp_path / "children.pid"
    yield pid_file
    for pid in (int(p) for p in pid_file.read_text().split()) if pid_file.exists() else ():
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("escape", [False, True], ids=["in_group", "escaped"])
def test_child_holding_stdout_does_not_stall_the_shard(child_pids, escape):
    """The twin answers and exits; its child keeps stdout open for 120 s. The shard ends
    in seconds, and a child still in the twin's process group is killed with it."""
    cmd = [*DAEMON_TWIN, f"--pid-file={child_pids}", *(["--escape"] if escape else [])]
    t0 = time.monotonic()
    res = simulate_via_protocol(cmd, *_many(6), env=ENV, workers=2, timeout_s=30,
                                progress=False)
    took = time.monotonic() - t0
    assert list(res.status) == ["ok"] * 6
    assert took < 15, took
    pids = [int(p) for p in child_pids.read_text().split()]
    assert len(pids) == 2
    if not escape:
        assert _ended(pids), pids


def test_crash_while_a_child_holds_stdout_is_a_crash_not_a_timeout(child_pids):
    """The twin crashes on every run while its child keeps stdout open: each attempt ends
    as a crash within seconds, not after the run's time limit (60 s here)."""
    cmd = [*DAEMON_TWIN, f"--pid-file={child_pids}", "--mode=crash:3"]
    x0, doses, seeds = _many(3)
    seeds = np.array([3, 5, 7], dtype=np.uint64)
    t0 = time.monotonic()
    res = simulate_via_protocol(cmd, x0, doses, seeds, env=ENV, timeout_s=60, retries=1,
                                progress=False)
    took = time.monotonic() - t0
    assert list(res.status) == ["error", "ok", "ok"]
    assert "worker exited with code 3" in res.message[0]
    assert took < 20, took
    assert _ended([int(p) for p in child_pids.read_text().split()])


# ---- full disk ----------------------------------------------------------------------------

_WRITE_BIG = """
import resource, sys
import numpy as np, pandas as pd
from twinfalsify import io
from twinfalsify.schema import ContractError
kind, path = sys.argv[1], sys.argv[2]
resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))  # ulimit -f: 200 kB
df = pd.DataFrame(np.random.default_rng(0).normal(size=(50_000, 8)), columns=list("abcdefgh"))
try:
    if kind == "parquet":
        io.write_parquet(df, path)
    elif kind == "csv":
        io.write_csv(df, path)
    elif kind == "text":
        io.write_text(df.to_csv(), path)
    else:
        import matplotlib.pyplot as plt
        from twinfalsify.figures import save_all
        fig, ax = plt.subplots()
        ax.plot(df["a"].to_numpy(), df["b"].to_numpy(), ".")
        save_all(fig, path)
except ContractError as exc:
    print(exc)
    sys.exit(2)
"""


@pytest.mark.parametrize("kind,name", [("parquet", "runs.parquet"), ("csv", "t.csv"),
                                       ("text", "t.txt"), ("figure", "f.pdf")])
def test_full_disk_is_one_line_and_leaves_no_temporary_file(tmp_path, kind, name):
    """A write that hits the file size limit (as a full disk would) ends in one line naming
    the file and the folder's free space; no temporary file stays behind. A later write
    that succeeds also removes a temporary file an earlier, killed writer left."""
    import subprocess
    import sys

    out = tmp_path / "results" / name
    done = subprocess.run([sys.executable, "-c", _WRITE_BIG, kind, str(out)], env={
        **os.environ, **ENV}, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr[-2000:]
    line = done.stdout.strip()
    assert "\n" not in line and line.startswith(f"{out}: cannot write: File too large ("), line
    assert f"free in {out.parent})" in line
    assert sorted(p.name for p in out.parent.iterdir()) == []  # no half file, no .tmp
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = out.parent / f".{name}.{dead}.tmp"  # left by a writer killed with -9
    stale.write_bytes(b"x" * 1000)
    done = subprocess.run([sys.executable, "-c", _WRITE_BIG.replace("200_000", "-1"), kind,
                           str(out)], env={**os.environ, **ENV}, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in out.parent.iterdir()) == [name]


# ---- smaller: warnings in the shard log, answer line cap ----------------------------------


def _in_rule(tmp_path, body):
    """Run ``body`` as a rule script does (io.run_rule: console and the rule's log file);
    return the log file's lines."""
    from types import SimpleNamespace

    from twinfalsify.io import run_rule

    log = tmp_path / "shard_0.log"
    run_rule(SimpleNamespace(log=[str(log)], rule="twin_shard"), lambda sm: body())
    return log.read_text().splitlines()


def test_implausible_shard_warning_reaches_the_shard_log(tmp_path):
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    x0, plan, actions = study_bits()
    twin = ProtocolTwin("faulty", [*FAULTY_TWIN, "--mode=implausible:%2=0"], env=ENV,
                        progress=False, retries=0)
    lines = _in_rule(tmp_path, lambda: run_shard(twin, plan, 0, x0, actions))
    assert any("WARNING: twin faulty shard 0:" in ln and "runs implausible" in ln
               for ln in lines), lines


def test_mixed_twin_versions_are_logged_as_a_warning(tmp_path):
    from twinfalsify.runs.plan import twin_hellos

    hellos = [{"name": "t", "version": "1"}, {"name": "t", "version": "2"}]
    lines = _in_rule(tmp_path, lambda: twin_hellos(hellos))
    assert any("WARNING: twin runs come from different twin versions" in ln for ln in lines)


def test_an_answer_line_over_the_cap_is_a_protocol_error_not_a_memory_blow_up(monkeypatch):
    """A twin that writes a huge line (here: over a cap lowered to 64 kB) gets the run an
    error naming the cap; the line is not read into memory."""
    from twinfalsify.runs import worker

    monkeypatch.setattr(worker, "MAX_LINE_BYTES", 64 << 10)
    monkeypatch.setattr(worker.Worker.ask, "__defaults__", (64 << 10,))
    x0, doses, seeds = _many(2)
    seeds = np.array([3, 4], dtype=np.uint64)
    script = ("import sys, runpy\n"
              "real = sys.stdout.write\n"
              "def write(s):\n"
              "    if '\"op\":\"result\"' in s and '\"id\":\"0.' in s:\n"
              "        s = 'x' * (1 << 20) + s\n"
              "    return real(s)\n"
              "sys.stdout.write = write\n"
              f"sys.argv = [{FAULTY_TWIN[1]!r}]\n"
              f"runpy.run_path({FAULTY_TWIN[1]!r}, run_name='__main__')\n")
    res = simulate_via_protocol([FAULTY_TWIN[0], "-c", script], x0, doses, seeds, env=ENV,
                                retries=0, progress=False, fail_fast_runs=0)
    assert list(res.status) == ["error", "ok"], list(res.message)  # run 0's answer is huge
    assert "answer line longer than 65,536 bytes, the cap for this request" in res.message[0]


def test_figure_files_are_byte_identical_across_runs(tmp_path):
    """The same figure saved twice, seconds apart (two runs of a study), gives the same bytes
    in PNG and PDF: no creation date in the files, so a checksum of results/ is stable."""
    import matplotlib.pyplot as plt

    from twinfalsify.figures import save_all

    def draw(folder):
        fig, ax = plt.subplots()
        ax.plot([0, 1, 2], [1, 3, 2], marker="o")
        ax.set_title("HR")
        save_all(fig, folder / "f.png", folder / "f.pdf")

    draw(tmp_path / "a")
    time.sleep(1.1)  # a PDF's creation date has one-second resolution
    draw(tmp_path / "b")
    for name in ("f.png", "f.pdf"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
