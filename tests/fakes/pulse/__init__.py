"""A FAKE of the Pulse Physiology Engine's Python package (``pulse``), test fixture only.

It mimics exactly the parts of Pulse 4.2's Python API that
``twinfalsify.pulse.worker`` uses, and serves the values RECORDED from a real
Pulse 4.2 engine (tests/fixtures/pulse-reference/runs.csv), so the worker's
tests run against real numbers. Put ``tests/fakes`` on sys.path to import it.

What it reproduces of the real engine (all observed in the recorded runs):
- ``initialize_engine`` returns False (no exception) for baselines outside Pulse's
  accepted ranges, with the reason only in the log file at [ERROR] level;
- ``pull_data()`` returns ``[sim_time_s, value_1, ..., value_k]`` in request order;
- ``pull_active_events()`` returns {event name: active duration s};
- a fatal error surfaces as the active event ``IrreversibleState`` after which
  ``advance_time_s`` returns False (inject with env FAKE_PULSE_IRREVERSIBLE_AT_HOUR=h);
- an SEUrinate without a comment kills the engine (the real one segfaults);
- a data root without Pulse's data folders kills the process with SIGSEGV inside
  ``initialize_engine`` / ``serialize_from_file`` (what real Pulse 4.2 does after logging
  "Unable to find substance directory"); ``DATA_ROOT`` is a valid stand-in root.
What it cannot do: simulate. A patient or dose history that was not recorded
raises ``LookupError`` naming what is missing.
"""

from pathlib import Path

DATA_ROOT = Path(__file__).resolve().parent / "data_root"
