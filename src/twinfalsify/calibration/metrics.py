"""Aggregates over replicates: FWER and power with Clopper-Pearson intervals, coverage,
adaptive twin-hours and kept rejections, widths."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from twinfalsify.calibration.config import (
    ADAPTIVE,
    EXACT_METHODS,
    HOURS_TARGET,
    KEPT_TARGET,
)


def _binom_ci(k: int, n: int) -> tuple[float, float]:
    """Clopper-Pearson 95 % interval (scipy.stats.binomtest(...).proportion_ci)."""
    ci = stats.binomtest(int(k), int(n)).proportion_ci(0.95, method="exact")
    return float(ci.low), float(ci.high)


def summarise(tests: pd.DataFrame, alpha: float = 0.05) -> pd.DataFrame:
    """Per (method, kind, bias): rate of >= 1 rejection over replicates with its 95 % CI,
    and the mean share of hypotheses rejected. At bias 0 the rate is the oracle's FWER.

    ``valid`` (bias 0 only): the CI's lower end is <= alpha, i.e. FWER <= alpha is
    not contradicted at the 95 % level (a method whose whole CI is above alpha fails).
    """
    rows = []
    for (method, kind, bias), g in tests.groupby(["method", "kind", "bias"], sort=True):
        k, n = int(g["any_rejected"].sum()), len(g)
        lo, hi = _binom_ci(k, n)
        share = (g["n_rejected"] / g["n_tests"].clip(lower=1)).mean()
        rows.append({
            "method": method, "kind": kind, "bias": float(bias), "replicates": n,
            "any_rejection_rate": k / n, "ci_low": lo, "ci_high": hi,
            "mean_rejections": float(g["n_rejected"].mean()),
            "mean_share_rejected": float(share), "mean_tests": float(g["n_tests"].mean()),
            "exact": method in EXACT_METHODS,
            "valid": bool(lo <= alpha) if bias == 0 else pd.NA,
        })  # fmt: skip
    return pd.DataFrame(rows)


def dominance(summary: pd.DataFrame, better: str = "betting", than: str = "hoeffding"):
    """Per (kind, bias > 0): does ``better`` reject at least as often as ``than``?

    Compared on the mean number of rejections per replicate and on the rate of
    >= 1 rejection (both from the same replicates, so the comparison is paired).
    """
    s = summary[summary["bias"] > 0].set_index(["kind", "bias", "method"])
    if better not in s.index.get_level_values("method") or than not in s.index.get_level_values(
        "method"
    ):
        return pd.DataFrame()
    a, b = s.xs(better, level="method"), s.xs(than, level="method")
    out = pd.DataFrame({
        f"{better}_mean_rejections": a["mean_rejections"],
        f"{than}_mean_rejections": b["mean_rejections"],
        f"{better}_rate": a["any_rejection_rate"], f"{than}_rate": b["any_rejection_rate"],
    })  # fmt: skip
    out["at_least_as_often"] = (a["mean_rejections"] >= b["mean_rejections"]) & (
        a["any_rejection_rate"] >= b["any_rejection_rate"]
    )
    return out.reset_index()


def coverage_summary(cov: pd.DataFrame) -> pd.DataFrame:
    """Per kind: hypotheses checked, share strictly inside, share inside up to MC error."""
    if cov.empty:
        return pd.DataFrame(columns=["kind", "checked", "covered", "covered_mc"])
    g = cov.groupby("kind")
    out = pd.DataFrame({
        "checked": g.size(), "covered": g["covered"].mean(), "covered_mc": g["covered_mc"].mean(),
        "mean_width_ratio": g.apply(
            lambda x: ((x.q_up_pop - x.q_lo_pop) / (x.y_up - x.y_lo)).mean(), include_groups=False
        ),
    })  # fmt: skip
    return out.reset_index()


def adaptive_summary(adaptive: pd.DataFrame) -> pd.DataFrame:
    """Per bias: twin-hours adaptive vs fixed and rejections kept, with the hours target.

    hours_ratio = sum_r hours_adaptive / sum_r hours_fixed (pooled over replicates: the
    share of the whole calibration's twin-hours; ``hours_ratio_max`` = the worst
    replicate). kept_share_<m> = sum_r kept_r / sum_r rejected_r(fixed m), where kept_r
    counts the fixed test's rejections (parameter set, side) the adaptive test also makes
    (NA when the fixed test made none: nothing to keep). Target:
    hours_ratio <= 1/10 and kept_share_betting >= 0.9 — the fixed betting test is the
    like-for-like comparison (same statistic at the full budget); Hoeffding (the paper's
    test) is reported alongside.
    """
    rows = []
    for bias, g in adaptive.groupby("bias", sort=True):
        ha, hf = float(g["twin_hours_adaptive"].sum()), float(g["twin_hours_fixed"].sum())
        row = {
            "bias": float(bias), "replicates": len(g), "batch_size": int(g["batch_size"].iloc[0]),
            "mean_twin_hours_adaptive": ha / len(g), "mean_twin_hours_fixed": hf / len(g),
            "hours_ratio": ha / hf, "hours_ratio_max": float(g["hours_ratio"].max()),
            # the same stopping without B_0 skipping, and against the paper's scheme
            "hours_ratio_all_x0": float(g["twin_hours_all_x0"].sum()) / hf,
            "hours_ratio_paper": ha / float(g["twin_hours_paper"].sum()),
            "mean_rejections_adaptive": float(g["n_rejected"].mean()),
        }  # fmt: skip
        for m in ("betting", "hoeffding"):
            fixed, kept = g[f"n_rejected_{m}"], g[f"n_kept_{m}"]
            ran = bool(fixed.notna().all())  # the fixed method was configured
            tot = int(fixed.sum()) if ran else 0
            row[f"mean_rejections_{m}"] = float(fixed.mean()) if ran else np.nan
            row[f"kept_share_{m}"] = float(kept.sum()) / tot if tot > 0 else np.nan
        row["mean_undecided_sides"] = float(g["undecided_sides"].mean())
        row["mean_stop_fraction"] = float(g["mean_stop_fraction"].mean())
        row["target_hours"] = bool(row["hours_ratio"] <= HOURS_TARGET)
        kept = row["kept_share_betting"]
        row["target_rejections"] = pd.NA if np.isnan(kept) else bool(kept >= KEPT_TARGET)
        rows.append(row)
    return pd.DataFrame(rows)


def attach_hours(summary: pd.DataFrame, asum: pd.DataFrame) -> pd.DataFrame:
    """The calibration table with the adaptive rows' twin-hours (per bias; the hours are
    the twin's, shared by both kinds) and kept share; NaN for the fixed-scheme methods."""
    cols = ["mean_twin_hours_adaptive", "mean_twin_hours_fixed", "hours_ratio",
            "kept_share_betting"]  # fmt: skip
    out = summary.copy()
    for c in cols:
        out[c] = np.nan
    if asum.empty:
        return out
    sel = out["method"] == ADAPTIVE
    by_bias = asum.set_index("bias")[cols]
    out.loc[sel, cols] = by_bias.reindex(out.loc[sel, "bias"]).to_numpy()
    return out


def width_summary(w: pd.DataFrame) -> pd.DataFrame:
    g = w.groupby("kind")
    return pd.DataFrame({
        "replicates": g.size(), "mean_hyps": g["n_hyps"].mean(),
        "mean_width_ratio": g["mean_width_ratio"].mean(),
        "sd_width_ratio": g["mean_width_ratio"].std(ddof=1),
    }).reset_index()  # fmt: skip


# -- figures and the Markdown summary ---------------------------------------------


