"""Shared fixtures: small synthetic studies built in-process (fast, seeded)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")


def shared_dir() -> Path | None:
    """../shared next to the checkout (CI layout), else /work/shared; None when absent."""
    for cand in (ROOT.parent / "shared", Path("/work/shared")):
        if cand.is_dir():
            return cand
    return None


@pytest.fixture(scope="session")
def root() -> Path:
    return ROOT
