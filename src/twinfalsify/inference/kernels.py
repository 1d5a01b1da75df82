"""The compiled loops (numba) of the betting test and its capital.

They live in one module that :mod:`~twinfalsify.inference.capital` and
:mod:`~twinfalsify.inference.betting` import when a test first bets, not when they are
imported: a job that never bets (most figures, the summary, a Hoeffding-only study) does not pay
numba's import. Each kernel's numpy form and formula are in the function that calls it;
tests compare every kernel with a plain form (``tests/inference/test_betting.py``,
``test_star_bets.py``).
``cache=True``: the machine code is kept beside this file and reused by later processes.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def rescaled_moments(staged: np.ndarray, real: np.ndarray, perm: np.ndarray,
                     offsets: np.ndarray, y_lo: np.ndarray, y_up: np.ndarray,
                     fill: float, x: np.ndarray, sig2: np.ndarray) -> None:  # pragma: no cover
    """One pass of what rescaling, ordering and ``capital.running_moments`` do in several.

    Element i of group g (flat, ``offsets``) is ``staged[perm[i]]`` rescaled to
    (clip(y, y_lo[g], y_up[g]) - y_lo[g]) / (y_up[g] - y_lo[g]) when ``real[perm[i]]``, else
    ``fill``; written to ``x``, and its predictable variance sigma2_{i-1} to ``sig2``. The
    sums run over the whole flat array and restart by subtraction, as
    ``capital.segment_cumsum`` does, so every value equals the numpy form's bit for bit.
    """
    cs, cs2, prev = 0.0, 0.0, 0.25
    for g in range(len(offsets) - 1):
        a, b = offsets[g], offsets[g + 1]
        lo, up = y_lo[g], y_up[g]
        w = up - lo
        base, base2 = cs, cs2
        for i in range(a, b):
            j = perm[i]
            if real[j]:
                v = staged[j]
                v = v if v > lo else lo  # numpy's clip: min(max(v, lo), up)
                v = v if v < up else up
                xi = (v - lo) / w
            else:
                xi = fill
            x[i] = xi
            t = i - a + 1
            cs += xi
            mu = (0.5 + (cs - base)) / (t + 1)
            cs2 += (xi - mu) * (xi - mu)
            sig2[i] = 0.25 if i == a else prev
            prev = (0.25 + (cs2 - base2)) / (t + 1)


LANES = 4  # groups stepped together: independent chains hide the latency of sqrt and log1p


@numba.njit(cache=True, nogil=True)
def star_kernel(x, sig2, offsets, m, target, sign, running_max, c, r0, order, out):
    """``capital.star_log_capital``'s recursion, ``LANES`` groups (by ``order``) at a time."""
    n_groups = len(offsets) - 1
    pos = np.empty(LANES, np.int64)
    end = np.empty(LANES, np.int64)
    ell = np.empty(LANES)
    top = np.empty(LANES)
    mg = np.empty(LANES)
    var_m = np.empty(LANES)
    cap = np.empty(LANES)
    tgt = np.empty(LANES)
    for g0 in range(0, n_groups, LANES):
        lanes = min(LANES, n_groups - g0)
        steps = np.int64(1) << 62
        for k in range(lanes):
            g = order[g0 + k]
            pos[k], end[k] = offsets[g], offsets[g + 1]
            steps = min(steps, end[k] - pos[k])
            mk = m[g] if sign > 0 else 1.0 - m[g]
            mg[k], var_m[k], cap[k], tgt[k] = mk, mk * (1.0 - mk), c / mk, target[g]
            ell[k], top[k] = 0.0, 0.0
        for j in range(steps):
            for k in range(lanes):
                i = pos[k] + j
                xi = x[i] if sign > 0 else 1.0 - x[i]
                need = tgt[k] - ell[k]
                b = math.sqrt(2.0 * max(need, r0) / ((end[k] - i) * min(sig2[i], var_m[k])))
                if need < r0:
                    b *= math.exp(need - r0)
                ell[k] += math.log1p(min(b, cap[k]) * (xi - mg[k]))
                top[k] = max(top[k], ell[k])
        for k in range(lanes):
            e, tp = ell[k], top[k]
            for i in range(pos[k] + steps, end[k]):
                xi = x[i] if sign > 0 else 1.0 - x[i]
                need = tgt[k] - e
                b = math.sqrt(2.0 * max(need, r0) / ((end[k] - i) * min(sig2[i], var_m[k])))
                if need < r0:
                    b *= math.exp(need - r0)
                e += math.log1p(min(b, cap[k]) * (xi - mg[k]))
                tp = max(tp, e)
            out[order[g0 + k]] = tp if running_max else e


@numba.njit(cache=True, nogil=True)
def mix64_one(z: np.uint64) -> np.uint64:  # pragma: no cover - compiled
    """``betting._mix64`` of one value (uint64 arithmetic wraps, as numpy's does)."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, nogil=True)
def stable_argsort(bits: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """argsort of uint64 keys, equal keys in ascending index (what a stable sort gives)."""
    idx = np.argsort(bits)
    n, i = len(bits), 0
    while i < n:
        j = i + 1
        while j < n and bits[idx[j]] == bits[idx[i]]:
            j += 1
        if j - i > 1:
            idx[i:j] = np.sort(idx[i:j])
        i = j
    return idx


@numba.njit(cache=True, nogil=True)
def order_within_groups(hk: np.ndarray, offsets: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Flat permutation: group g's positions sorted by the top 53 bits of
    splitmix64(hk[g] ^ position), ties by position. One group at a time (cache-sized),
    the same permutation as ``np.lexsort((U, gid))`` over the whole flat array."""
    out = np.empty(offsets[-1], np.int64)
    for g in range(len(offsets) - 1):
        a, n = offsets[g], offsets[g + 1] - offsets[g]
        bits = np.empty(n, np.uint64)
        for p in range(n):
            bits[p] = mix64_one(hk[g] ^ np.uint64(p)) >> np.uint64(11)
        out[a: a + n] = stable_argsort(bits) + a
    return out
