"""The release recipe: one version, stated alike in the changelog and the citation, and a tag.

The version is written once, in ``twinfalsify.__version__`` (``pyproject.toml`` reads it). A
release ``V`` needs ``CHANGELOG.md`` to have a section ``## [V] - YYYY-MM-DD`` and
``CITATION.cff`` to state ``version: V`` and ``date-released: YYYY-MM-DD`` (the same date);
the deployed workflow is then loaded at the git tag ``vV`` (docs/how-to/deploy.md).

    python -m twinfalsify.release            # what is inconsistent, if anything
    python -m twinfalsify.release --tag      # the same checks, a clean tree, then git tag vV
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import twinfalsify

ROOT = Path(__file__).resolve().parents[2]


def changelog_date(text: str, version: str) -> str | None:
    """The date of the changelog's section for ``version``, or None without one."""
    m = re.search(rf"^## \[{re.escape(version)}\] - (\d{{4}}-\d{{2}}-\d{{2}})\s*$", text, re.M)
    return m.group(1) if m else None


def citation_field(text: str, key: str) -> str | None:
    """A top-level scalar of CITATION.cff (quotes removed), or None."""
    m = re.search(rf"^{key}:\s*['\"]?([^'\"\n]+?)['\"]?\s*$", text, re.M)
    return m.group(1) if m else None


def release_problems(root: Path = ROOT, version: str = twinfalsify.__version__) -> list[str]:
    """One line per inconsistency between the version, CHANGELOG.md and CITATION.cff."""
    problems = []
    changelog = (root / "CHANGELOG.md").read_text()
    citation = (root / "CITATION.cff").read_text()
    date = changelog_date(changelog, version)
    if date is None:
        problems.append(f"CHANGELOG.md: no section '## [{version}] - YYYY-MM-DD'")
    cited = citation_field(citation, "version")
    if cited != version:
        problems.append(f"CITATION.cff: version is {cited!r}, the package's is {version!r}")
    released = citation_field(citation, "date-released")
    if date is not None and released != date:
        problems.append(f"CITATION.cff: date-released is {released!r}, CHANGELOG.md's "
                        f"[{version}] is dated {date}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twinfalsify.release")
    parser.add_argument("--tag", action="store_true", help="tag the release v<version>")
    args = parser.parse_args(argv)
    version = twinfalsify.__version__
    problems = release_problems(ROOT, version)
    if args.tag:
        status = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT,
                                capture_output=True, text=True)
        if status.returncode != 0 or status.stdout.strip():
            problems.append("git: the working tree has uncommitted changes (or is no checkout)")
    for line in problems:
        print(f"release {version}: {line}", file=sys.stderr)
    if problems:
        return 1
    if args.tag:
        subprocess.run(["git", "tag", "-a", f"v{version}", "-m", f"twinfalsify {version}"],
                       cwd=ROOT, check=True)
        print(f"tagged v{version}: push it with the commit (git push --follow-tags)")
    else:
        print(f"release {version}: CHANGELOG.md and CITATION.cff agree")
    return 0


if __name__ == "__main__":
    sys.exit(main())
