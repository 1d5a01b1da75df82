"""Figures recomputed from the results table (matplotlib/seaborn, print-size).

seaborn is imported only by the figures that draw with it (the boxen plots):
importing it, and the scipy.stats it imports, is most of a small figure job's time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from twinfalsify.design import N_DOSE_BINS, WHOLE_SPACE, subgroup_parts  # noqa: E402
from twinfalsify.io import write_atomic  # noqa: E402
from twinfalsify.schema import OUTCOMES  # noqa: E402

# seaborn's theme, written out as a matplotlib style file (tests check that they agree)
STYLE = {"context": "paper", "style": "whitegrid", "font_scale": 1.1}
STYLE_FILE = Path(__file__).with_name("figures.mplstyle")


# No creation date in the files: two runs of a study give byte-identical figures (PNG
# carries none; PDF and SVG would carry the time of the run)
_FIXED_METADATA = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}


def _savefig(fig: plt.Figure, path: Path) -> None:
    fmt = path.suffix.lstrip(".").lower()
    write_atomic(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=200, bbox_inches="tight",
                                               metadata=_FIXED_METADATA.get(fmt)))


def save(fig: plt.Figure, path: str | Path) -> None:
    """Write the figure (format from the suffix) atomically, without a creation date."""
    _savefig(fig, Path(path))
    plt.close(fig)


def pvalue_boxen(
    results: pd.DataFrame, method: str = "hoeffding", kind: str = "causal", title: str | None = None
) -> plt.Figure:
    """Boxen plots of -log10 p_lo and -log10 p_up per outcome (paper's p-value figure)."""
    import seaborn as sns

    apply_style()
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
            threshold_line(ax, sub, part)
            mark_floor(ax, part)
            legend_with_headroom(ax)
        ax.set_xlabel("outcome")
        # the panels share the y axis, whose one label (left) must hold for both sides: the
        # side is in each panel's title
        ax.set_ylabel("$-\\log_{10}$ p (dimensionless)")
        ax.set_title(f"$H_{{{side}}}$: p-values {label}")
        ax.tick_params(axis="x", rotation=60)
    fig.suptitle(title or f"{method} p-values, {kind} hypotheses")
    fig.tight_layout()
    return fig


# -- shared helpers ----------------------------------------------------------------------------


def mark_floor(ax: plt.Axes, part: pd.DataFrame) -> None:
    """Mark p-values reported at a floor (bootstrap: every resample separated, so the true p is
    below the bootstrap's resolution and only known to be <= the floor): a dotted line at the
    floor whose legend entry gives their count (one legend box, so no note hides under it)."""
    if "p_floor" not in part or not part["p_floor"].any():
        return
    fl = part.loc[part["p_floor"].astype(bool), "p_value"]
    y = -np.log10(float(fl.max()))
    ax.axhline(y, ls=":", color="0.4", lw=1,
               label=f"{len(fl)} at p = {fl.max():.0e}: all resamples separated\n"
               "(true p below the bootstrap's resolution)")  # fmt: skip


def legend_with_headroom(ax: plt.Axes, loc: str = "upper right", share: float = 0.32) -> None:
    """Legend of the labelled lines in the top ``share`` of the panel, kept free of data by
    raising the upper y limit (boxen plots reach the top of their data range)."""
    handles, labels = ax.get_legend_handles_labels()
    if not handles:
        return
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo, hi + (hi - lo) * share / (1 - share))
    ax.legend(handles, labels, loc=loc, fontsize=7, framealpha=0.9)

COLORS = {
    "bound": "#4c72b0",  # observational bounds [Q_lo, Q_up]
    "twin": "#dd8452",  # twin mean Q_twin
    "naive": "#55a868",  # naive observational mean
    "rejected": "#c44e52",
    "kept": "#8c8c8c",
}


CORRECTION_NAMES = {"holm": "Holm", "by": "Benjamini-Yekutieli", "bonferroni": "Bonferroni",
                    "none": "uncorrected"}


def rejection_threshold(p_values: np.ndarray, correction: str, alpha: float) -> float:
    """The p-value cut the correction applied to this family: every rejected p is <= it and
    every other p is above it (``inference.multiple_testing.correct``'s decisions).

    Holm stops at the first sorted p_(k+1) > alpha / (m - k): the cut is alpha / (m - k)
    (alpha when all m are rejected, alpha / m when none). Benjamini-Yekutieli rejects up to
    the largest k with p_(k) <= k alpha / (m c_m): the cut is max(k, 1) alpha / (m c_m).
    Bonferroni: alpha / m; none: alpha.
    """
    p = np.sort(np.asarray(p_values, float))
    m = p.size
    if m == 0 or correction == "none":
        return float(alpha)
    if correction == "bonferroni":
        return float(alpha) / m
    if correction == "holm":
        stop = np.flatnonzero(p > alpha / np.arange(m, 0, -1))
        k = int(stop[0]) if stop.size else m
        return float(alpha) / (m - k) if k < m else float(alpha)
    if correction == "by":
        c_m = float(np.sum(1.0 / np.arange(1, m + 1)))
        below = np.flatnonzero(p <= np.arange(1, m + 1) / m / c_m * alpha)
        k = int(below[-1]) + 1 if below.size else 0
        return max(k, 1) * float(alpha) / (m * c_m)
    raise ValueError(f"unknown correction {correction!r}")


def threshold_line(ax: plt.Axes, family: pd.DataFrame, part: pd.DataFrame) -> float:
    """Draw the correction's cut (``rejection_threshold`` over the whole ``family``: one
    method and bound kind, both sides) at -log10 of it, labelled with the correction, alpha
    and the rejections of this panel's ``part``; the y range then runs from 0 to above it,
    so a panel where every p is 1 still shows how far the cut is. Returns the cut."""
    correction = str(family["correction"].iloc[0]) if "correction" in family else "holm"
    alpha = float(family["alpha"].iloc[0]) if "alpha" in family else 0.05
    cut = rejection_threshold(family["p_value"].to_numpy(float), correction, alpha)
    y = -np.log10(cut)
    what = (f"{CORRECTION_NAMES.get(correction, correction)} threshold, alpha = {alpha:g}"
            if correction != "none" else f"threshold alpha = {alpha:g}, uncorrected")
    ax.axhline(y, ls="--", color=COLORS["rejected"], lw=1,
               label=f"{what}: {int(part['rejected'].sum())} of {len(part)} rejected")
    hi = max(ax.get_ylim()[1], 1.1 * y)
    ax.set_ylim(-0.03 * hi, hi)  # -log10 p >= 0: the axis starts at 0
    return cut


def apply_style() -> None:
    """One look for every figure: seaborn's theme STYLE, from its style file."""
    plt.style.use(STYLE_FILE)


def unit_label(feature: str) -> str:
    """'Glucose (mg/dL)' from the schema's units."""
    from twinfalsify.schema import FEATURE_BY_NAME

    f = FEATURE_BY_NAME.get(feature)
    if f is None or f.unit in ("", "0/1"):
        return feature
    return f"{feature} ({f.unit})"


def save_all(fig: plt.Figure, *paths: str | Path) -> None:
    """Save one figure to several files (PNG and PDF), then close it."""
    for p in paths:
        _savefig(fig, Path(p))
    plt.close(fig)


ORDINALS = ("1st", "2nd", "3rd", "4th")


def doses_in_brief(actions) -> str:
    """The dose sequence in words: per hour 'none' or the D0 dose quartiles given
    ('IV Q2 + vaso Q1'), repeats folded ('none x 3')."""
    words = []
    for a in actions:
        iv, vaso = int(a) // N_DOSE_BINS, int(a) % N_DOSE_BINS
        parts = ([f"IV Q{iv}"] if iv else []) + ([f"vaso Q{vaso}"] if vaso else [])
        words.append(" + ".join(parts) or "none")
    out: list[list] = []
    for w in words:
        if out and out[-1][0] == w:
            out[-1][1] += 1
        else:
            out.append([w, 1])
    return ", ".join(w if k == 1 else f"{w} x {k}" for w, k in out)


def patients_in_brief(outcome: str, bins) -> str:
    """The B-sets in words: 'every patient', or sex, age quartile and the outcome above (+)
    or at or below (-) the D0 median at hours 0..t."""
    if all(int(b) == WHOLE_SPACE for b in bins):
        return "every patient"
    sex, age_q, _ = subgroup_parts(bins[0])
    signs = "".join("+" if subgroup_parts(b)[2] else "-" for b in bins)
    return (f"{'female' if sex else 'male'}, {ORDINALS[age_q]} age quartile, {outcome} vs "
            f"D0 median at hours 0-{len(bins) - 1}: {signs}")


def describe_hypothesis(outcome: str, t: int, actions, bins) -> str:
    """Short text: outcome at t, the doses and the patients in words."""
    return (f"{outcome}, t = {t}; doses {doses_in_brief(actions)}; "
            f"{patients_in_brief(outcome, bins)}")


# -- item 4: longitudinal bounds ---------------------------------------------------------------


def longitudinal(frame: pd.DataFrame, title: str | None = None) -> plt.Figure:
    """Qhat_twin_t and [Qhat_lo, Qhat_up] with Hoeffding intervals over t, next to the naive mean.

    frame: summary.longitudinal_frame output (one row per prefix s = 1..t).
    """
    apply_style()
    f = frame.sort_values("t")
    t = f["t"].to_numpy(float)
    fig, ax = plt.subplots(figsize=(8.4, 4.2))
    # a band over one hour has no width: draw it as a box around that hour instead
    bx = np.array([t[0] - 0.3, t[0] + 0.3]) if len(t) == 1 else t

    def band(v: pd.Series) -> np.ndarray:
        return np.repeat(v.to_numpy(float), 2) if len(t) == 1 else v.to_numpy(float)

    ax.fill_between(bx, band(f["q_lo_hat"] - f["r_bound"]), band(f["q_up_hat"] + f["r_bound"]),
                    color=COLORS["bound"], alpha=0.12, lw=0,
                    label="bounds with Hoeffding intervals")  # fmt: skip
    ax.fill_between(bx, band(f["q_lo_hat"]), band(f["q_up_hat"]), color=COLORS["bound"],
                    alpha=0.3, lw=0, label=r"$[\hat Q_{lo}, \hat Q_{up}]$")  # fmt: skip
    ax.errorbar(t - 0.06, f["q_twin_hat"], yerr=f["r_twin"], fmt="o-", color=COLORS["twin"],
                capsize=3, label=r"twin $\hat Q_{twin}$")  # fmt: skip
    ax.errorbar(t + 0.06, f["q_obs_hat"], yerr=f["r_obs"], fmt="s--", color=COLORS["naive"],
                capsize=3, label="naive observational mean")  # fmt: skip
    if "twin_mean" in f and np.isfinite(f["twin_mean"].to_numpy(float)).any():
        # the size of the difference the clipping hides: the twin's unclipped mean
        ax.plot(t - 0.06, f["twin_mean"], "x", color=COLORS["twin"], ms=8,
                label="twin mean, unclipped")
    ax.set_xticks(t)
    # one short line each (four hours side by side must not run into each other)
    beyond = ([f"\ntwin < y_lo: {b:.0%}\ntwin > y_up: {a:.0%}" for b, a in
               zip(f["twin_below"], f["twin_above"], strict=True)]
              if "twin_below" in f else [""] * len(f))
    ax.set_xticklabels([f"{int(s)}\nn={n}, $\\hat n$={nh}{b}" for s, n, nh, b in
                        zip(f["t"], f["n"], f["nhat"], beyond, strict=True)],
                       fontsize=8)  # fmt: skip
    ax.set_xlabel("hour t (n: trajectories entering, $\\hat n$: twin runs entering; share of "
                  "the twin's outputs below y_lo, above y_up)", fontsize=9)
    outcome = f["outcome"].iloc[0]
    ax.set_ylabel(f"{unit_label(outcome)}\n(clipped to [y_lo, y_up]; x: unclipped)", fontsize=9)
    last = f.iloc[-1]
    default = describe_hypothesis(outcome, int(last["t"]), last["actions"], last["bins"])
    ax.set_title(title or default, fontsize=10)
    # right of the axes: inside, "best" still lands on an interval when the bands fill the panel
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    return fig


def longitudinal_title(twin: str, frame: pd.DataFrame, kind: str,
                       rejected_hours: dict[str, list[int]], correction: str = "holm") -> str:
    """Title of the bounds-over-time figure: the hypothesis, the intervals drawn (Hoeffding,
    as ``longitudinal`` draws them) and, per test method, the hours t whose own hypothesis
    that method rejected after ``correction``; methods with the same hours share a clause."""
    last = frame.iloc[-1]
    head = (f"twin {twin}: {last['outcome']} ({kind}), doses {doses_in_brief(last['actions'])}"
            f"\n{patients_in_brief(last['outcome'], last['bins'])}")  # fmt: skip
    groups: dict[tuple[int, ...], list[str]] = {}
    for method, hours in rejected_hours.items():
        groups.setdefault(tuple(sorted(hours)), []).append(method)
    clauses = [f"t = {', '.join(map(str, hours))} by {', '.join(ms)}"
               for hours, ms in sorted(groups.items(), key=lambda g: (len(g[0]), g[0]))
               if hours]  # fmt: skip
    state = (f"rejected ({correction}) at " + "; ".join(clauses)) if clauses else \
        "rejected by no method"
    return f"{head}\nHoeffding intervals drawn; {state}"


# -- item 5: outcome histograms ----------------------------------------------------------------


def outcome_histograms(cases: list[dict], twin: str | None = None,
                       methods: list[str] | None = None, alpha: float | None = None
                       ) -> plt.Figure:  # fmt: skip
    """Per case (summary.histogram_data): histogram of raw outcomes, observational followers vs
    twin runs, with the Hoeffding intervals of the bounds and of Q_twin drawn below.

    ``twin`` names the twin in the title; ``methods``: the test methods whose smallest p
    "min p" is (every method of the results); ``alpha``: the level of the intervals."""
    if not cases:
        raise ValueError("outcome_histograms: no case to draw")
    apply_style()
    fig, axes = plt.subplots(2, len(cases), figsize=(5.6 * len(cases), 5.2), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1]}, sharex="col")  # fmt: skip
    for j, c in enumerate(cases):
        ax, bx = axes[0, j], axes[1, j]
        vals = np.concatenate([c["obs"], c["twin"]])
        edges = np.histogram_bin_edges(vals, bins=30) if len(vals) else np.linspace(0, 1, 31)
        for key, lab, col in (("obs", "observational: A = a, X in B", COLORS["naive"]),
                              ("twin", "twin: $X^{twin}$ in B", COLORS["twin"])):  # fmt: skip
            v = c[key]
            if len(v):
                ax.hist(v, bins=edges, density=True, alpha=0.45, color=col,
                        label=f"{lab} ({len(v)})")  # fmt: skip
        for y in (c["y_lo"], c["y_up"]):
            ax.axvline(y, color="k", ls=":", lw=1)
        ax.set_ylabel("density")
        state = "rejected" if c["rejected"] else "not rejected"
        over = f" over {', '.join(methods)}" if methods else " over the methods"
        ax.set_title(f"{describe_hypothesis(c['outcome'], c['t'], c['actions'], c['bins'])}\n"
                     f"{state}; min p{over} = {c['p_min']:.2g}", fontsize=9)  # fmt: skip
        ax.legend(fontsize=7)
        lo, up = c["q_lo_hat"] - c["r_bound"], c["q_up_hat"] + c["r_bound"]
        bx.plot([lo, up], [1, 1], color=COLORS["bound"], lw=6, solid_capstyle="butt",
                label="$[Q_{lo}, Q_{up}]$ interval")  # fmt: skip
        bx.plot([c["q_lo_hat"], c["q_up_hat"]], [1, 1], "|", color="k", ms=12)
        bx.errorbar([c["q_twin_hat"]], [0], xerr=[[c["r_twin"]], [c["r_twin"]]], fmt="o",
                    color=COLORS["twin"], capsize=4, label="$Q_{twin}$ interval")  # fmt: skip
        bx.set_yticks([0, 1], ["$Q_{twin}$", "bounds"])
        bx.set_ylim(-0.7, 1.7)
        level = "1 - alpha/2" if alpha is None else f"{1 - alpha / 2:g}"
        bx.set_title(f"Hoeffding intervals (one-sided {level}, unadjusted)", fontsize=8)
        bx.set_xlabel(f"raw {unit_label(c['outcome'])} at t = {c['t']}")
    fig.suptitle(f"twin {twin}: outcomes of {len(cases)} hypotheses, data and twin"
                 if twin else f"outcomes of {len(cases)} hypotheses, data and twin")
    fig.tight_layout()
    return fig


# -- item 6: sample sizes ----------------------------------------------------------------------


def size_ticks(lo: float, hi: float) -> list[int]:
    """Round sizes (0, then 1, 2, 3, 5 x 10^k) between ``lo`` and ``hi``: at most 7, the
    2s and 5s dropped first (a narrow range: two sizes inside it), for a log10(size + 1)
    axis labelled with the sizes."""
    cands = [0] + [m * 10**k for k in range(7) for m in (1, 2, 3, 5)]
    inside = [c for c in cands if lo <= c <= hi]
    if len(inside) < 2:  # a narrow range: sizes inside it, with as few digits as will do
        for digits in range(2, 8):
            vals = {int(float(f"{v:.{digits}g}")) for v in np.linspace(max(lo, 0), hi, 5)[1:4]}
            vals = sorted(v for v in vals if lo <= v <= hi)
            if len(vals) >= 2:
                return vals
    for keep in ((1, 2, 3, 5), (1, 3), (1,)):
        pick = [c for c in inside if c == 0 or int(str(c)[0]) in keep]
        if len(pick) <= 7:
            break
    return pick


def sample_size_strips(results: pd.DataFrame, kind: str = "causal",
                       twin: str | None = None) -> plt.Figure:  # fmt: skip
    """n (test-set trajectories entering the bounds) and nhat (twin runs entering) of every
    parameter set (H_lo and H_up of a set share them): two panels, one row per outcome that
    has parameter sets, one point per set, coloured and offset by its hour t; x is
    log10(size + 1), labelled with the sizes, over the range of the data, so zeros show
    (untestable sets) and no panel is empty. ``twin`` names the twin in the title."""
    apply_style()
    sub = results[results["kind"] == kind].drop_duplicates("hyp_id")
    if sub.empty:
        sub = results.drop_duplicates("hyp_id")
        kind = "all"
    outs = [o for o in OUTCOMES if o in set(sub["outcome"])]
    outs += sorted(set(sub["outcome"]) - set(outs), key=str)
    hours = sorted(int(t) for t in pd.unique(sub["t"]))
    colours = dict(zip(hours, plt.get_cmap("viridis")(np.linspace(0.1, 0.85, len(hours))),
                       strict=True))  # fmt: skip
    width = 0.6 / max(1, len(hours))  # hours side by side within an outcome's row
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 0.32 * len(outs) + 1.6), sharey=True,
                             squeeze=False)  # fmt: skip
    row = {o: i for i, o in enumerate(outs)}
    for ax, col, what in zip(axes[0], ("n", "nhat"),
                             ("n: test-set trajectories entering the bounds",
                              r"$\hat n$: twin runs entering"), strict=True):  # fmt: skip
        x = np.log10(sub[col].to_numpy(float) + 1)
        for t in hours:
            at = (sub["t"] == t).to_numpy()
            y = np.array([row[o] for o in sub.loc[at, "outcome"]], float)
            y += (hours.index(t) - (len(hours) - 1) / 2) * width
            ax.scatter(x[at], y, s=9, color=colours[t], alpha=0.7, edgecolors="none",
                       label=f"t = {t}")  # fmt: skip
        lo, hi = float(x.min()), float(x.max())
        pad = max(0.05, 0.04 * (hi - lo))
        ax.set_xlim(max(-0.08, lo - pad), hi + pad)
        ticks = size_ticks(10 ** (lo - pad) - 1, 10 ** (hi + pad) - 1)
        ax.set_xticks(np.log10(np.asarray(ticks, float) + 1), [f"{v:,}" for v in ticks])
        ax.set_xlabel(f"{what} (log scale of size + 1)")
        zeros = int((sub[col] == 0).sum())
        ax.set_title(f"{what.split(':')[0]}: median {int(sub[col].median()):,}, "
                     f"{zeros} of {len(sub)} sets at 0", fontsize=9)  # fmt: skip
    ax0 = axes[0, 0]
    ax0.set_yticks(range(len(outs)), outs)
    ax0.set_ylim(len(outs) - 0.5, -0.5)  # the first outcome on top
    ax0.set_ylabel("outcome")
    handles, labels = ax0.get_legend_handles_labels()
    head = f"twin {twin}: " if twin else ""
    fig.suptitle(f"{head}sample sizes of the {len(sub)} {kind} parameter sets", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1 - 0.9 / fig.get_size_inches()[0], 1))
    fig.legend(handles, labels, loc="center right", fontsize=8, frameon=False,
               title="hour", title_fontsize=8, markerscale=1.6)  # fmt: skip
    return fig


# -- item 7: propensity vs n -------------------------------------------------------------------


def propensity_scatter(results: pd.DataFrame, twin: str | None = None) -> plt.Figure:
    """P(A_1:t = a_1:t | X_0:N in B_0:N) against n, one point per parameter set, coloured by
    rejection (of H_lo or H_up), one panel per (method, kind) that has a parameter set with
    n > 0: a row per method, a column per bound kind, each column's n axis over its own data
    (Manski sets have all of D, causal ones a subgroup). Low propensity = wide bounds = hard
    to reject. ``twin`` names the twin in the title."""
    apply_style()
    drawn = results[results["n"] > 0]
    methods = [m for m in pd.unique(results["method"]) if (drawn["method"] == m).any()]
    kinds = [k for k in ("causal", "manski") if (drawn["kind"] == k).any()]
    kinds += sorted(set(drawn["kind"]) - set(kinds))
    if not methods:  # nothing to draw: one panel saying so
        methods, kinds = list(pd.unique(results["method"]))[:1] or ["-"], ["causal"]
    span = {}  # per kind: the range of n drawn
    for k in kinds:
        n_k = drawn.loc[drawn["kind"] == k, "n"].to_numpy(float)
        span[k] = (float(n_k.min()), float(n_k.max())) if n_k.size else (1.0, 10.0)
    # a kind whose sets all have one n (Manski: all of D) gets a narrow column, a strip
    narrow = {k: span[k][1] <= 1.02 * span[k][0] for k in kinds}
    ratios = [0.45 if narrow[k] else 1.0 for k in kinds]
    size = (5.2 * sum(ratios) + 0.4, 3.8 * len(methods))
    fig, axes = plt.subplots(len(methods), len(kinds), figsize=size, squeeze=False,
                             sharex="col", sharey=True,
                             gridspec_kw={"width_ratios": ratios})  # fmt: skip
    for j, k in enumerate(kinds):
        lo, hi = span[k]
        for i, m in enumerate(methods):
            ax = axes[i, j]
            part = results[(results["method"] == m) & (results["kind"] == k)]
            per = part.groupby("hyp_id").agg(n=("n", "first"), p=("propensity", "first"),
                                             rej=("rejected", "any"))  # fmt: skip
            per = per[per["n"] > 0]
            for rej, col, lab in ((False, COLORS["kept"], "not rejected"),
                                  (True, COLORS["rejected"], "rejected, either side")):  # fmt: skip
                q = per[per["rej"] == rej]
                ax.scatter(q["n"], q["p"], s=10 if not rej else 18, alpha=0.6, color=col,
                           label=lab, edgecolors="none")  # fmt: skip
            ax.set_xscale("log")
            ax.set_ylim(-0.02, 1.02)
            ax.set_title(f"{m}, {k}:{chr(10) if narrow[k] else ' '}{int(per['rej'].sum())} of "
                         f"{len(per)} parameter sets rejected", fontsize=10)  # fmt: skip
            ax.set_xlabel("n (test-set trajectories\nentering)" if narrow[k]
                          else "n (test-set trajectories entering)")  # fmt: skip
            if j == 0:  # the panels share the y axis
                ax.set_ylabel("$P(A_{1:t} = a_{1:t} | X_{0:N} \\in B_{0:N})$")
        # the column's n range, a little wider (a log axis around one value if all share n)
        pad = max(1.08, (hi / lo) ** 0.05)
        axes[0, j].set_xlim(lo / pad, hi * pad)
        ticks = [int(lo)] if narrow[k] else size_ticks(lo / pad, hi * pad)
        axes[0, j].set_xticks(ticks, [f"{v:,}" for v in ticks])
        axes[0, j].xaxis.set_minor_locator(plt.NullLocator())
    # one legend for every panel, above them: no panel's points can sit under it
    handles, labels = axes[0, 0].get_legend_handles_labels()
    head = f"twin {twin}: " if twin else ""
    fig.suptitle(f"{head}propensity of the action sequence against n, per parameter set "
                 "(n = 0 not shown)", fontsize=11, y=1 - 0.05 / size[1], va="top")
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.42 / size[1]))
    fig.legend(handles, labels, loc="upper center", ncol=2, fontsize=8, frameon=False,
               markerscale=1.5, bbox_to_anchor=(0.5, 1 - 0.26 / size[1]))  # fmt: skip
    return fig


# -- item 8: sensitivity -----------------------------------------------------------------------


def sensitivity_lines(sweep: pd.DataFrame, twin: str | None = None) -> plt.Figure:
    """Rejections against Delta (widening of [y_lo, y_up]) as small multiples: a first panel
    with the totals over outcomes, then one panel per outcome (its own y scale), each with one
    line per (method: colour, kind: line style). sweep columns: delta, method, group,
    n_hypotheses, n_rejected, kind. ``twin`` names the twin in the title."""
    need = {"delta", "method", "group", "n_hypotheses", "n_rejected"}
    if need - set(sweep.columns):
        raise ValueError(f"sensitivity_lines: missing columns {sorted(need - set(sweep.columns))}")
    apply_style()
    sweep = sweep if "kind" in sweep else sweep.assign(kind="causal")
    methods = list(pd.unique(sweep["method"]))
    groups = [g for g in OUTCOMES if g in set(sweep["group"])]
    groups += sorted(set(sweep["group"]) - set(groups), key=str)
    panels = ["all outcomes", *groups]
    ncol = min(4, len(panels))
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.9 * ncol + 1.8, 2.3 * nrow + 0.7),
                             squeeze=False, sharex=True)  # fmt: skip
    # methods by colour (a qualitative palette: at most a few, all far apart), kinds by style
    colours = dict(zip(methods, plt.get_cmap("tab10").colors, strict=False))
    styles = {"causal": "-", "manski": "--"}
    kinds = [k for k in styles if k in set(sweep["kind"])]
    kinds += sorted(set(sweep["kind"]) - set(kinds))
    for ax, panel in zip(axes.flat, panels, strict=False):
        sub = sweep if panel == "all outcomes" else sweep[sweep["group"] == panel]
        top = 1.0
        for (m, k), part in sub.groupby(["method", "kind"], sort=False):
            tot = part.groupby("delta")["n_rejected"].sum()
            top = max(top, float(tot.max()))
            ax.plot(tot.index, tot.to_numpy(), color=colours[m], ls=styles.get(k, ":"),
                    marker="o", ms=3, lw=1.4 if panel == "all outcomes" else 1.1)  # fmt: skip
        ax.set_title(panel, fontsize=9, fontweight="bold" if panel == "all outcomes" else None)
        ax.tick_params(labelsize=7)
        # counts: integer ticks from 0; a panel without rejections still spans 0..1
        ax.set_ylim(-0.04 * top * 1.08, top * 1.08)
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("rejected hypotheses", fontsize=8)
    for ax in axes[-1, :]:
        ax.set_xlabel(r"$\Delta$", fontsize=9)
    handles = [Line2D([], [], color=colours[m], ls=styles.get(k, ":"), marker="o", ms=3,
                      label=f"{m}, {k}") for m in methods for k in kinds]  # fmt: skip
    head = f"twin {twin}: " if twin else ""
    fig.suptitle(f"{head}rejected hypotheses as the bounds widen to "
                 r"$[y_{lo}(1 - \Delta/2),\ y_{up}(1 + \Delta/2)]$", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1 - 1.7 / fig.get_size_inches()[0], 1))
    fig.legend(handles=handles, loc="center right", fontsize=8, frameon=False,
               title="method, bounds", title_fontsize=8)  # fmt: skip
    return fig


# -- item 9: confounding -----------------------------------------------------------------------


def confounding(frame: pd.DataFrame, outcome: str, show_action: int | None = None,
                labels: dict[int, str] | None = None) -> plt.Figure:  # fmt: skip
    """Left: outcome distribution among those who took one action vs everyone under it.
    Right: per action, mean observed among takers vs mean if everyone took it.
    frame: summary.confounding_frame output."""
    apply_style()
    labels = labels or {}
    obs = frame[frame["which"] == "observed"]
    counts = obs.groupby("action").size()
    if show_action is None:  # the most common non-zero action shows the bias best
        nz = counts.drop(index=0, errors="ignore")
        show_action = int((nz if len(nz) else counts).idxmax())
    elif show_action not in counts.index:
        raise ValueError(
            f"figures.confounding.action: action {show_action} was never taken at hour 1 "
            f"(taken: {sorted(int(a) for a in counts.index)})"
        )
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [1, 1.4]})
    sel = frame[frame["action"] == show_action]
    edges = np.histogram_bin_edges(sel["value"], bins=30)
    for which, col, lab in (("observed", COLORS["naive"], "observed among those treated"),
                            ("everyone", COLORS["bound"], "if everyone were treated")):  # fmt: skip
        v = sel.loc[sel["which"] == which, "value"]
        ax.hist(v, bins=edges, density=True, alpha=0.5, color=col, label=f"{lab} ({len(v)})")
        ax.axvline(v.mean(), color=col, lw=2)
    ax.set_xlabel(f"{unit_label(outcome)} at hour 1")
    ax.set_ylabel("density")
    ax.set_title(f"action {labels.get(show_action, show_action)} at hour 1", fontsize=10)
    ax.legend(fontsize=7)
    keep = counts[counts >= 20].index
    means = frame[frame["action"].isin(keep)].groupby(["action", "which"])["value"].mean().unstack()
    x = np.arange(len(means))
    bx.scatter(x, means["observed"], color=COLORS["naive"], label="mean among those treated")
    bx.scatter(x, means["everyone"], color=COLORS["bound"], marker="D",
               label="mean if everyone were treated")  # fmt: skip
    bx.vlines(x, means["observed"], means["everyone"], color="k", lw=0.8)
    bx.set_xticks(x, [str(labels.get(int(a), a)) for a in means.index], rotation=60, fontsize=7)
    bx.set_xlabel("action at hour 1 (IV bin, vasopressor bin); actions taken >= 20 times")
    bx.set_ylabel(f"mean {unit_label(outcome)} at hour 1")
    bx.legend(fontsize=7)
    fig.tight_layout()
    return fig


def pvalue_boxen_methods(
    results: pd.DataFrame, kind: str = "causal", title: str | None = None
) -> plt.Figure:
    """pvalue_boxen for every method in the results, one row of (H_lo, H_up) panels each."""
    methods = list(pd.unique(results["method"]))
    if not methods:
        raise ValueError("pvalue_boxen_methods: results have no rows")
    import seaborn as sns

    apply_style()
    order = [o for o in OUTCOMES if o in set(results["outcome"])]
    fig, axes = plt.subplots(len(methods), 2, figsize=(11, 4.2 * len(methods)), squeeze=False,
                             sharey="row")  # fmt: skip
    for i, method in enumerate(methods):
        sub = results[(results["method"] == method) & (results["kind"] == kind)].copy()
        sub["neg_log10_p"] = -np.log10(np.clip(sub["p_value"].to_numpy(float), 1e-300, 1.0))
        for ax, side in zip(axes[i], ("lo", "up"), strict=True):
            part = sub[sub["side"] == side]
            if len(part):
                sns.boxenplot(data=part, x="outcome", y="neg_log10_p", order=order, ax=ax,
                              color=COLORS["bound"], k_depth="trustworthy")  # fmt: skip
                threshold_line(ax, sub, part)
                mark_floor(ax, part)
                legend_with_headroom(ax)
            ax.set_xlabel("outcome" if i == len(methods) - 1 else "")
            # one y label per row (the row's panels share the axis): the side is in the title
            ax.set_ylabel("$-\\log_{10}$ p (dimensionless)")
            ax.set_title(f"{method}: $H_{{{side}}}$, p-values $p_{{{side}}}$", fontsize=10)
            ax.tick_params(axis="x", rotation=60)
    fig.suptitle(title or f"p-values, {kind} hypotheses")
    fig.tight_layout()
    return fig
