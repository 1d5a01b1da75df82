"""The documentation site builds in strict mode.

``mkdocs build --strict`` fails on a broken link or anchor, a page missing from the nav or a
nav entry without a page, and (``docs/hooks/config_reference.py``) on a configuration
reference that differs from the schema's (``tests/docs/test_config_reference.py`` checks the page
itself).
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.docs import build_site, require_mkdocs
from helpers.paths import ROOT
from helpers.workflow import built_once


def test_site_builds_in_strict_mode(tmp_path_factory):
    require_mkdocs()
    site = built_once(tmp_path_factory, "docs-site", build_site)
    assert (site / "reference" / "config" / "index.html").is_file()
    html = (site / "reference" / "config" / "index.html").read_text()
    # the committed page is served, its key names in code that does not wrap
    assert '<code style="white-space: nowrap">runs_per_sequence</code>' in html
    assert 'id="betting"' in html and '<code style="white-space: nowrap">n_resamples</code>' in html
    # the formulas' typesetter is served by the site itself (offline); no CDN, no web font
    page = (site / "explanation" / "statistics" / "index.html").read_text()
    assert "assets/vendor/katex/katex.min.js" in page
    assert (site / "assets" / "vendor" / "katex" / "fonts" / "KaTeX_Main-Regular.woff2").is_file()
    assert "fonts.googleapis.com" not in page and "cdn.jsdelivr" not in page


def test_strict_build_fails_on_a_broken_link(tmp_path):
    """The guard itself: a page with a link to a missing page must fail the strict build."""
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        pytest.skip("mkdocs / mkdocs-material not installed (pip install -e '.[dev]')")
    import shutil

    work = tmp_path / "repo"
    shutil.copytree(ROOT / "docs", work / "docs")
    shutil.copy(ROOT / "mkdocs.yml", work / "mkdocs.yml")
    (work / "workflow" / "schemas").mkdir(parents=True)
    shutil.copy(ROOT / "workflow" / "schemas" / "config.schema.yaml", work / "workflow" / "schemas")
    page = work / "docs" / "reference" / "outputs.md"
    page.write_text(page.read_text() + "\nSee [nowhere](no-such-page.md).\n")
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=work, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode != 0
    assert "no-such-page.md" in out.stderr


def test_every_relative_link_of_the_readme_resolves_in_a_clone():
    """A reader of the README on a clone (or on the forge) follows links to files, not to the
    built site: each relative link names a file or folder of the checkout that git tracks."""
    import re

    text = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    local = [u.split("#")[0] for u in links if not re.match(r"[a-z]+:", u) and u.split("#")[0]]
    assert "docs/reference/config.md" in local and "docs/reference/outputs.md" in local
    tracked = set(subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                                 check=True).stdout.split())  # fmt: skip
    dirs = {str(Path(p).parent) for p in tracked}
    for path in local:
        assert path in tracked or path.rstrip("/") in dirs, f"README links to {path}: not in git"
