"""No stale result, no needless rerun: `snakemake -n` on a finished study with a command twin.

One small synthetic study (Hoeffding only) with a builtin twin and a ``kind: command`` twin
(the fault-injection twin, run as a script named in its command) that can never initialise
the first X_0 its shards schedule, with ``fail_fast_runs: 3``:

- the study finishes; that patient's runs are recorded ``init_failed``, every other run ok;
- editing the command twin's script reruns exactly its shards and what follows (none of the
  builtin twin's jobs); the same bytes written back rerun nothing;
- an edit of the MIMIC-III source package or of an unused test method (betting.py) reruns
  nothing; an edit of the method in use (hoeffding.py) still reruns the tests;
- a rule script rewritten with the same bytes reruns nothing under ``--rerun-triggers mtime
  params input`` (the profiles' and make's setting); new bytes rerun its rule;
- execution-only keys of a served twin rerun nothing; a library edit reruns exactly the rules
  whose scripts reach the edited module and what follows them.

The tests share one study and edit its repository copy in place, each restoring what it
edits: they run in order on one worker (``conftest``: a module fixture groups its module).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from shlex import quote as shlex_quote

import pandas as pd
import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import ROOT
from helpers.workflow import copy_repo, copy_study

from twinfalsify import provenance

pytestmark = pytest.mark.slow


def _snakemake(repo, work, config, *args, timeout=2400):
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(repo / "Snakefile"), "--directory",
         str(work), "--configfile", str(config), "--cores", "2", *args],
        capture_output=True, text=True, timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(repo / "src"), "MPLBACKEND": "Agg"})


def dry_run(repo, work, config, *args: str) -> dict[str, list[str]]:
    """{rule: [output of each job]} that `snakemake -n` would run."""
    done = _snakemake(repo, work, config, "-n", *args, timeout=300)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    jobs: dict[str, list[str]] = {}
    for m in re.finditer(r"^ *(?:local)?rule (\w+):\n((?: +.*\n)*)", out, re.M):
        outputs = re.search(r"output: (.*)", m.group(2))
        jobs.setdefault(m.group(1), []).append(outputs.group(1) if outputs else "")
    return jobs


@contextmanager
def edited(path: Path):
    """``path`` with a comment appended (new bytes, as an edit), restored afterwards."""
    text = path.read_text()
    path.write_text(text + "\n# an edit\n")
    try:
        yield path
    finally:
        path.write_text(text)


def n_jobs(jobs: dict[str, list[str]]) -> int:
    return sum(len(v) for v in jobs.values())


@pytest.fixture(scope="module")
def study(tmp_path_factory, test_study):
    """A finished study (repo copy, work folder, config) with the command twin 'ext':
    config/test.yaml with its oracle served over the twin protocol and 'ext' added, run from
    the repository copy on a copy of the finished config/test.yaml study (conftest's
    ``test_study``): what that study built and this config keeps (every step before the twins,
    the in-process biased twin) is up to date, so only the served oracle, 'ext' and the
    summary are built by this fixture. ``build.log`` beside the config holds every rule that
    ran, in both runs."""
    from twinfalsify.runs.plan import TwinPlan

    tmp = tmp_path_factory.mktemp("reruns")
    repo = tmp / "repo"
    copy_repo(repo)
    work = copy_study(test_study[0], tmp / "work")
    (work / "twin").mkdir()
    shutil.copy(FAULTY_TWIN[1], work / "twin" / "faulty_twin.py")
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    assert cfg["twin_runs"]["n_shards"] == 2
    cfg["twins"]["oracle"] = {"kind": "oracle", "protocol": True, "workers": 1,
                              "timeout_s": 60, "retries": 1}
    plan = TwinPlan.from_json(yaml.safe_load(
        (work / "results" / cfg["study"] / "twin_plan.json").read_text()))
    seeds = plan.run_seeds()
    first = int(seeds.min())  # every shard's runs come grouped by X_0, lowest seed first
    patient = plan.x0_stay_ids[int(seeds.argmin())]
    cfg["twins"]["ext"] = {"kind": "command",
                           "command": f"python twin/faulty_twin.py --mode=init_failed:{first}",
                           "workers": 1, "timeout_s": 30, "fail_fast_runs": 3}
    config = tmp / "study.yaml"
    config.write_text(yaml.safe_dump(cfg))
    done = _snakemake(repo, work, config)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert "rule trajectories:" not in done.stdout + done.stderr  # the shared study's
    # every rule that ran: the shared study's build, then this one
    (tmp / "build.log").write_text((test_study[0] / "build.log").read_text()
                                   + done.stdout + done.stderr)
    return repo, work, config, cfg, patient


def test_a_twin_failing_one_patient_finishes_its_study(study):
    repo, work, config, cfg, patient = study
    runs = pd.read_parquet(work / "results" / cfg["study"] / "twins" / "ext" / "runs.parquet")
    mine = runs["init_stay_id"] == patient
    assert mine.any() and (runs.loc[mine, "status"] == "init_failed").all()
    assert (runs.loc[~mine, "status"] == "ok").all()
    assert (work / "results" / cfg["study"] / "twins" / "ext" / "results.parquet").exists()
    summary = yaml.safe_load(
        (work / "results" / cfg["study"] / "twins" / "ext" / "run_summary.json").read_text())
    assert summary["twin"] == {"name": "faulty", "version": "1"}  # what its hello said


def test_editing_a_command_twins_script_reruns_exactly_its_shards(study):
    repo, work, config, cfg, _ = study
    assert dry_run(repo, work, config) == {}
    script = work / "twin" / "faulty_twin.py"
    text = script.read_text()
    script.write_text(text + "\n# a fix\n")
    jobs = dry_run(repo, work, config)
    assert len(jobs["twin_shard"]) == cfg["twin_runs"]["n_shards"]
    outputs = [o for outs in jobs.values() for o in outs]
    # nothing of the builtin twins; outside the twin's folder only the study summary
    assert not [o for o in outputs if "/twins/" in o and "/twins/ext/" not in o], outputs
    assert {r for r, outs in jobs.items() if any("/twins/ext/" not in o for o in outs)} \
        <= {"summary", "all"}, jobs
    for rule in ("trajectories", "split", "design", "twin_plan"):
        assert rule not in jobs
    script.write_text(text)  # the same bytes again, a newer time: nothing to do
    assert dry_run(repo, work, config) == {}


@pytest.mark.parametrize(("path", "reruns"), [
    ("src/twinfalsify/sources/mimic3/tables.py", False),  # a synthetic study
    ("src/twinfalsify/inference/betting.py", False),  # Hoeffding only
    ("src/twinfalsify/inference/bernstein.py", False),
    ("src/twinfalsify/inference/hoeffding.py", True),  # the method in use
])
def test_library_edits_rerun_what_this_config_uses(study, path, reruns):
    repo, work, config, cfg, _ = study
    f = repo / path
    with edited(f):
        jobs = dry_run(repo, work, config)
    assert bool(jobs) == reruns, jobs
    if reruns:
        assert "tests" in jobs and "twin_shard" not in jobs and "trajectories" not in jobs


CONTENT_ONLY = ("--rerun-triggers", "mtime", "params", "input")  # as profiles/default


def test_a_finished_study_started_from_another_checkout_has_nothing_to_do(study, tmp_path):
    """Another clone of the repository in another folder (fresh file times), started with
    the plain command: the project's profile (profiles/default, read by Snakemake from the
    Snakefile's folder) gives its rerun triggers, so nothing reruns; without the profile
    Snakemake's code trigger would rerun every job."""
    repo, work, config, cfg, _ = study
    other = copy_repo(tmp_path / "elsewhere" / "checkout")
    for f in other.rglob("*"):  # a fresh clone: every file newer than the study's outputs
        if f.is_file():
            os.utime(f)
    assert dry_run(other, work, config) == {}
    assert dry_run(other, work, config, "--workflow-profile", "none")  # Snakemake's default
    moved = tmp_path / "moved"  # the study folder moved with mv, started again
    shutil.move(work, moved)
    try:
        assert dry_run(other, moved, config) == {}
    finally:
        shutil.move(moved, work)


def test_a_rule_script_with_the_same_bytes_reruns_nothing(study):
    """Snakemake's own code trigger compares the script's time with its outputs': without it
    (CONTENT_ONLY) the code param, which holds the script's bytes, decides."""
    repo, work, config, cfg, _ = study
    script = repo / "scripts" / "tests.py"
    text, st = script.read_bytes(), script.stat()
    script.unlink()
    script.write_bytes(text)  # as `git checkout` does: same bytes, new file, new time
    try:
        assert dry_run(repo, work, config, *CONTENT_ONLY) == {}
        # Snakemake's own default, without the project's profile: by time
        assert "tests" in dry_run(repo, work, config, "--workflow-profile", "none")
        assert dry_run(repo, work, config) == {}  # the project's profile: by content
        script.write_bytes(text + b"\n# an edit\n")  # new bytes: the rule and what follows
        jobs = dry_run(repo, work, config, *CONTENT_ONLY)
        assert "tests" in jobs and "twin_shard" not in jobs and "design" not in jobs, jobs
    finally:
        script.write_bytes(text)
        os.utime(script, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert dry_run(repo, work, config) == {}


# ---- which edits rerun what -------------------------------------------------------------


def _rule_scripts(repo) -> dict[str, str]:
    """rule name -> the script it runs, read from workflow/rules/*.smk."""
    import re

    out = {}
    for smk in (repo / "workflow" / "rules").glob("*.smk"):
        for block in re.split(r"\n(?=rule \w+:)", smk.read_text()):
            m = re.match(r"rule (\w+):", block)
            s = re.search(r'scripts/(\w+)\.py', block)
            if m and s:
                out[m.group(1)] = s.group(1)
    return out


def _dry_run(work, config, repo):
    """{rule: reason} of the jobs `snakemake -n` would run (empty: nothing to do)."""
    import re
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(repo / "Snakefile"), "--directory",
         str(work), "--configfile", str(config), "-n", "--cores", "2"],
        capture_output=True, text=True, timeout=300,
        env={**__import__("os").environ, "PYTHONPATH": str(repo / "src")},
    )
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    jobs: dict[str, set[str]] = {}
    # grouped jobs (the twin shards) are listed indented under "Group job twin_shards"
    for m in re.finditer(r"^ *(?:local)?rule (\w+):\n(?: +.*\n)*? +reason: (.*)$", out, re.M):
        jobs.setdefault(m.group(1), set()).add(m.group(2))
    return jobs


def test_what_reruns_after_which_change(study):
    """On the finished study: execution-only keys of its served twin rerun nothing; a library
    edit reruns exactly the rules whose scripts reach the edited module (params changed) and
    what is downstream of them (inputs updated); a builtin twin's module reruns the shards."""
    import re

    repo, work, config, cfg, _ = study
    build_log = (config.parent / "build.log").read_text()
    assert _dry_run(work, config, repo) == {}
    original = config.read_text()

    # execution-only keys of a served twin: no shard, no job at all
    changed = {**cfg, "twins": {**cfg["twins"], "oracle": {
        **cfg["twins"]["oracle"], "workers": 2, "timeout_s": 90, "retries": 0, "batch_size": 7,
        "fail_fast_runs": 5, "max_restarts": 3}}}
    config.write_text(yaml.safe_dump(changed))
    try:
        assert _dry_run(work, config, repo) == {}
    finally:
        config.write_text(original)

    # a library edit: exactly the rules whose scripts reach bounds.py, by params
    bounds = repo / "src" / "twinfalsify" / "bounds.py"
    with edited(bounds):
        jobs = _dry_run(work, config, repo)
    reach = {rule for rule, script in _rule_scripts(repo).items()
             if "twinfalsify.bounds" in provenance.script_modules(
                 repo / "scripts" / f"{script}.py", repo / "src")}
    ran = set(re.findall(r"^ *(?:local)?rule (\w+):", build_log, re.M))
    by_params = {r for r, why in jobs.items() if any("Params have changed" in w for w in why)}
    # Snakemake gives one reason per job: a job whose inputs an earlier rerun job rewrites
    # says so, even if its params changed too; so: every rule of the study that reaches
    # bounds.py reruns, a rerun for changed params is always one of them, and every other
    # rerun is downstream of one of them
    assert reach & ran <= set(jobs), (reach & ran) - set(jobs)
    assert by_params and by_params <= reach, by_params
    others = set(jobs) - reach
    assert all(any("updated by another job" in w for w in jobs[r]) for r in others), jobs
    for rule in ("trajectories", "split", "design", "twin_plan", "twin_shard", "twin_runs"):
        assert rule in ran and rule not in jobs, (rule, jobs.get(rule))
    assert _dry_run(work, config, repo) == {}  # back as it was: nothing to do

    # a builtin twin's module: both twins' shards (and what follows), not the design stage
    builtin = repo / "src" / "twinfalsify" / "twins" / "builtin.py"
    with edited(builtin):
        jobs = _dry_run(work, config, repo)
    # the shards rerun; Snakemake gives one reason per job, and the first is the twin's
    # hello (its code is the shard's), rerun by params, which the shards wait for
    assert "twin_shard" in jobs and any("Params have changed" in w for w in jobs["twin_hello"])
    for rule in ("trajectories", "split", "design", "observational_side", "twin_plan"):
        assert rule not in jobs, (rule, jobs.get(rule))
    assert _dry_run(work, config, repo) == {}


# ---- over-broad reruns, reruns on every start, the documented remedy ----------------------


@pytest.mark.parametrize("module", ["runs/runner.py", "runs/worker.py",
                                    "runs/command.py"])
def test_a_protocol_client_edit_reruns_no_in_process_twin(study, module):
    """The builtin twin simulated in the shard's own process (biased) never runs the protocol
    client: editing it reruns the shards of the twins that run through it (the served oracle,
    the command twin), none of biased's."""
    repo, work, config, cfg, _ = study
    f = repo / "src" / "twinfalsify" / module
    with edited(f):
        jobs = dry_run(repo, work, config, *CONTENT_ONLY)
    shards = jobs.get("twin_shard", [])
    assert {o.split("/twins/")[1].split("/")[0] for o in shards} == {"oracle", "ext"}, jobs
    assert not [o for outs in jobs.values() for o in outs if "/twins/biased/" in o], jobs
    assert dry_run(repo, work, config, *CONTENT_ONLY) == {}


def test_a_command_as_a_list_is_the_same_twin(study):
    """The command twin's command written as a list of words instead of one string: the same
    words run, so nothing reruns."""
    import shlex

    repo, work, config, cfg, _ = study
    original = config.read_text()
    listed = {**cfg, "twins": {**cfg["twins"], "ext": {
        **cfg["twins"]["ext"], "command": shlex.split(cfg["twins"]["ext"]["command"])}}}
    config.write_text(yaml.safe_dump(listed))
    try:
        assert dry_run(repo, work, config, *CONTENT_ONLY) == {}
    finally:
        config.write_text(original)


@pytest.mark.parametrize("code", [".", "results", "results/test/twins"])
def test_a_code_path_holding_the_results_is_refused_when_the_config_is_read(study, code):
    """``code: [.]`` would put what the study writes into the twin's fingerprint (a rerun on
    every start): one line when the config is read, no job runs."""
    repo, work, config, cfg, _ = study
    original = config.read_text()
    bad = {**cfg, "twins": {**cfg["twins"], "ext": {**cfg["twins"]["ext"], "code": [code]}}}
    config.write_text(yaml.safe_dump(bad))
    try:
        done = _snakemake(repo, work, config, "-n", timeout=300)
    finally:
        config.write_text(original)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    line = next(ln for ln in out.splitlines() if ln.startswith("invalid config:"))
    assert line.startswith(f"invalid config: twins.ext.code: {code!r} ")
    assert "the results folder results" in line and "rerun it on every start" in line


def test_the_documented_rerun_of_one_twin_reruns_exactly_that_twin(study):
    """The docs' one command for a change the workflow cannot see (run-workflow.md, "Rerun
    one twin"), run as written: the twin's shards and what follows are rebuilt, no shard
    or result of another twin; afterwards nothing is left to do."""
    repo, work, config, cfg, _ = study
    doc = (ROOT / "docs" / "how-to" / "run-workflow.md").read_text()
    block = doc.split("<!-- rerun-one-twin -->", 1)[1].split("```bash\n", 1)[1].split("```")[0]
    command = block.strip()
    assert command.startswith("snakemake ") and "\n" not in command
    study_name = cfg["study"]
    (work / "config").mkdir(exist_ok=True)
    shutil.copy(config, work / "config" / f"{study_name}.yaml")
    command = command.replace("<study>", study_name).replace("<twin>", "ext").replace(
        "snakemake ", f"{shlex_quote(sys.executable)} -m snakemake -s "
                     f"{shlex_quote(str(repo / 'Snakefile'))} ", 1).replace(
        "$(python ", f"$({shlex_quote(sys.executable)} ")
    # the twin's shard files deleted first: the command must not need them
    for shard in (work / "results" / study_name / "twins" / "ext" / "shards").glob("*"):
        shard.unlink()
    twins = work / "results" / study_name / "twins"
    before = {p: p.stat().st_mtime_ns for p in twins.rglob("*") if p.is_file()}
    done = subprocess.run(command, shell=True, cwd=work, capture_output=True, text=True,
                          timeout=1200, env={**os.environ, "PYTHONPATH": str(repo / "src"),
                                             "MPLBACKEND": "Agg"})
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    changed = {p.relative_to(twins).parts[0] for p, t in before.items()
               if p.exists() and p.stat().st_mtime_ns != t}
    assert changed == {"ext"}, changed
    shards = sorted((twins / "ext" / "shards").glob("*.parquet"))
    assert len(shards) == cfg["twin_runs"]["n_shards"]  # rebuilt
    assert (twins / "ext" / "results.parquet").stat().st_mtime_ns != before[
        twins / "ext" / "results.parquet"]
    assert dry_run(repo, work, config, *CONTENT_ONLY) == {}


def test_a_shard_asking_more_than_a_day_says_nothing_of_slurm_on_a_local_run(study):
    """The command twin budgeted at Pulse speed with no useful timeout: its shards' derived
    Slurm time limit exceeds a day, which is worth a warning on Slurm only: a local dry run
    plans the shards without a word about Slurm."""
    repo, work, config, cfg, _ = study
    original = config.read_text()
    slow = {**cfg, "twins": {**cfg["twins"], "ext": {**cfg["twins"]["ext"],
                                                      "timeout_s": 10**6}}}
    config.write_text(yaml.safe_dump(slow))
    try:
        done = _snakemake(repo, work, config, "-n", "--forcerun",
                          *sorted(str(p.relative_to(work)) for p in (
                              work / "results" / cfg["study"] / "twins" / "ext" / "shards"
                          ).glob("*.parquet")), timeout=300)
    finally:
        config.write_text(original)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    assert "asks Slurm" not in out, [ln for ln in out.splitlines() if "Slurm" in ln]


def test_a_truncated_intermediate_file_is_named_with_delete_it(study, tmp_path):
    """A shard file cut short (a full disk, a kill outside Snakemake's watch) looks finished
    to Snakemake: the job reading it fails in one line naming the file and saying to delete
    it; deleted, the same command again rebuilds it and the job that needed it. On a copy of
    the study, with the twin's runs (the job reading the shards) as the command's target:
    what follows the runs (tests, tables, figures) is not what is checked."""
    repo, work, config, cfg, _ = study
    work = copy_study(work, tmp_path / "work")
    shard = work / "results" / cfg["study"] / "twins" / "oracle" / "shards" / "0.parquet"
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])
    runs = f"results/{cfg['study']}/twins/oracle/runs.parquet"
    done = _snakemake(repo, work, config, runs, "--forcerun", runs, timeout=600)
    out = done.stdout + done.stderr
    assert done.returncode != 0
    line = next(ln for ln in out.splitlines()[::-1] if "cannot read twin shard" in ln)
    assert f"results/{cfg['study']}/twins/oracle/shards/0.parquet: cannot read twin shard " \
           "as Parquet, the file is damaged or truncated" in line
    assert line.endswith("delete it and run the same command again: the rule that writes it "
                         "reruns"), line
    shard.unlink()
    done = _snakemake(repo, work, config, runs, "--forcerun", runs, timeout=900)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert shard.is_file()
    assert dry_run(repo, work, config, runs) == {}
