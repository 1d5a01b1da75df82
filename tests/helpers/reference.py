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
