"""The release recipe: the version, CHANGELOG.md and CITATION.cff agree (twinfalsify.release)."""

from __future__ import annotations

import shutil

from helpers.paths import ROOT

import twinfalsify
from twinfalsify.release import release_problems


def test_the_checkout_is_consistent_for_its_version():
    assert release_problems(ROOT) == []


def test_each_disagreement_is_named(tmp_path):
    for name in ("CHANGELOG.md", "CITATION.cff"):
        shutil.copy(ROOT / name, tmp_path / name)
    cff = tmp_path / "CITATION.cff"
    cff.write_text(cff.read_text().replace(f"version: {twinfalsify.__version__}",
                                           "version: 9.9.9"))
    problems = release_problems(tmp_path)
    assert problems == [f"CITATION.cff: version is '9.9.9', the package's is "
                        f"'{twinfalsify.__version__}'"]
    assert any("no section '## [7.0.0]" in p for p in release_problems(tmp_path, "7.0.0"))
    cff.write_text(cff.read_text().replace("version: 9.9.9",
                                           f"version: {twinfalsify.__version__}")
                   .replace("date-released: ", "date-released: 1999-01-01\nx: "))
    assert any("date-released is '1999-01-01'" in p for p in release_problems(tmp_path))
