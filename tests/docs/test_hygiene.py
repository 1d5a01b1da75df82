"""The product speaks to its users: no narration of how it was developed, no machine paths.

Every text file a user reads or runs (README, docs, library, configs, tests and their
fixtures, benchmarks, environments, scripts, workflow) is searched for numbered periods of
work ("session 3"), issue numbers ("issue 12", "#12"), "the brief", "built here" /
"measured here" (say what, how, with which command and on which machine kind instead), and
absolute paths of one machine (``/work/...``, ``/root/...``, ``/home/...``). A hit fails the
test naming ``file:line`` and the line.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.paths import ROOT

SCOPE = ("README.md", "CHANGELOG.md", "CITATION.cff", "LICENSE", "docs", "src", "config",
         "tests", "benchmarks", "envs", "scripts", "workflow", "profiles", "Snakefile",
         "Makefile",
         "mkdocs.yml", ".ci")  # fmt: skip
SELF = Path(__file__).resolve()
# third-party files served with the docs site (KaTeX from npm): not the project's words
VENDORED = ("docs/assets/vendor/",)

# Each pattern is case-insensitive; the name says what it catches.
PATTERNS: dict[str, str] = {
    "a period of work": r"\b(this|last|next|earlier|previous|that|same) session\b"
    r"|\bsessions? [0-9]+\b",
    "an issue number": r"\bissues?[ -]?#?[0-9]+\b|(?<![\w&/#])#[0-9]+\b(?![0-9a-f]*;)",
    "the brief": r"\bthe brief\b",
    "an issue as a source": r"\bthe issue'?s?\b",
    "a place, not a machine kind": r"\b(built|measured|run|ran) here\b",
    "a team role": r"\bthe lead'?s?\b(?! time)",
    "an absolute machine path": r"(?<![\w.~$}>-])/(work|farm|root|home|Users)/",
}
REGEX = re.compile("|".join(f"(?P<p{i}>{p})" for i, p in enumerate(PATTERNS.values())),
                   re.IGNORECASE)  # fmt: skip
NAMES = list(PATTERNS)
BINARY_SUFFIXES = {".png", ".pdf", ".parquet", ".gz", ".pbb", ".jar", ".xlsx", ".pyc", ".woff2"}


def files_in_scope() -> list[Path]:
    """Tracked files of the scope (git), else every file under it (a source tarball)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--", *SCOPE], cwd=ROOT,
                             capture_output=True, check=True).stdout  # fmt: skip
        paths = [ROOT / p for p in out.decode().split("\0") if p]
    except (OSError, subprocess.CalledProcessError):
        paths = []
        for s in SCOPE:
            p = ROOT / s
            paths += [p] if p.is_file() else [q for q in p.rglob("*") if q.is_file()]
    return [p for p in paths if p.is_file() and p.suffix not in BINARY_SUFFIXES
            and p.resolve() != SELF
            and not p.relative_to(ROOT).as_posix().startswith(VENDORED)]  # fmt: skip


# The user's documentation states what is; how it came to be goes to CHANGELOG.md. Searched in
# README.md and docs/ only: in code, "a worker that no longer runs" is no history.
HISTORY: dict[str, str] = {
    "narrated change": r"\bno longer\b|\bpredat(?:e|es|ed|ing)\b|\bnot adopted\b"
    r"|\bearlier (?:run|runs|version|versions|extraction|default|measurements?|revision|code)\b"
    r"|\bformer (?:revision|code|definition|default|version)\b|\b(?:now|then) the default\b"
    r"|\bnow (?:draws|uses|gives|reads|keeps|counts|stages|runs|has|is the)\b|\b(?:is|are) now\b"
    r"|\bbefore the (?:data order|revision|rewrite|change|fix)\b"
    r"|\bwas (?:withdrawn|replaced)\b|\bused to (?:run|be|give|draw|read)\b"
    r"|\bthe old (?:code|default|version|rule)\b|\bbefore: ",
}
HISTORY_REGEX = re.compile("|".join(f"(?P<p{i}>{p})" for i, p in enumerate(HISTORY.values())),
                           re.IGNORECASE)  # fmt: skip
HISTORY_SCOPE = ("README.md", "docs")
HISTORY_EXEMPT = ("CHANGELOG.md",)

# what continues a sentence on the next line: indentation and comment or quote markers
_CONTINUATION = re.compile(r"^\s*(?:#+|//|\*|>|\"\"\"|\'\'\')?\s*")


def hits(text: str, regex: re.Pattern = REGEX, names: list[str] = NAMES
         ) -> list[tuple[int, str, str]]:
    """(line number, what was found, the line) for every matching line of ``text``, and for
    a line whose words run on into the next ("issue" at the end of one line, "15" at the
    start of the next)."""
    found = []
    lines = text.splitlines()
    for no, line in enumerate(lines, 1):
        m = regex.search(line)
        if not m and no < len(lines):
            joined = line.rstrip() + " " + _CONTINUATION.sub("", lines[no], count=1)
            m = next((j for j in regex.finditer(joined) if j.end() > len(line.rstrip())),
                     None)
        if m:
            found.append((no, names[int(m.lastgroup[1:])], line.strip()[:140]))
    return found


def history_hits(text: str) -> list[tuple[int, str, str]]:
    """Passages of ``text`` that narrate change ("an earlier run", "no longer")."""
    return hits(text, HISTORY_REGEX, list(HISTORY))


def test_no_process_words_or_machine_paths():
    bad = []
    for path in files_in_scope():
        raw = path.read_bytes()
        if b"\0" in raw[:4096]:
            continue
        for no, what, line in hits(raw.decode("utf-8", errors="replace")):
            bad.append(f"{path.relative_to(ROOT)}:{no}: {what}: {line}")
    assert not bad, "development-process words or machine paths:\n" + "\n".join(bad)


def test_user_docs_state_what_is():
    bad = []
    for path in files_in_scope():
        rel = path.relative_to(ROOT).as_posix()
        if not rel.startswith(HISTORY_SCOPE) or rel in HISTORY_EXEMPT or path.suffix != ".md":
            continue
        for no, what, line in history_hits(path.read_text(errors="replace")):
            bad.append(f"{rel}:{no}: {what}: {line}")
    assert not bad, ("history in the docs (state what is; history goes to CHANGELOG.md):\n"
                     + "\n".join(bad))  # fmt: skip


@pytest.mark.parametrize(
    "line",
    [
        "(The measurements below predate the data order: they used one seeded order.)",
        "was measured in the adaptive mode and not adopted: the decisions barely moved",
        "Earlier measurements (before the data order; the study's data have changed since",
        "An earlier run of the same study took 65 min",
        "the fixed default is now the data-order plug-in: 44 and 290",
        "(`bets: mixture`, then the default; R = 200)",
        "The world now draws X_0 inside the contract's ranges",
        "MRSA screens no\nlonger count as cultures",
        "Against the former revision (62 and 60)",
        "A culture without HADM_ID (before: dropped) is given",
    ],
)
def test_the_history_patterns_catch_narrated_change(line):
    assert history_hits(line), line


@pytest.mark.parametrize(
    "line",
    [
        "the values of hour t use only data charted at or before the end of hour t",
        "a stay weaned from vasopressors would be excluded without the last condition",
        "weight charted in an earlier stay of the patient",
        "the state after the last completed hour stays saved",
    ],
)
def test_the_history_patterns_leave_ordinary_words(line):
    assert not history_hits(line), line


def test_an_injected_history_phrase_fails_the_docs_check(tmp_path, monkeypatch):
    """The guard itself: a docs page with one narrated change is reported, naming it."""
    page = tmp_path / "docs" / "explanation" / "x.md"
    page.parent.mkdir(parents=True)
    page.write_text("# X\n\nThe bets are capped at c.\nThis predates the data order.\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "files_in_scope", lambda: [page])
    with pytest.raises(AssertionError, match=r"docs/explanation/x.md:4: narrated change"):
        test_user_docs_state_what_is()


@pytest.mark.parametrize(
    "line",
    [
        "measured in session 1; after this session's changes",
        "Until session 6 the bets were capped",
        "(issue 11: 0.090 / 0.186)",
        "see #12 for the discussion",
        "the issue-11 target",
        "Default R = 100 (not the issue's target 200)",
        "reading in the issue; any floor",
        "The brief's third example patient",
        "a real Pulse engine built here from its public source",
        "Cost measured here: 155 CPU-s",
        "`hoeffding.py`, the lead's",
        "fall back to /work/shared",
        "export PYTHONPATH=/root/pulse/install/bin",
        'Path("/home/user/data")',
        "one line naming the file, no traceback (issue\n15). Cases: a truncated file",
        "# fixed in the last\n# session, by hand",
    ],
)
def test_the_patterns_catch_process_words(line):
    assert hits(line), line


@pytest.mark.parametrize(
    "line",
    [
        "a lost login session or a node failure",
        "## Example session",
        '@pytest.fixture(scope="session")',
        "color: #1f77b4",
        "PREFIX/install/bin and ../shared/data/mimic-iii-demo",
        "results/synthetic/work/x and $HOME/work/",
        "src/twinfalsify/work/ is fine",
        "the lead time of a treatment",
    ],
)
def test_the_patterns_leave_ordinary_words(line):
    assert not hits(line), line
