"""Sensitivity of the rejections to the outcome range [y_lo, y_up] (the paper's appendix).

For every Delta in a grid, rerun each test with

    y_lo -> y_lo (1 - Delta/2),   y_up -> y_up (1 + Delta/2)

(Delta = 0 reproduces the main analysis; larger Delta widens the bounds for
positive outcomes, so rejections should fall), correct all 2H one-sided p-values
of the run together (Holm by default, as in the main analysis) and count
rejections per group (e.g. outcome). Note: for a negative y_lo the map moves y_lo
up (towards 0), i.e. it is a relative, not an absolute, widening; every outcome
in this study is positive (MIMIC units), and the sweep refuses ranges that become
empty. Reference: Cornish et al. (2026), JMLR, appendix (sensitivity to y_lo, y_up).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]
COLUMNS = ["delta", "method", "group", "n_hypotheses", "n_rejected"]


def widened(samples: HypothesisSamples, delta: float) -> HypothesisSamples:
    """The samples with [y_lo (1 - delta/2), y_up (1 + delta/2)]."""
    y_lo = samples.y_lo * (1 - delta / 2)
    y_up = samples.y_up * (1 + delta / 2)
    if np.any(~(y_up > y_lo)):
        bad = np.flatnonzero(~(y_up > y_lo))[:5].tolist()
        raise ValueError(f"sensitivity: Delta={delta} leaves an empty range for hypotheses {bad}")
    return samples.with_bounds(y_lo, y_up)


def sensitivity_sweep(
    samples: HypothesisSamples,
    deltas: Sequence[float],
    methods: Mapping[str, Method],
    alpha: float = 0.05,
    correction: str = "holm",
    group: np.ndarray | None = None,
) -> pd.DataFrame:
    """Long table (delta, method, group, n_hypotheses, n_rejected); both sides counted.

    n_hypotheses counts one-sided hypotheses (2 per parameter set, as the paper's
    1,442 = 2 x 721); the correction runs over all of them at each (delta, method).
    ``group`` labels each parameter set (default: one group "all").
    """
    h = len(samples)
    labels = np.full(h, "all", dtype=object) if group is None else np.asarray(group, dtype=object)
    if labels.shape != (h,):
        raise ValueError(f"sensitivity: group has shape {labels.shape}, expected ({h},)")
    if not methods:
        raise ValueError("sensitivity: no methods given")
    uniq = pd.unique(labels)
    rows = []
    for delta in deltas:
        s = widened(samples, float(delta))
        for name, fn in methods.items():
            p_lo, p_up = fn(s)
            rej = correct(np.concatenate([p_lo, p_up]), alpha=alpha, method=correction)
            per = rej[:h].astype(int) + rej[h:].astype(int)
            counts = pd.Series(per).groupby(labels).sum()
            sizes = pd.Series(np.ones(h, int)).groupby(labels).sum()
            for g in uniq:
                rows.append((float(delta), name, g, int(2 * sizes[g]), int(counts[g])))
    return pd.DataFrame(rows, columns=COLUMNS)


def plot_sensitivity(table: pd.DataFrame, path: str | Path) -> Path:
    """Line figure: rejections per group against Delta, one panel per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    missing = set(COLUMNS) - set(table.columns)
    if missing:
        raise ValueError(f"plot_sensitivity: table lacks columns {sorted(missing)}")
    methods = list(pd.unique(table["method"]))
    fig, axes = plt.subplots(1, len(methods), figsize=(4.5 * len(methods), 3.6), squeeze=False,
                             sharey=True)
    for ax, m in zip(axes[0], methods, strict=True):
        sub = table[table["method"] == m]
        for g, d in sub.groupby("group", sort=True):
            d = d.sort_values("delta")
            ax.plot(d["delta"], d["n_rejected"], marker="o", ms=3, label=str(g))
        ax.set_title(m)
        ax.set_xlabel(r"$\Delta$")
    axes[0][0].set_ylabel("rejections")
    axes[0][-1].legend(fontsize=7, ncol=1, bbox_to_anchor=(1.02, 1), loc="upper left")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)  # atomic
    return path
