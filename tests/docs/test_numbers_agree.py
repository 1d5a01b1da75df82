"""A number the documentation states in two places is the same in both, and the same as its source.

- The default study's parameter sets and hypotheses (causal, Manski, both kinds, and the
  Holm and tuning levels derived from them) wherever README.md and docs/ state them, against
  the sentence ``make readme-table`` writes above the README's rejection table.
- The job counts stated for the default study, the paper-scale study and the tiny study of
  ``config/test.yaml``, against the "Job stats" total of ``snakemake -n`` in an empty folder
  (a dry run: seconds each).
- The version, wherever a page names a release, against ``src/twinfalsify/__init__.py``, the
  one place it is written (``pyproject.toml`` reads it).
- Every statement of how many tests the suite passed, against each other.

Each statement is found by a pattern; a statement reworded so that its pattern no longer
matches fails the test too, naming the file and pattern to update.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.paths import ENV, ROOT

PAGES = [ROOT / "README.md", ROOT / "config" / "README.md",
         *sorted((ROOT / "docs").rglob("*.md"))]  # fmt: skip
NUM = r"(\d{1,3}(?:(?:,|\{,\})\d{3})*|\d+)"  # 2,042, 2{,}042 (LaTeX) or 2042


def num(s: str) -> int:
    return int(s.replace("{,}", "").replace(",", ""))


def text(rel: str) -> str:
    return (ROOT / rel).read_text()


def readme_sentence() -> tuple[int, int]:
    """(causal, Manski) parameter sets of the default study, from the generated sentence."""
    m = re.search(r"<!-- readme-table: generated.*?\n.*?(\d+) causal parameter sets and "
                  r"(\d+) Manski parameter sets", text("README.md"), re.S)
    assert m, "README.md: the generated sentence above the rejection table is missing"
    return int(m.group(1)), int(m.group(2))


def default_counts() -> dict[str, int]:
    c, m = readme_sentence()
    return {"C": c, "M": m, "2C": 2 * c, "2M": 2 * m, "C+M": c + m, "2(C+M)": 2 * (c + m)}


# (file, pattern, the quantity each group states); every match of the pattern must agree
STATEMENTS: list[tuple[str, str, tuple[str, ...]]] = [
    ("README.md", rf"Of the fitted twin's {NUM} causal hypotheses", ("2C",)),
    ("docs/explanation/statistics.md",
     rf"its {NUM} causal hypotheses \({NUM} parameter sets, two sides", ("2C", "C")),
    ("docs/explanation/statistics.md", rf"threshold \$0\.05/{NUM} = ", ("2C",)),
    ("docs/explanation/statistics.md", rf"\$H = {NUM}\$ causal", ("C",)),
    ("docs/explanation/statistics.md", rf"\\alpha_0 = 0\.05/{NUM} = ", ("2C",)),
    ("docs/explanation/statistics.md", rf"yes: 0 of {NUM} under 3 renumberings", ("2(C+M)",)),
    ("docs/explanation/statistics.md", rf"\(biased\) of {NUM} decisions", ("2(C+M)",)),
    ("docs/reference/benchmarks.md",
     rf"\({NUM} parameter sets,\s+{NUM} hypotheses: {NUM} causal, {NUM} Manski\)",
     ("C+M", "2(C+M)", "2C", "2M")),
    ("docs/reference/benchmarks.md",
     rf"\| hypotheses \(causal \+ Manski\) \| {NUM} \({NUM} \+ {NUM}\)", ("2(C+M)", "2C", "2M")),
    ("docs/reference/benchmarks.md", rf"rejected or not, {NUM}\s+per twin", ("2(C+M)",)),
    ("docs/reference/benchmarks.md", rf"\| \d+, \d+ of {NUM}", ("2(C+M)",)),
    ("docs/reference/benchmarks.md", rf"0\.05 / {NUM} = 4\.5e-05, in its causal\s+family of {NUM}",
     ("2C", "2C")),
    ("docs/reference/benchmarks.md", rf"pooling both kinds\), {NUM} one-sided hypotheses",
     ("2(C+M)",)),
    ("docs/reference/benchmarks.md", rf"{NUM}\s+Manski\s+hypotheses, none rejected", ("2M",)),
    ("docs/reference/benchmarks.md",
     rf"`config/config.yaml`: {NUM} parameter sets = {NUM} one-sided hypotheses",
     ("C+M", "2(C+M)")),
]


@pytest.mark.parametrize("rel, pattern, what", STATEMENTS,
                         ids=[f"{s[0]}:{s[2]}" for s in STATEMENTS])
def test_the_default_studys_hypotheses_are_the_readme_tables(rel, pattern, what):
    want = default_counts()
    found = list(re.finditer(pattern, text(rel)))
    assert found, f"{rel}: no statement matches {pattern!r} (reworded? update this test)"
    for m in found:
        got = tuple(num(g) for g in m.groups())
        assert got == tuple(want[w] for w in what), (
            f"{rel}: {m.group(0)!r} states {dict(zip(what, got, strict=True))}; the "
            f"README's generated table says {dict((w, want[w]) for w in what)}")


def test_derived_levels_follow_the_counts():
    """The smallest Holm threshold alpha/(2C) and the causal family's tuning level alpha/(2C)
    as printed."""
    n = default_counts()
    stats = text("docs/explanation/statistics.md")
    holm = re.search(rf"0\.05/{NUM} = ([\d.]+) \\times 10\^\{{-5\}}", stats)
    tune = re.search(rf"\\alpha_0 = 0\.05/{NUM} = ([\d.]+) \\times 10\^\{{-5\}}", stats)
    assert holm and tune
    assert float(holm.group(2)) == pytest.approx(0.05 / n["2C"] * 1e5, abs=0.05)
    assert float(tune.group(2)) == pytest.approx(0.05 / n["2C"] * 1e5, abs=0.05)


def dry_run_total(tmp_path: Path, config: str) -> int:
    """The "Job stats" total of ``snakemake -n`` for a study in an empty folder."""
    work = tmp_path / Path(config).stem
    work.mkdir()
    done = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "--directory",
         str(work), "--configfile", str(ROOT / config), "-n", "--cores", "2"],
        capture_output=True, text=True, timeout=300, env={**os.environ, **ENV})
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    m = re.search(r"^total\s+(\d+)\s*$", out, re.M)
    assert m, out[-3000:]
    return int(m.group(1))


# (file, pattern stating a job count, the study's config)
JOB_COUNTS = [
    ("docs/reference/benchmarks.md", r"the study itself \((\d+) jobs", "config/config.yaml"),
    ("docs/reference/benchmarks.md",
     r"The workflow of this version\s+runs (\d+) \(`snakemake -n --configfile "
     r"config/paper-scale.yaml`\)", "config/paper-scale.yaml"),
    ("docs/how-to/run-workflow.md", r"\(2 twins, 2 shards each, (\d+) jobs in all",
     "config/test.yaml"),
]


def test_stated_job_counts_are_the_dry_runs(tmp_path):
    totals: dict[str, int] = {}
    for rel, pattern, config in JOB_COUNTS:
        found = re.findall(pattern, text(rel))
        assert found, f"{rel}: no statement matches {pattern!r} (reworded? update this test)"
        if config not in totals:
            totals[config] = dry_run_total(tmp_path, config)
        for n in found:
            assert int(n) == totals[config], (
                f"{rel} states {n} jobs for {config}; `snakemake -n` lists {totals[config]}")


def test_the_measured_paper_scale_runs_job_counts_agree():
    """The paper-scale measurement's job count: the benchmarked jobs and `all`."""
    bench = text("docs/reference/benchmarks.md")
    m = re.search(r"The measured run had (\d+) jobs: the (\d+) that write a benchmark", bench)
    per_rule = re.search(r"every other rule under 6 CPU s; (\d+) jobs, ", bench)
    assert m and per_rule
    assert int(m.group(1)) == int(m.group(2)) + 1 == int(per_rule.group(1)) + 1


def version() -> str:
    m = re.search(r'^__version__ = "([^"]+)"', text("src/twinfalsify/__init__.py"), re.M)
    assert m, "src/twinfalsify/__init__.py: no __version__ literal"
    return m.group(1)


def test_the_version_is_written_once_and_named_the_same_everywhere():
    v = version()
    pyproject = text("pyproject.toml")
    assert re.search(r'^dynamic = \["version"\]', pyproject, re.M)
    assert 'version = {attr = "twinfalsify.__version__"}' in pyproject
    for rel in ("docs/index.md", "docs/how-to/deploy.md"):
        assert "src/twinfalsify/__init__.py" in text(rel), f"{rel}: where the version lives"
    named = 0
    for page in PAGES:
        body = page.read_text()
        for pattern in (r'tag="v(\d+\.\d+\.\d+)"', r"@v(\d+\.\d+\.\d+)\b",
                        r"this workflow is twinfalsify (\d+\.\d+\.\d+)"):
            for hit in re.findall(pattern, body):
                named += 1
                assert hit == v, f"{page.relative_to(ROOT)} names release {hit}; the version is {v}"
    assert named, "no page names the release to deploy (docs/how-to/deploy.md)"


def test_statements_of_the_suites_test_count_agree():
    """The whole suite's passed tests, wherever a page states them (CHANGELOG.md records
    earlier suites and is not searched)."""
    bench = text("docs/reference/benchmarks.md")
    whole = re.search(r"\| `(?:make lint && )?make test` \| ([\d,]+) / (\d+) \|", bench)
    unit = re.search(r"\| `make test-fast` \(`-m \"not slow\"`\) \| ([\d,]+) / (\d+) \|", bench)
    assert whole and unit, "docs/reference/benchmarks.md: the suite's table rows"
    passed = num(whole.group(1))
    assert num(unit.group(1)) < passed
    for page in PAGES:
        body = page.read_text()
        for hit in re.finditer(rf"{NUM} tests? passed|\| {NUM} / \d+ \| \*\*", body):
            n = num(hit.group(1) or hit.group(2))
            assert n in (passed, num(unit.group(1))), (
                f"{page.relative_to(ROOT)}: {hit.group(0)!r}; the suite passed {passed}")
        for hit in re.finditer(r"about ([\d,]+) tests", body):
            assert num(hit.group(1)) <= passed, f"{page.relative_to(ROOT)}: {hit.group(0)!r}"
