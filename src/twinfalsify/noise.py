"""Counter-based randomness: normals keyed by integers, independent of call order.

A twin's noise for run i, hour s and feature k is a pure function of
(seed_i, hash of doses 1..s, s, k), so the same run gives the same numbers in
any batch, shard or worker process, and sequences sharing a prefix share it.
SplitMix64 (Steele, Lea & Flood 2014) mixes the keys; uniforms go through the
normal quantile function.
"""

from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def mix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = np.asarray(x, dtype=np.uint64) + _GOLDEN
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
        return z ^ (z >> np.uint64(31))


def combine(*keys: np.ndarray | int) -> np.ndarray:
    """Hash several integer keys (broadcast) into one uint64 key."""
    out = np.uint64(0x243F6A8885A308D3)
    for k in keys:
        out = mix64(np.bitwise_xor(out, np.asarray(k).astype(np.uint64)))
    return out


def uniform(key: np.ndarray) -> np.ndarray:
    """U(0, 1) strictly inside (0, 1), from the top 53 bits of a mixed key."""
    bits = mix64(key) >> np.uint64(11)
    return (bits.astype(np.float64) + 0.5) / float(1 << 53)


def normal(key: np.ndarray) -> np.ndarray:
    from scipy.special import ndtri  # not at import: the workflow's parse imports this module

    return ndtri(uniform(key))


def dose_prefix_keys(doses: np.ndarray) -> np.ndarray:
    """(n, t, 2) doses -> (n, t) uint64 keys; key[:, s] hashes doses of hours 1..s+1."""
    bits = np.ascontiguousarray(doses, dtype=np.float64).view(np.uint64)
    n, t, _ = doses.shape
    keys = np.empty((n, t), dtype=np.uint64)
    h = np.full(n, np.uint64(0x13198A2E03707344))
    for s in range(t):
        h = combine(h, bits[:, s, 0], bits[:, s, 1])
        keys[:, s] = h
    return keys
