"""Tests of the hypotheses H_lo: Q_twin >= Q_lo and H_up: Q_twin <= Q_up.

Every method takes a :class:`HypothesisSamples` (vectorised over hypotheses)
and returns one-sided p-values ``(p_lo, p_up)``, arrays of shape (H,).
"""

from twinfalsify.inference.samples import HypothesisSamples, Ragged

__all__ = ["HypothesisSamples", "Ragged"]
