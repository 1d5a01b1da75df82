"""The documentation site builds in strict mode, and its configuration reference is complete.

``mkdocs build --strict`` fails on a broken link or anchor, a page missing from the nav or a
nav entry without a page; the configuration reference is generated from the schema at build
time (``docs/hooks/config_reference.py``), so here it is checked to name every key.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import built_once

ROOT = Path(__file__).resolve().parents[1]


def _hook():
    spec = importlib.util.spec_from_file_location(
        "config_reference", ROOT / "docs" / "hooks" / "config_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _schema_paths(node: dict, path: str = "") -> list[str]:
    """Every key path of the schema, ``<name>`` for a free-named mapping (twins)."""
    out = [path] if path else []
    for key, sub in node.get("properties", {}).items():
        out += _schema_paths(sub, f"{path}.{key}" if path else key)
    extra = node.get("additionalProperties")
    if isinstance(extra, dict) and extra.get("properties"):
        out += _schema_paths(extra, f"{path}.<name>")
    return out


def test_config_reference_names_every_schema_key_with_its_default_and_limits():
    hook = _hook()
    schema = hook.load_schema()
    page = hook.render(schema)
    paths = _schema_paths(schema)
    assert len(paths) > 50
    for p in paths:
        assert f"| `{p}` |" in page, f"config reference lacks {p}"
    row = next(line for line in page.splitlines() if line.startswith("| `design.min_support` |"))
    assert "`10`" in row and ">= 1" in row
    row = next(line for line in page.splitlines() if line.startswith("| `twin_runs.mode` |"))
    assert "`fixed`" in row and "`adaptive`" in row
    # a doc path in a description becomes a link the strict build checks
    assert "[explanation/sequential.md](../explanation/sequential.md)" in page


def require_mkdocs() -> None:
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        pytest.skip("mkdocs / mkdocs-material not installed (pip install -e '.[dev]')")


def build_site(dest: Path) -> None:
    """``mkdocs build --strict`` of the checkout into ``dest`` (raises with mkdocs' output on
    a warning). Built once per test run (``built_once``): ``tests/test_docs_maths.py`` reads
    the same site in a browser."""
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(dest)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode == 0, out.stderr[-4000:]


def test_site_builds_in_strict_mode(tmp_path_factory):
    require_mkdocs()
    site = built_once(tmp_path_factory, "docs-site", build_site)
    assert (site / "reference" / "config" / "index.html").is_file()
    html = (site / "reference" / "config" / "index.html").read_text()
    assert "twin_runs.runs_per_sequence" in html
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
