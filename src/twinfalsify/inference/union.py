"""The paper's union rule and its p-value, shared by every interval method.

Rule (docs/explanation/method.md, Cornish et al. 2026): reject H_lo: Q_twin >= Q_lo at level alpha
when the upper (1 - alpha/2) confidence bound of Q_twin lies strictly below the
lower (1 - alpha/2) confidence bound of Q_lo (mirror for H_up: the upper bound
of Q_up below the lower bound of Q_twin). By a union bound over the two one-sided
bounds the test has level alpha. Its p-value is

    p = inf { alpha in (0, 1] : the rule rejects at alpha },   p = 1 if it never does.

When the bounds widen as alpha decreases (every method here), the rejection set
is an interval [p, 1] (or (p, 1]), so p is found by bisection on log(alpha),
vectorised over hypotheses. Methods with a closed form (Hoeffding, empirical
Bernstein, betting) use it; this bisection is their reference in the tests.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: smallest alpha the bisection resolves (p-values below it are reported as it)
ALPHA_FLOOR = 1e-300


def union_reject(upper_small: np.ndarray, lower_large: np.ndarray) -> np.ndarray:
    """The rule itself: the upper bound of the smaller mean < the lower bound of the larger.

    For H_lo pass (upper bound of Q_twin, lower bound of Q_lo); for H_up pass
    (upper bound of Q_up, lower bound of Q_twin). NaN bounds (empty samples) never reject.
    """
    u, lo = np.asarray(upper_small, float), np.asarray(lower_large, float)
    with np.errstate(invalid="ignore"):
        return np.isfinite(u) & np.isfinite(lo) & (u < lo)


def smallest_rejecting_alpha(
    reject: Callable[[np.ndarray], np.ndarray],
    size: int,
    *,
    rtol: float = 1e-10,
    max_iter: int = 200,
    alpha_floor: float = ALPHA_FLOOR,
) -> np.ndarray:
    """p = inf{alpha : reject(alpha)} for ``size`` hypotheses at once, by bisection.

    ``reject(alpha)`` takes an array of shape (size,) of levels (one per hypothesis)
    and returns booleans of shape (size,); it must be monotone (rejecting at alpha
    implies rejecting at every larger alpha). Bisection runs on log(alpha) until
    the bracket's relative width is below ``rtol``; the returned value is the
    bracket's upper end (a level at which the rule does reject), so p is never
    understated by more than ``rtol`` relative. p = 1 where reject(1) is False.
    """
    hi = np.ones(size)
    ok = np.asarray(reject(hi), bool)
    p = np.ones(size)
    if not ok.any():
        return p
    idx = np.flatnonzero(ok)
    lo_log = np.full(idx.size, np.log(alpha_floor))
    hi_log = np.zeros(idx.size)
    full = np.ones(size)  # hypotheses that never reject stay at alpha = 1
    for _ in range(max_iter):
        if np.all(hi_log - lo_log <= rtol):
            break
        mid = 0.5 * (lo_log + hi_log)
        full[idx] = np.exp(mid)
        r = np.asarray(reject(full), bool)[idx]
        hi_log = np.where(r, mid, hi_log)
        lo_log = np.where(r, lo_log, mid)
    p[idx] = np.exp(hi_log)
    return p
