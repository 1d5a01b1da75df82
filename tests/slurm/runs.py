"""Run small studies with Snakemake in a scratch directory, and compare their results."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[2]
SNAKEFILE = ROOT / "Snakefile"
SMALL_STUDY = Path(__file__).with_name("study.yaml")


def snakemake_cmd(workdir: Path, config: Path, *args: str) -> list[str]:
    """The snakemake command line for a study in ``workdir`` (the repo's Snakefile)."""
    return [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(SNAKEFILE),
        "--directory",
        str(workdir),
        "--configfile",
        str(config),
        *args,
    ]


def run_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    # scripts import the library from <repo>/src themselves; PYTHONPATH serves the jobstep
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": str(ROOT / "src")}
    return {**env, **(extra or {})}


def new_study(workdir: Path, config: Path = SMALL_STUDY, **changes: dict) -> Path:
    """Copy ``config`` into ``workdir`` (with top-level sections updated) and return its path."""
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load(config.read_text())
    for key, value in changes.items():
        cfg[key] = {**cfg[key], **value} if isinstance(value, dict) else value
    path = workdir / "study.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run(workdir: Path, config: Path, *args: str, env=None, timeout=900):
    return subprocess.run(
        snakemake_cmd(workdir, config, *args),
        capture_output=True,
        text=True,
        env=run_env(env),
        timeout=timeout,
    )


def results_dir(workdir: Path, config: Path) -> Path:
    return workdir / "results" / yaml.safe_load(config.read_text())["study"]


def results_files(workdir: Path, config: Path) -> dict[str, Path]:
    """Every twin's results.parquet of a finished study, by twin name."""
    r = results_dir(workdir, config)
    twins = yaml.safe_load(config.read_text())["twins"]
    return {t: r / "twins" / t / "results.parquet" for t in twins}


def assert_same_results(a: dict[str, Path], b: dict[str, Path]) -> None:
    """Equal tables (exactly: same rows, order, dtypes, values) and equal Parquet bytes."""
    assert a.keys() == b.keys()
    for twin in a:
        fa, fb = pd.read_parquet(a[twin]), pd.read_parquet(b[twin])
        pd.testing.assert_frame_equal(fa, fb, check_exact=True)
        assert len(fa) > 0
        # pyarrow writes no timestamp or host into the file, so equal tables give equal bytes
        assert a[twin].read_bytes() == b[twin].read_bytes(), f"{twin}: same table, other bytes"


def build_reference_run(work: Path, cores: int) -> None:
    """One uninterrupted run of the small study in ``work`` (the determinism, resume and
    Slurm tests compare against it; ``conftest.reference_runs`` builds it once per run)."""
    config = new_study(work)
    # only what is compared (results.parquet): tables and figures would add minutes to CI
    targets = [str(p.relative_to(work)) for p in results_files(work, config).values()]
    done = run(work, config, "--cores", str(cores), *targets)
    if done.returncode != 0:
        raise AssertionError(f"reference run failed:\n{done.stderr[-3000:]}")
