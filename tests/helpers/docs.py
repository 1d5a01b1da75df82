"""The documentation site, built in strict mode."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers.paths import ROOT


def require_mkdocs() -> None:
    """Skip the calling test when mkdocs or its theme is not installed."""
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        pytest.skip("mkdocs / mkdocs-material not installed (pip install -e '.[dev]')")


def build_site(dest: Path) -> None:
    """``mkdocs build --strict`` of the checkout into ``dest`` (raises with mkdocs' output on
    a warning). Built once per test run (``built_once``): ``tests/docs/test_docs.py`` checks
    the site and ``tests/docs/test_docs_maths.py`` reads the same site in a browser."""
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(dest)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode == 0, out.stderr[-4000:]
