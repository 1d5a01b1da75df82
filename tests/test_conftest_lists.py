"""The test lists of conftest name tests and files that exist.

``SLOW_UNIT_TESTS`` marks tests slow by node id and ``LONG_FIRST`` orders files: an entry
left behind after a test was renamed or removed silently marks or orders nothing.
"""

from __future__ import annotations

import ast
from pathlib import Path

from conftest import LONG_FIRST, SLOW_UNIT_TESTS
from helpers.paths import TESTS


def _functions(path: Path) -> set[str]:
    """Names of the functions defined anywhere in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)}


def test_every_listed_slow_test_exists():
    stale = []
    for node in SLOW_UNIT_TESTS:
        file, _, name = node.partition("::")
        path = TESTS / file
        if not path.is_file() or name.split("::")[-1] not in _functions(path):
            stale.append(node)
    assert not stale, f"conftest.SLOW_UNIT_TESTS names tests that do not exist: {stale}"


def test_every_long_first_file_exists():
    stale = [f for f in LONG_FIRST if not (TESTS / f).is_file()]
    assert not stale, f"conftest.LONG_FIRST names files that do not exist: {stale}"
