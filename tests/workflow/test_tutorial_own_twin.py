"""The tutorial "Falsify your own twin" runs as written.

Every line of the page's ```bash blocks is executed in order, in a copy of the repository
whose ``.venv`` is the interpreter running the tests (so ``.venv/bin/python`` and
``.venv/bin/snakemake`` work as the page writes them) and with the copy's ``src/`` first on
PYTHONPATH. Each command must exit 0; at the end the study's results and report exist, the
template twin passed every check and the table check printed what the page says.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.paths import ROOT

PAGE = ROOT / "docs" / "tutorials" / "own-twin.md"
# the library's bytecode and numba's caches are copied (with their sources' times, so valid)
SKIP = shutil.ignore_patterns(".git", ".venv", "results", ".snakemake", "site", ".pytest_cache",
                              ".ruff_cache", "*.egg-info")


def commands(markdown: str) -> list[str]:
    """The shell commands of the page's ```bash blocks, in order (one per line)."""
    out = []
    for block in re.findall(r"^```bash\n(.*?)^```", markdown, flags=re.M | re.S):
        out += [ln.strip() for ln in block.splitlines() if ln.strip()
                and not ln.strip().startswith("#")]
    return out


def test_the_page_has_the_steps_a_user_needs():
    cmds = commands(PAGE.read_text())
    assert cmds[0].startswith(".venv/bin/python -m twinfalsify.sources.table check ")
    assert any("twinfalsify.runs.check" in c for c in cmds)
    assert any(c.startswith(".venv/bin/snakemake") and "--report" in c for c in cmds)


@pytest.mark.slow
def test_tutorial_commands_run_as_written(tmp_path):
    work = tmp_path / "repo"
    shutil.copytree(ROOT, work, ignore=SKIP)
    (work / ".venv").symlink_to(Path(sys.prefix), target_is_directory=True)
    env = {**os.environ, "MPLBACKEND": "Agg",
           "PYTHONPATH": os.pathsep.join(p for p in (str(work / "src"),
                                                     os.environ.get("PYTHONPATH")) if p)}
    outputs, times = [], []
    for cmd in commands(PAGE.read_text()):
        t0 = time.monotonic()
        done = subprocess.run(["bash", "-c", cmd], cwd=work, env=env, capture_output=True,
                              text=True, timeout=1200)
        times.append((round(time.monotonic() - t0, 1), cmd[:60]))
        assert done.returncode == 0, f"{cmd}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
        outputs.append(done.stdout)
    print("tutorial command times (s):", times)
    assert "ok, 1000 stays, 5000 rows" in outputs[0]
    check = next(o for c, o in zip(commands(PAGE.read_text()), outputs, strict=True)
                 if "twinfalsify.runs.check" in c)
    assert "all checks passed" in check and "FAIL" not in check and "WARN" not in check
    # every row the page shows is what the check prints (the times are the machine's)
    page = PAGE.read_text()
    shown = re.search(r"^```text\n(hello .*?)^```", page, flags=re.M | re.S).group(1)
    def untimed(line: str) -> str:
        return re.sub(r"\d[\d.e-]* s\b", "_ s", line.rstrip())
    assert [untimed(ln) for ln in shown.splitlines()] == \
        [untimed(ln) for ln in check.splitlines()[1:-1]]
    r = work / "results" / "table-example"
    assert (r / "report.html").stat().st_size > 10_000
    for twin in ("mine", "fitted"):
        assert (r / "twins" / twin / "tables" / "rejections.csv").is_file()
    import pandas as pd

    # step 6: the template is not rejected; the fitted twin once, as the page says
    assert "1,000 stays" in page and "200 of the 1,000 stays" in \
        (work / "config" / "table-example.yaml").read_text()
    mine = pd.read_parquet(r / "twins" / "mine" / "results.parquet")
    assert not mine["rejected"].any()
    fitted = pd.read_parquet(r / "twins" / "fitted" / "results.parquet")
    (hit,) = fitted[fitted["rejected"]].itertuples()
    assert (hit.method, hit.kind, hit.outcome, hit.t) == ("betting", "causal", "paCO2", 1)
    assert f"{hit.p_value:.1e}" == "1.5e-04"
    assert "betting, causal, paCO2 at hour 1,\np = 1.5e-4" in page
    assert not (r / "figures" / "confounding.png").exists()  # the synthetic world only
    # the deliberately wrong twin (heart rate +15 /min per hour): the conformance check names
    # its drift, and the study rejects it, only on heart rate
    wrong = pd.read_parquet(work / "results" / "table-wrong" / "twins" / "mine" /
                            "results.parquet")
    rejected = wrong[wrong["rejected"]]
    assert len(rejected) > 0 and set(rejected["outcome"]) == {"HR"}
    # naming the two files built the wrong twin's outputs only, as the page says
    assert (work / "results" / "table-wrong" / "twins" / "mine" / "figures" /
            "pvalues.png").stat().st_size > 10_000
    assert not (work / "results" / "table-wrong" / "twins" / "fitted").exists()
    check = outputs[[i for i, c in enumerate(commands(PAGE.read_text()))
                     if "--config wrong.yaml" in c][0]]
    drift = [ln for ln in check.splitlines() if ln.startswith("drift")]
    assert drift and "FAIL" in drift[0] and "HR:" in drift[0] and "a check failed" in check
    assert drift[0].split("FAIL", 1)[1].strip().split(" (typical")[0] in " ".join(
        page.split())
