"""Exact test of H_lo / H_up from the empirical Bernstein bound (Maurer & Pontil 2009).

For n >= 2 i.i.d. values in [y_lo, y_up] (width R) with mean mu, sample mean Xbar
and unbiased sample variance V (Maurer & Pontil 2009, Theorem 4, applied to the
values and to their reflection), each of the following holds with probability >= 1 - delta:

    mu >= Xbar - R sqrt(2 (V/R^2) log(2/delta) / n) - 7 R log(2/delta) / (3 (n - 1)),
    mu <= Xbar + R sqrt(2 (V/R^2) log(2/delta) / n) + 7 R log(2/delta) / (3 (n - 1)).

Union rule at level alpha (delta = alpha/2 per side, so log(2/delta) = log(4/alpha) =: s^2):
H_lo is rejected iff d = Qhat_lo - Qhat_twin > A s + B s^2 with
A = sqrt(2 V_lo / n) + sqrt(2 V_twin / nhat), B = 7 R / (3 (n - 1)) + 7 R / (3 (nhat - 1)).
The smallest such alpha is closed-form: s* = (-A + sqrt(A^2 + 4 B d)) / (2 B),
p_lo = min(1, 4 exp(-s*^2)) for d > 0, else 1 (mirror for H_up). p = 1 when n < 2
or nhat < 2 (the bound needs a variance estimate).

Assumptions: i.i.d. and bounded samples, sides independent. Tighter than Hoeffding
only when the variance is well below R^2/4 and n is large (the 7/3 log term costs
more than Hoeffding saves otherwise); docs/explanation/statistics.md has the comparison.
Reference: A. Maurer & M. Pontil (2009), "Empirical Bernstein bounds and
sample-variance penalization", COLT 2009, Theorem 4.
"""

from __future__ import annotations

import numpy as np

from twinfalsify.inference.samples import HypothesisSamples, Ragged


def _group_sq_dev(values: Ragged, center: np.ndarray) -> np.ndarray:
    """Per-group sum of (value - center[group])^2."""
    gid = values.group_ids()
    c = np.where(np.isfinite(center), center, 0.0)
    return np.bincount(gid, weights=(values.values - c[gid]) ** 2, minlength=len(values))


def _means_and_variances(samples: HypothesisSamples):
    """(means, unbiased variances) of Y_lo, Y_up, Y_twin; clips each side once."""
    n, nf, nhat = samples.n.astype(float), samples.n_follow, samples.nhat.astype(float)
    follow, twin = samples.follow_f, samples.twin_f
    fs, ts = follow.sums(), twin.sums()
    with np.errstate(invalid="ignore", divide="ignore"):
        means = ((fs + (n - nf) * samples.y_lo) / n, (fs + (n - nf) * samples.y_up) / n, ts / nhat)
        variances = []
        for fill, mean in ((samples.y_lo, means[0]), (samples.y_up, means[1])):
            ss = _group_sq_dev(follow, mean) + (n - nf) * (fill - np.nan_to_num(mean)) ** 2
            variances.append(np.where(n >= 2, ss / (n - 1), np.nan))
        variances.append(np.where(nhat >= 2, _group_sq_dev(twin, means[2]) / (nhat - 1), np.nan))
    return means, tuple(variances)


def sample_variances(samples: HypothesisSamples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unbiased sample variances of Y_lo, Y_up and Y_twin (NaN when fewer than 2 values)."""
    return _means_and_variances(samples)[1]


def bernstein_radius(
    var: np.ndarray, count: np.ndarray, width: np.ndarray, alpha: float
) -> np.ndarray:
    """One-sided (1 - alpha/2) empirical-Bernstein radius sqrt(2 V l / n) + 7 R l / (3 (n-1)).

    l = log(2/delta) with delta = alpha/2. NaN/inf where count < 2.
    """
    ell = np.log(4.0 / alpha)
    count = np.asarray(count, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(2 * var * ell / count) + 7 * width * ell / (3 * (count - 1))
    return np.where(count >= 2, r, np.inf)


def _pvalue(d, a, b) -> np.ndarray:
    ok = np.isfinite(d) & np.isfinite(a) & np.isfinite(b) & (d > 0) & (b > 0)
    a_, b_, d_ = np.where(ok, a, 0.0), np.where(ok, b, 1.0), np.where(ok, d, 0.0)
    s = (-a_ + np.sqrt(a_**2 + 4 * b_ * d_)) / (2 * b_)
    return np.where(ok, np.minimum(1.0, 4.0 * np.exp(-(s**2))), 1.0)


def bernstein_test(samples: HypothesisSamples) -> tuple[np.ndarray, np.ndarray]:
    """Empirical-Bernstein p-values (p_lo, p_up), shape (H,) each (see module doc)."""
    (q_lo, q_up, q_tw), (v_lo, v_up, v_tw) = _means_and_variances(samples)
    n, nhat, r = samples.n.astype(float), samples.nhat.astype(float), samples.width
    with np.errstate(invalid="ignore", divide="ignore"):
        b = 7 * r / (3 * (n - 1)) + 7 * r / (3 * (nhat - 1))
        a_lo = np.sqrt(2 * v_lo / n) + np.sqrt(2 * v_tw / nhat)
        a_up = np.sqrt(2 * v_up / n) + np.sqrt(2 * v_tw / nhat)
    valid = (n >= 2) & (nhat >= 2)
    b = np.where(valid, b, np.nan)
    p_lo = _pvalue(q_lo - q_tw, a_lo, b)
    p_up = _pvalue(q_tw - q_up, a_up, b)
    return p_lo, p_up
