"""twinfalsify: causal falsification of digital twins against observational data."""

__version__ = "0.1.0"
