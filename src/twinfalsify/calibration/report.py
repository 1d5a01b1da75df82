"""The calibration report: power and coverage figures, the markdown summary."""

from __future__ import annotations

import numpy as np
import pandas as pd

from twinfalsify.calibration.config import (
    ADAPTIVE,
    HOURS_TARGET,
    KEPT_TARGET,
    NAIVE,
    CalibrationConfig,
)
from twinfalsify.calibration.metrics import adaptive_summary, coverage_summary, width_summary
from twinfalsify.tables import markdown_table


def plot_power(summary: pd.DataFrame, png: str, pdf: str) -> None:
    """Power curves: rate of >= 1 rejection (95 % CI bars) and mean share rejected vs bias,
    one column per kind, one line per method; bias 0 is the oracle (its FWER)."""
    from twinfalsify.figures import plt, save

    kinds = sorted(pd.unique(summary["kind"]))
    fig, axes = plt.subplots(2, len(kinds), figsize=(5.2 * len(kinds), 7), squeeze=False)
    for j, kind in enumerate(kinds):
        sub = summary[summary["kind"] == kind]
        for method, d in sub.groupby("method", sort=True):
            d = d.sort_values("bias")
            style = dict(marker="o", ms=3, ls="--" if method == NAIVE else "-", label=method)
            yerr = np.vstack([d["any_rejection_rate"] - d["ci_low"],
                              d["ci_high"] - d["any_rejection_rate"]])  # fmt: skip
            axes[0][j].errorbar(d["bias"], d["any_rejection_rate"], yerr=yerr, capsize=2, **style)
            axes[1][j].plot(d["bias"], d["mean_share_rejected"], **style)
        axes[0][j].axhline(0.05, color="grey", lw=0.8, ls=":")
        axes[0][j].set_title(f"{kind}: P(>= 1 Holm rejection)")
        axes[1][j].set_title(f"{kind}: mean share of hypotheses rejected")
        for i in range(2):
            axes[i][j].set_xlabel("twin bias (outcome SDs; 0 = oracle)")
            axes[i][j].set_ylim(-0.02, 1.02)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.tight_layout()
    save(fig, png)
    save(fig, pdf)
    plt.close(fig)


def plot_coverage(cov: pd.DataFrame, png: str, pdf: str) -> None:
    """Position of the true Q within the population bounds, (Q - Q_lo)/(Q_up - Q_lo):
    the theorem says every value lies in [0, 1]."""
    from twinfalsify.figures import plt, save

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for kind, d in cov.groupby("kind", sort=True):
        pos = (d["q_true"] - d["q_lo_pop"]) / (d["q_up_pop"] - d["q_lo_pop"]).where(
            lambda w: w > 0
        )
        ax.hist(pos.dropna(), bins=30, range=(-0.25, 1.25), alpha=0.6, label=f"{kind} ({len(d)})")
    for x in (0, 1):
        ax.axvline(x, color="k", lw=0.8)
    ax.set_xlabel(r"$(Q - Q_{lo}) / (Q_{up} - Q_{lo})$ (true Q by Monte Carlo)")
    ax.set_ylabel("hypotheses")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save(fig, png)
    save(fig, pdf)
    plt.close(fig)


def _md_table(df: pd.DataFrame, floatfmt: str = ".3f") -> str:
    return markdown_table(df, floatfmt)


def markdown_summary(
    cfg: CalibrationConfig,
    summary: pd.DataFrame,
    dom: pd.DataFrame,
    cov: pd.DataFrame,
    wid: pd.DataFrame,
    timing: pd.DataFrame,
    adaptive: pd.DataFrame | None = None,
) -> str:
    """The run's findings in Markdown: every number is read from the tables passed in
    (``adaptive``: the per-replicate ADAPTIVE_COLUMNS table, when the adaptive test ran)."""
    r = int(summary["replicates"].max())
    fw = summary[summary["bias"] == 0].copy()
    fw["FWER (95 % CI)"] = [
        f"{a:.3f} [{lo:.3f}, {hi:.3f}]"
        for a, lo, hi in zip(fw["any_rejection_rate"], fw["ci_low"], fw["ci_high"], strict=True)
    ]
    fw["verdict"] = [
        ("ok" if v else "FAILS") if e else ("ok" if v else "above alpha (reported)")
        for v, e in zip(fw["valid"], fw["exact"], strict=True)
    ]
    fw = fw[["method", "kind", "FWER (95 % CI)", "mean_rejections", "exact", "verdict"]]
    pw = summary[summary["bias"] > 0].pivot_table(
        index=["method", "kind"], columns="bias", values="any_rejection_rate"
    )
    pw.columns = [f"bias {b:g}" for b in pw.columns]
    sh = summary[summary["bias"] > 0].pivot_table(
        index=["method", "kind"], columns="bias", values="mean_rejections"
    )
    sh.columns = [f"bias {b:g}" for b in sh.columns]
    cs = coverage_summary(cov)
    ws = width_summary(wid)
    exact_bad = fw[(fw["exact"]) & (fw["verdict"] != "ok")]
    parts = [
        "# Calibration on the synthetic world",
        "",
        f"{r} replicates; {cfg.n_stays} stays each (D0 {cfg.d0_fraction:.0%}, min_support "
        f"{cfg.min_support}), {cfg.runs_per_sequence} twin runs per action sequence, "
        f"alpha {cfg.alpha}, correction {cfg.correction} within each (method, kind) family. "
        f"Biased twins: every outcome in {len(cfg.bias_features)} shifted by bias x its D0 SD. "
        f"Mean {timing['n_hyps'].mean():.0f} parameter sets per replicate; "
        f"{timing['seconds'].sum():.0f} s of replicate compute in total.",
        "",
        "## Family-wise error of the oracle twin",
        "",
        _md_table(fw),
        "",
        "Exact methods failing calibration: "
        + (", ".join(f"{m} ({k})" for m, k in exact_bad[["method", "kind"]].itertuples(index=False))
           or "none") + ".",  # fmt: skip
        "",
        "## Power against biased twins: P(>= 1 rejection)",
        "",
        _md_table(pw.reset_index()),
        "",
        "Mean number of rejections per replicate:",
        "",
        _md_table(sh.reset_index(), ".1f"),
        "",
    ]
    if not dom.empty:
        ok = bool(dom["at_least_as_often"].all())
        parts += [
            f"Betting rejects at least as often as Hoeffding at every bias level: **{ok}**",
            "",
            _md_table(dom),
            "",
        ]
    if adaptive is not None and not adaptive.empty:
        parts += adaptive_markdown(adaptive_summary(adaptive))
    parts += ["## Coverage of the bounds", "", _md_table(cs) if not cs.empty else "(not run)", ""]
    naive = summary[(summary["method"] == NAIVE)]
    if not naive.empty:
        o = naive[naive["bias"] == 0]
        parts += [
            "## The naive-comparison pitfall (Welch t-test, twin vs followers, no bounds)",
            "",
            "Oracle (a correct twin) rejected in "
            + ", ".join(
                f"{k}: {a:.0%} of replicates (mean {m:.1f} rejections)"
                for k, a, m in o[["kind", "any_rejection_rate", "mean_rejections"]].itertuples(
                    index=False
                )
            )
            + ".",
            "",
        ]
    parts += ["## Width of the bounds: mean (Q_up - Q_lo)/(y_up - y_lo)", "", _md_table(ws), ""]
    return "\n".join(parts)


def adaptive_markdown(asum: pd.DataFrame) -> list[str]:
    """Summary section of the adaptive test: twin-hours and kept rejections per bias, and
    the hours target read off the table (never asserted)."""

    def share(x: float) -> str:
        return "n/a" if np.isnan(x) else f"{x:.0%}"

    def verdict(v) -> str:
        return "n/a (no fixed rejection)" if v is pd.NA else ("met" if v else "missed")

    t = pd.DataFrame({
        "bias": asum["bias"],
        "twin-hours adaptive / fixed (mean)": [
            f"{a:,.0f} / {f:,.0f}"
            for a, f in zip(asum["mean_twin_hours_adaptive"], asum["mean_twin_hours_fixed"],
                            strict=True)
        ],
        "hours ratio (pooled, worst)": [
            f"{r:.3f} ({m:.3f})" for r, m in zip(asum["hours_ratio"], asum["hours_ratio_max"],
                                                 strict=True)
        ],
        "rejections adaptive / betting / Hoeffding": [
            f"{a:.1f} / {b:.1f} / {h:.1f}"
            for a, b, h in zip(asum["mean_rejections_adaptive"], asum["mean_rejections_betting"],
                               asum["mean_rejections_hoeffding"], strict=True)
        ],
        "kept (betting, Hoeffding)": [
            f"{share(b)}, {share(h)}"
            for b, h in zip(asum["kept_share_betting"], asum["kept_share_hoeffding"], strict=True)
        ],
        "undecided sides": asum["mean_undecided_sides"].map(lambda x: f"{x:.1f}"),
        "hours <= 1/10": asum["target_hours"].map(lambda v: "met" if v else "missed"),
        "kept >= 90 %": asum["target_rejections"].map(verdict),
    })  # fmt: skip
    return [
        f"## Adaptive twin runs ({ADAPTIVE}, batches of {int(asum['batch_size'].iloc[0])})",
        "",
        "Its FWER and power are the betting_sequential rows of the tables above. Twin-hours "
        "with prefix reuse, means per replicate; the ratio is pooled over replicates (worst "
        "replicate in brackets). Kept = share of the fixed test's rejections (same replicate, "
        "parameter set and side) that the adaptive test also makes. Per-replicate means of "
        "rejections over both kinds.",
        "",
        _md_table(t),
        "",
        f"Target (<= {HOURS_TARGET:g} of the fixed twin-hours while keeping >= "
        f"{KEPT_TARGET:.0%} of the fixed betting test's rejections; the hours alone where the "
        "fixed test rejects nothing) met at bias level(s): "
        + (", ".join(
            f"{b:g}" for b, h, k in zip(asum["bias"], asum["target_hours"],
                                        asum["target_rejections"], strict=True)
            if h and k is not False
        ) or "none") + ".",
        "",
    ]  # fmt: skip
