"""twinfalsify: causal falsification of digital twins against observational data."""

__version__ = "0.2.0"  # the one place: pyproject.toml reads it; CHANGELOG.md says what changed
