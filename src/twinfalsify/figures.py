"""Figures recomputed from the results table (matplotlib/seaborn, print-size)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import seaborn as sns  # noqa: E402

from twinfalsify.schema import OUTCOMES  # noqa: E402

STYLE = {"context": "paper", "style": "whitegrid", "font_scale": 1.1}


def save(fig: plt.Figure, path: str | Path) -> None:
    """Write the figure (format from the suffix) atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=200, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)


def pvalue_boxen(
    results: pd.DataFrame, method: str = "hoeffding", kind: str = "causal", title: str | None = None
) -> plt.Figure:
    """Boxen plots of -log10 p_lo and -log10 p_up per outcome (paper's p-value figure)."""
    sns.set_theme(**STYLE)
    sub = results[(results["method"] == method) & (results["kind"] == kind)].copy()
    sub["neg_log10_p"] = -np.log10(np.clip(sub["p_value"].to_numpy(float), 1e-300, 1.0))
    order = [o for o in OUTCOMES if o in set(sub["outcome"])]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    for ax, side, label in zip(axes, ("lo", "up"), ("$p_{lo}$", "$p_{up}$"), strict=True):
        part = sub[sub["side"] == side]
        if len(part):
            sns.boxenplot(
                data=part,
                x="outcome",
                y="neg_log10_p",
                order=order,
                ax=ax,
                color="#4c72b0",
                k_depth="trustworthy",
            )
            rej = part[part["rejected"]]
            if len(rej):
                thr = -np.log10(rej["p_value"].max())
                ax.axhline(
                    thr,
                    ls="--",
                    color="#c44e52",
                    lw=1,
                    label=f"rejected after {part['correction'].iloc[0]}",
                )
                ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel("outcome")
        ax.set_ylabel(f"$-\\log_{{10}}$ {label}")
        ax.set_title(f"H_{side}: {label}")
        ax.tick_params(axis="x", rotation=60)
    fig.suptitle(title or f"{method} p-values, {kind} hypotheses")
    fig.tight_layout()
    return fig
