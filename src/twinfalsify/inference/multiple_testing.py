"""Family-wise (Holm) and false-discovery (Benjamini-Yekutieli) corrections.

Holm (1979) controls the FWER under arbitrary dependence; Benjamini & Yekutieli
(2001) control the FDR under arbitrary dependence (H_lo and H_up of one
parameter set are dependent, so BH's PRDS condition is not assumed).
Both via statsmodels.stats.multitest.multipletests.
"""

from __future__ import annotations

import numpy as np
from statsmodels.stats.multitest import multipletests

CORRECTIONS = {"holm": "holm", "by": "fdr_by", "bonferroni": "bonferroni", "none": None}


def correct(p_values: np.ndarray, alpha: float = 0.05, method: str = "holm") -> np.ndarray:
    """Boolean rejections after the named correction over all p-values given."""
    if method not in CORRECTIONS:
        raise ValueError(f"unknown correction {method!r}; choose one of {sorted(CORRECTIONS)}")
    p = np.asarray(p_values, float)
    if p.size == 0:
        return np.zeros(0, dtype=bool)
    if CORRECTIONS[method] is None:
        return p <= alpha
    reject, *_ = multipletests(p, alpha=alpha, method=CORRECTIONS[method])
    return reject
