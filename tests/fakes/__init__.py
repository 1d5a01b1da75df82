"""Test doubles: a fake ``pulse`` package (tests/fakes/pulse, put on sys.path by the tests
that need it) and the fault-injecting protocol twin (faulty_twin.py).

``FAULTY_TWIN`` is the command that starts the fault-injecting twin; its subprocess needs
``src/`` on PYTHONPATH (the tests' ENV).
"""

import sys
from pathlib import Path

FAULTY_TWIN = [sys.executable, str(Path(__file__).resolve().parent / "faulty_twin.py")]
