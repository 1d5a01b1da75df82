r"""Family-wise (Holm, Bonferroni) and false-discovery (Benjamini-Yekutieli) corrections.

With the m p-values of a family sorted, :math:`p_{(1)} \le \dots \le p_{(m)}`:

- **Holm** (1979), step-down: reject :math:`H_{(1)}, \dots, H_{(k)}` for the largest k with
  :math:`p_{(j)} \le \alpha / (m - j + 1)` for every :math:`j \le k`. Controls the FWER under
  arbitrary dependence.
- **Bonferroni**: reject :math:`H_i` when :math:`p_i \le \alpha / m`.
- **Benjamini & Yekutieli** (2001), step-up: reject :math:`H_{(1)}, \dots, H_{(k)}` for the
  largest k with :math:`p_{(k)} \le k \alpha / (m\, c_m)`, :math:`c_m = \sum_{i=1}^m 1/i`.
  Controls the FDR under arbitrary dependence (H_lo and H_up of one parameter set are
  dependent, so BH's PRDS condition is not assumed).

The decisions equal ``statsmodels.stats.multitest.multipletests`` with ``holm``,
``bonferroni`` and ``fdr_by``, operation for operation
(``tests/inference/test_hoeffding.py`` compares them on random and tied families). They are
written out here because that function calls ``gc.collect()`` on every family (about 75 ms
in a rule job's heap) and its import brings scipy.stats (about 0.9 s per rule job).
"""

from __future__ import annotations

import numpy as np

CORRECTIONS = ("holm", "by", "bonferroni", "none")


def correct(p_values: np.ndarray, alpha: float = 0.05, method: str = "holm") -> np.ndarray:
    """Boolean rejections after the named correction over all p-values given (one family)."""
    if method not in CORRECTIONS:
        raise ValueError(f"unknown correction {method!r}; choose one of {sorted(CORRECTIONS)}")
    p = np.asarray(p_values, float)
    if p.ndim != 1:
        raise ValueError(f"p-values must be one-dimensional, got shape {p.shape}")
    m = p.size
    if m == 0:
        return np.zeros(0, dtype=bool)
    if np.isnan(p).any():
        raise ValueError(f"{int(np.isnan(p).sum())} of {m} p-values are NaN")
    if method == "none":
        return p <= alpha
    if method == "bonferroni":
        return p <= alpha / float(m)
    order = np.argsort(p)
    p_sorted = p[order]
    if method == "holm":
        stop = np.flatnonzero(p_sorted > alpha / np.arange(m, 0, -1))
        k = stop[0] if stop.size else m  # the first sorted p-value that is not rejected
        reject_sorted = np.arange(m) < k
    else:  # by: step-up with the harmonic constant c_m
        c_m = np.sum(1.0 / np.arange(1, m + 1))
        below = np.flatnonzero(p_sorted <= (np.arange(1, m + 1) / float(m)) / c_m * alpha)
        reject_sorted = np.arange(m) <= below[-1] if below.size else np.zeros(m, dtype=bool)
    reject = np.empty(m, dtype=bool)
    reject[order] = reject_sorted
    return reject


def correct_within(p_values: np.ndarray, families: np.ndarray, alpha: float = 0.05,
                   method: str = "holm") -> np.ndarray:
    """Boolean rejections after the named correction within each family (one label per
    p-value): the one place a study's families are corrected (tests, sensitivity, sequential)."""
    p = np.asarray(p_values, float)
    fam = np.asarray(families)
    if fam.shape != p.shape:
        raise ValueError(f"families has shape {fam.shape}, p-values {p.shape}")
    out = np.zeros(p.shape, dtype=bool)
    for idx in _groups(fam):
        out[idx] = correct(p[idx], alpha, method)
    return out


def _groups(labels: np.ndarray) -> list[np.ndarray]:
    """Indices of each distinct label, in order of first appearance."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    return [np.flatnonzero(inverse == g) for g in order]


def thresholds(p_values: np.ndarray, alpha: float = 0.05,
               method: str = "holm") -> tuple[np.ndarray, np.ndarray]:
    """(threshold, rank) of each p-value in one family: the level its own step compares it
    with (Holm: alpha / (m - rank + 1), a step-down that also needs every smaller p-value
    rejected; Bonferroni: alpha / m; BY: rank alpha / (m c_m), a step-up; none: alpha) and
    its 1-based rank among the sorted p-values (ties in the order given)."""
    if method not in CORRECTIONS:
        raise ValueError(f"unknown correction {method!r}; choose one of {sorted(CORRECTIONS)}")
    p = np.asarray(p_values, float)
    m = p.size
    rank = np.empty(m, dtype=np.int64)
    rank[np.argsort(p, kind="stable")] = np.arange(1, m + 1)
    if method == "none":
        level = np.full(m, float(alpha))
    elif method == "bonferroni":
        level = np.full(m, alpha / max(m, 1))
    elif method == "holm":
        level = alpha / (m - rank + 1.0)
    else:
        level = rank / float(m) / np.sum(1.0 / np.arange(1, m + 1)) * alpha
    return level, rank


def thresholds_within(p_values: np.ndarray, families: np.ndarray, alpha: float = 0.05,
                      method: str = "holm") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(threshold, rank, family size) of each p-value within its family (as ``correct_within``
    groups them)."""
    p = np.asarray(p_values, float)
    level = np.zeros(p.shape)
    rank = np.zeros(p.shape, dtype=np.int64)
    size = np.zeros(p.shape, dtype=np.int64)
    for idx in _groups(np.asarray(families)):
        level[idx], rank[idx] = thresholds(p[idx], alpha, method)
        size[idx] = idx.size
    return level, rank, size
