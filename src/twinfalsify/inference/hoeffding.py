"""Exact test of H_lo / H_up from Hoeffding's inequality (the paper's Proposition).

For i.i.d. samples bounded in [y_lo, y_up] (width R), Hoeffding's inequality
gives the one-sided (1 - alpha/2) confidence bounds

    Q_lo >= Qhat_lo - R sqrt(log(2/alpha) / (2n)),
    Q_twin <= Qhat_twin + R sqrt(log(2/alpha) / (2 nhat)).

H_lo: Q_twin >= Q_lo is rejected at level alpha when the second bound lies
below the first (a union bound over both sides gives level alpha). Solving for
the smallest such alpha gives, with d = Qhat_lo - Qhat_twin > 0,

    p_lo = min(1, c exp(-2 d^2 / (R^2 (n^-1/2 + nhat^-1/2)^2))),   c = 2,

and p_lo = 1 when d <= 0 (mirror for H_up with d = Qhat_twin - Qhat_up).
The test refuses to reject (p = 1) when n = 0 or nhat = 0.

Assumptions: observational trajectories i.i.d., twin runs i.i.d. and
independent of them; outcomes clipped to [y_lo, y_up] (so bounded).
Reference: Hoeffding (1963), JASA 58:13-30; Cornish et al. (2026), JMLR,
Proposition on Hoeffding-based p-values. The authors' code uses c = 4
(twice as conservative); ``factor=4`` reproduces it for comparison.
"""

from __future__ import annotations

import numpy as np

from twinfalsify.inference import options
from twinfalsify.inference.samples import HypothesisSamples

FACTOR_MIN = 2.0  # the constant of Hoeffding's two-sided union bound: smaller is invalid


def check_options(opts: dict) -> None:
    """Config options of :func:`hoeffding_test` (``factor``), types and ranges.

    factor < 2 understates p (it is the union bound's constant, not a tuning knob): 0 would
    reject whatever the data; larger values are valid and more conservative.
    """
    options.number(opts, "factor", lo=FACTOR_MIN,
                   note="2 = Hoeffding's bound, the paper's; 4 = the authors' code")


def hoeffding_pvalue(
    d: np.ndarray, width: np.ndarray, n: np.ndarray, nhat: np.ndarray, factor: float = 2.0
) -> np.ndarray:
    """p = min(1, factor * exp(-2 d^2 / (R^2 (n^-1/2 + nhat^-1/2)^2))) for d > 0, else 1."""
    d, width = np.asarray(d, float), np.asarray(width, float)
    n, nhat = np.asarray(n, float), np.asarray(nhat, float)
    ok = (n > 0) & (nhat > 0) & (width > 0) & (d > 0) & np.isfinite(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = 1.0 / np.sqrt(np.where(ok, n, 1.0)) + 1.0 / np.sqrt(np.where(ok, nhat, 1.0))
        z = np.where(ok, d / (np.where(ok, width, 1.0) * s), 0.0)
        p = np.minimum(1.0, factor * np.exp(-2.0 * z**2))
    return np.where(ok, p, 1.0)


def hoeffding_radius(width: np.ndarray, count: np.ndarray, alpha: float) -> np.ndarray:
    """One-sided (1 - alpha/2) Hoeffding radius R sqrt(log(2/alpha) / (2 count))."""
    count = np.asarray(count, float)
    with np.errstate(divide="ignore"):
        return np.asarray(width, float) * np.sqrt(np.log(2.0 / alpha) / (2.0 * count))


def hoeffding_test(
    samples: HypothesisSamples, factor: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Hoeffding p-values (p_lo, p_up) for every hypothesis."""
    q_twin = samples.q_twin_hat
    p_lo = hoeffding_pvalue(
        samples.q_lo_hat - q_twin, samples.width, samples.n, samples.nhat, factor
    )
    p_up = hoeffding_pvalue(
        q_twin - samples.q_up_hat, samples.width, samples.n, samples.nhat, factor
    )
    return p_lo, p_up
