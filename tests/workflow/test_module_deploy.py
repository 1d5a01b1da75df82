"""The workflow deployed as a Snakemake module, the way a user outside the project runs it.

A release is a git tag; a user's study folder holds a Snakefile with a ``module`` block that
loads ``workflow/Snakefile`` at that tag (from a git URL with ``github(...)``/``gitlab(...)``,
from a local clone with ``gitfile(...)``, or from a plain path), the project's rerun
triggers, and their config. The test builds exactly that from a local bare repository (a
clone of this checkout's files, tagged ``v<version>``) and runs the tiny study of
``config/test.yaml`` through it (the outputs it compares; the whole study is planned through
a deployed module below): the results must be those of the checkout, byte for byte.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.paths import ROOT

import twinfalsify

pytestmark = pytest.mark.slow

TAG = f"v{twinfalsify.__version__}"


def _git(*args: str, cwd: Path) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@example.org",
           "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@example.org"}
    run = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    return run.stdout


def _release(tmp: Path) -> Path:
    """A local clone of a bare repository holding this checkout's files at tag TAG."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                            capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("the checkout is not a git repository (git ls-files failed)")
    src = tmp / "src-repo"
    for rel in filter(None, listed.stdout.split("\0")):
        path = ROOT / rel
        if path.is_file():  # listed but deleted in the working tree: not part of the release
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, src / rel)
    _git("init", "-q", "-b", "main", cwd=src)
    _git("add", "-A", cwd=src)
    _git("commit", "-q", "-m", "release", cwd=src)
    _git("tag", TAG, cwd=src)
    bare = tmp / "twinfalsify.git"
    _git("clone", "-q", "--bare", str(src), str(bare), cwd=tmp)
    clone = tmp / "twinfalsify"
    _git("clone", "-q", str(bare), str(clone), cwd=tmp)
    return clone


def _study_folder(folder: Path, snakefile_source: str) -> Path:
    """A user's study folder: the module block, the rerun triggers, the tiny study's config."""
    (folder / "config").mkdir(parents=True)
    shutil.copy(ROOT / "config" / "test.yaml", folder / "config" / "config.yaml")
    (folder / "profiles" / "default").mkdir(parents=True)
    shutil.copy(ROOT / "profiles" / "default" / "config.yaml",
                folder / "profiles" / "default" / "config.yaml")
    (folder / "Snakefile").write_text(
        'configfile: "config/config.yaml"\n\n\n'
        "module twinfalsify:\n"
        f"    snakefile:\n        {snakefile_source}\n"
        "    config:\n        config\n\n\n"
        "use rule * from twinfalsify\n"
    )
    return folder


def _snakemake(folder: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", *args]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(cmd, cwd=folder, capture_output=True, text=True, env=env,
                          timeout=900)


# what the deployed study is compared on, per twin, and what it must have built besides
COMPARED = ("results.parquet", "tables/rejections.csv", "tables/sensitivity.csv")
BUILT = ("summary.md", "design/hypotheses.parquet", "figures/confounding.png")


def test_deployed_from_a_git_tag_the_study_equals_the_checkouts(tmp_path, test_study):
    clone = _release(tmp_path)
    folder = _study_folder(tmp_path / "my-study",
                           f'gitfile("{clone}", path="workflow/Snakefile", tag="{TAG}")')
    work, _ = test_study
    theirs = work / "results" / "test"
    twins = sorted(p.name for p in (theirs / "twins").iterdir())
    assert twins
    # only what is compared or checked (through the module's rules: the results, the
    # tables, the sensitivity sweep, the summary, the confounding figure); the other figures
    # add a minute and are the checkout's rules too (tests/workflow/test_figures_workflow.py)
    targets = [f"results/test/twins/{twin}/{rel}" for twin in twins for rel in COMPARED]
    targets += [f"results/test/{rel}" for rel in BUILT]
    run = _snakemake(folder, *targets)
    assert run.returncode == 0, run.stderr[-4000:]
    mine = folder / "results" / "test"
    for twin in twins:
        for rel in COMPARED:
            a, b = mine / "twins" / twin / rel, theirs / "twins" / twin / rel
            assert a.read_bytes() == b.read_bytes(), f"{twin}/{rel} differs from the checkout's"
    for rel in ("design/hypotheses.parquet", "observational/counts.parquet"):
        assert (mine / rel).read_bytes() == (theirs / rel).read_bytes(), rel
    for rel in BUILT:
        assert (mine / rel).is_file(), rel
    assert "## Software" in (mine / "summary.md").read_text()
    # a second start has nothing to do: the module's rules track their code by content
    again = _snakemake(folder, "-n", *targets)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "Nothing to be done" in again.stdout + again.stderr


def test_deployed_from_a_local_path_parses_and_plans_the_whole_study(tmp_path):
    folder = _study_folder(tmp_path / "my-study",
                           f'"{ROOT / "workflow" / "Snakefile"}"')
    run = _snakemake(folder, "-n")
    assert run.returncode == 0, run.stderr[-4000:]
    out = run.stdout + run.stderr
    for rule in ("trajectories", "twin_shard", "tests", "figure_sensitivity", "summary"):
        assert rule in out, rule


def test_a_deployed_workflow_refuses_a_library_of_another_version(tmp_path):
    clone = _release(tmp_path)
    init = clone / "src" / "twinfalsify" / "__init__.py"
    text = init.read_text()
    init.write_text(text.replace(f'__version__ = "{twinfalsify.__version__}"',
                                 '__version__ = "0.0.1"'))
    _git("commit", "-q", "-am", "another version", cwd=clone)
    _git("tag", "v0.0.1", cwd=clone)
    folder = _study_folder(tmp_path / "my-study",
                           f'gitfile("{clone}", path="workflow/Snakefile", tag="v0.0.1")')
    run = _snakemake(folder, "-n")
    assert run.returncode != 0
    assert (f"this workflow is twinfalsify 0.0.1 but the installed library is "
            f"{twinfalsify.__version__}") in run.stdout + run.stderr
