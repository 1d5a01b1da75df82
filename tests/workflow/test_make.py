"""The Makefile's targets do what the README and the docs say (``make -n``: printed, not run)."""

from __future__ import annotations

import shutil
import subprocess

import pytest
from helpers.paths import ROOT

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")


def dry_run(*args: str) -> list[str]:
    out = subprocess.run(["make", "-n", *args], cwd=ROOT, capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    return out.stdout.splitlines()


@pytest.mark.parametrize("config, study", [(None, "synthetic"), ("config/test.yaml", "test")])
def test_report_builds_the_study_then_writes_its_report(config, study):
    lines = dry_run("report", *([f"CONFIG={config}"] if config else []))
    cfg = config or "config/config.yaml"
    build = [i for i, ln in enumerate(lines)
             if ln.endswith(f"snakemake --cores 2 --configfile {cfg}")]
    report = [i for i, ln in enumerate(lines)
              if ln.endswith(f"--configfile {cfg} --report results/{study}/report.html")]
    assert build and report and build[0] < report[0], lines


def test_docs_builds_the_site_strictly():
    assert any(ln.endswith("mkdocs build --strict") for ln in dry_run("docs"))
