"""Reference forms of optimised library code: the tests hold the fast forms to these bit for
bit."""

from __future__ import annotations

import numpy as np

from twinfalsify.inference.bootstrap import draw_blocks
from twinfalsify.inference.samples import Ragged


def resample_sums_reference(
    values: Ragged, rows: np.ndarray, counts: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """``bootstrap._resample_sums``'s draws and sums in their first form (a padded copy of
    each group, int64 draws, ``take_along_axis``, ``where``) over the library's blocks: what
    the faster form must keep."""
    n_rows, n_b = counts.shape
    out = np.zeros((n_rows, n_b))
    if n_rows == 0:
        return out
    sizes = values.sizes[rows]
    m_row = counts.max(axis=1)
    for block in draw_blocks(m_row, n_b):  # the blocks are the library's own
        m = int(m_row[block].max())
        if m > 0:
            r = block.size
            size_i = sizes[block].astype(np.int64)
            col = np.arange(int(size_i.max()))
            src = values.offsets[rows[block]][:, None] + np.minimum(
                col, np.maximum(size_i, 1)[:, None] - 1
            )
            padded = values.values[np.minimum(src, max(len(values.values) - 1, 0))]
            idx = rng.integers(0, 1 << 32, size=(r, n_b * m), dtype=np.int64)
            idx *= size_i[:, None]
            idx >>= 32
            g = np.take_along_axis(padded, idx, axis=1).reshape(r, n_b, m)
            keep = np.arange(m) < counts[block][:, :, None]
            out[block] = np.where(keep, g, 0.0).sum(axis=2)
    return out


def hashed_order_reference(sizes: np.ndarray, keys: np.ndarray, copy: np.ndarray,
                           seed: int | None, salt: int) -> np.ndarray:
    """``betting._hashed_order`` in its first form: the whole flat array's hash keys in numpy,
    then ``np.lexsort((U, gid))``."""
    from twinfalsify.inference.betting import _DATA_ORDER, _mix64

    sizes = np.asarray(sizes, np.int64)
    gid = np.repeat(np.arange(len(sizes)), sizes)
    pos = np.arange(int(sizes.sum()), dtype=np.int64) - np.repeat(
        np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes)
    head = _DATA_ORDER if seed is None else (int(seed) & 0xFFFFFFFF) << 8
    with np.errstate(over="ignore"):
        base = _mix64(np.array([head | salt], dtype=np.uint64))
        hk = _mix64(base ^ np.asarray(keys, np.int64).astype(np.uint64))
        hk = _mix64(hk ^ (np.asarray(copy, np.int64).astype(np.uint64) << np.uint64(40)))
        u = _mix64(hk[gid] ^ pos.astype(np.uint64))
    frac = (u >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)
    return np.lexsort((frac, gid))
