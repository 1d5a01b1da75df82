"""The checkout's folders as the tests see them, and the environment of their subprocesses."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src"
TESTS = ROOT / "tests"
FIXTURES = TESTS / "fixtures"
FAKES = TESTS / "fakes"
BAD_INPUTS = TESTS / "bad_inputs"
# a subprocess (twin, worker, script) imports the package of this checkout
ENV = {"PYTHONPATH": f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def shared_dir() -> Path | None:
    """The shared data folder: ``$TWINFALSIFY_SHARED`` if set, else ``../shared`` next to the
    checkout (the CI layout); None when absent (the tests that need it skip)."""
    env = os.environ.get("TWINFALSIFY_SHARED")
    cand = Path(env) if env else ROOT.parent / "shared"
    return cand if cand.is_dir() else None
