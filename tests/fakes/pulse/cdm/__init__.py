"""Fake pulse.cdm (see tests/fakes/pulse/__init__.py)."""
