"""Reference forms of optimised library code: the tests hold the fast forms to these bit for
bit."""

from __future__ import annotations

import numpy as np

from twinfalsify.inference.bootstrap import _CHUNK_DRAWS
from twinfalsify.inference.samples import Ragged


def resample_sums_reference(
    values: Ragged, rows: np.ndarray, counts: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """``bootstrap._resample_sums`` as it first was (a padded copy of each group, int64
    draws, ``take_along_axis``, ``where``): the draws and sums the faster form must keep."""
    n_rows, n_b = counts.shape
    out = np.zeros((n_rows, n_b))
    if n_rows == 0:
        return out
    sizes = values.sizes[rows]
    m_row = counts.max(axis=1)
    order = np.argsort(m_row, kind="stable")
    i = 0
    while i < n_rows:
        m_first = int(m_row[order[i]])
        j = i + 1
        while j < n_rows:
            m_j = int(m_row[order[j]])
            if (j + 1 - i) * n_b * max(m_j, 1) > _CHUNK_DRAWS or m_j > 1.25 * m_first + 16:
                break
            j += 1
        block = order[i:j]
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
        i = j
    return out
