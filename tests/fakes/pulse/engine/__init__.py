"""Fake pulse.engine (see tests/fakes/pulse/__init__.py)."""
