"""Design stage on D0: action bins, B-sets and the hypothesis parameters.

Paper's case-study choices (docs/explanation/method.md):
* actions: per dose, bin 0 = zero dose, bins 1-4 = quartiles of the non-zero
  hourly doses in D0; action code a = 5 * iv_bin + vaso_bin (25 actions). The
  twin receives the median D0 dose of each bin.
* B_t: 16 bins = sex (2) x age quartile in D0 (4) x outcome at t above/below
  its D0 median at t (2); code = 8 sex + 2 age_quartile + above.
* hypotheses: every (t, a_1:t, B_0:t) followed by at least one D0 trajectory,
  y_lo, y_up = 0.2 / 0.8 quantiles of the outcome at t in that D0 subset
  (kind causal); Manski: B_0:t = whole space, one per (outcome, t, a_1:t).
  Parameter sets whose D0 subset gives y_up <= y_lo (e.g. one trajectory) have
  no range to test and are dropped (counted in the design report).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from twinfalsify.schema import (
    FEATURES,
    IV_FLUID,
    OUTCOMES,
    STAY_ID,
    T_MAX,
    TIME,
    VASOPRESSOR,
    WHOLE_SPACE,
    ContractError,
    to_array,
)

log = logging.getLogger("twinfalsify")

N_DOSE_BINS = 5


@dataclass(frozen=True)
class ActionBins:
    """Per dose: inner edges (q25, q50, q75 of non-zero D0 doses) and the median of each bin."""

    iv_edges: tuple[float, float, float]
    vaso_edges: tuple[float, float, float]
    iv_medians: tuple[float, ...]  # 5 values, bin 0 = 0
    vaso_medians: tuple[float, ...]

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> ActionBins:
        return cls(**{k: tuple(v) for k, v in data.items()})

    def doses(self, actions: np.ndarray) -> np.ndarray:
        """Action codes (..., t) -> doses (..., t, 2): [IV mL/h, vasopressor ug/kg/min]."""
        a = np.asarray(actions, dtype=np.int64)
        iv = np.asarray(self.iv_medians)[a // N_DOSE_BINS]
        vaso = np.asarray(self.vaso_medians)[a % N_DOSE_BINS]
        return np.stack([iv, vaso], axis=-1)


def _dose_bins(dose: np.ndarray, edges: tuple[float, float, float]) -> np.ndarray:
    """0 for zero dose; 1..4 by the inner edges (right-closed: (0, q25], (q25, q50], ...)."""
    bins = 1 + np.searchsorted(np.asarray(edges), dose, side="left")
    return np.where(dose > 0, bins, 0)


def fit_action_bins(d0: pd.DataFrame, t_max: int = T_MAX, min_nonzero: int = 0) -> ActionBins:
    """Quartile bins of non-zero D0 doses over the hours whose action is used (t < t_max).

    With fewer than 8 non-zero doses the quartiles are crude (a small cohort such as the
    MIMIC-III demo): a warning is logged and the bins are formed anyway. With none, every
    non-zero dose falls in bin 4 (edges 0) with a twin dose of 0: no D0 trajectory takes such
    an action, so no hypothesis uses it. Fewer than ``min_nonzero`` (> 0) is an error.
    """
    used = d0[d0[TIME] < t_max]
    parts = {}
    for dose in (IV_FLUID, VASOPRESSOR):
        nz = used.loc[used[dose] > 0, dose].to_numpy(float)
        if len(nz) < min_nonzero:
            raise ContractError(
                f"design: D0 has {len(nz)} non-zero {dose} dose(s), fewer than the "
                f"{min_nonzero} needed to form its quartile bins; enlarge split.d0_fraction"
            )
        if len(nz) == 0:
            log.warning("design: no non-zero %s dose in D0: non-zero doses form one bin (4) "
                        "that no hypothesis uses", dose)
            parts[dose] = ((0.0, 0.0, 0.0), (0.0,) * N_DOSE_BINS)
            continue
        if len(nz) < 8:
            log.warning("design: only %d non-zero %s doses in D0: quartile bins are crude",
                        len(nz), dose)
        edges = tuple(float(q) for q in np.quantile(nz, [0.25, 0.5, 0.75]))
        b = _dose_bins(nz, edges)  # type: ignore[arg-type]
        medians = [0.0] + [
            float(np.median(nz[b == k])) if np.any(b == k) else edges[min(k, 3) - 1]
            for k in range(1, N_DOSE_BINS)
        ]
        parts[dose] = (edges, tuple(medians))
    return ActionBins(
        iv_edges=parts[IV_FLUID][0],
        vaso_edges=parts[VASOPRESSOR][0],
        iv_medians=parts[IV_FLUID][1],
        vaso_medians=parts[VASOPRESSOR][1],
    )


def action_codes(traj: pd.DataFrame, bins: ActionBins, t_max: int = T_MAX) -> np.ndarray:
    """(n_stays, t_max) action codes: entry s is A_{s+1}, the action of hour s -> s+1."""
    iv = _dose_bins(traj[IV_FLUID].to_numpy(float), bins.iv_edges)
    vaso = _dose_bins(traj[VASOPRESSOR].to_numpy(float), bins.vaso_edges)
    a = (N_DOSE_BINS * iv + vaso).reshape(-1, t_max + 1)
    return a[:, :t_max]


@dataclass(frozen=True)
class StateBins:
    """B-set definition: age quartile edges (D0, t = 0) and per-outcome medians at each t."""

    age_edges: tuple[float, float, float]
    medians: dict[str, tuple[float, ...]]  # outcome -> median at t = 0..T

    def to_json(self) -> dict:
        return {
            "age_edges": list(self.age_edges),
            "medians": {k: list(v) for k, v in self.medians.items()},
        }

    @classmethod
    def from_json(cls, data: dict) -> StateBins:
        return cls(tuple(data["age_edges"]), {k: tuple(v) for k, v in data["medians"].items()})

    def base_codes(self, x0: np.ndarray) -> np.ndarray:
        """8 sex + 2 age_quartile for rows of X_0 (..., len(FEATURES))."""
        sex = x0[..., FEATURES.index("sex")].astype(np.int64)
        age_q = np.searchsorted(
            np.asarray(self.age_edges), x0[..., FEATURES.index("age")], side="right"
        )
        return 8 * sex + 2 * age_q

    def above(self, outcome: str, values: np.ndarray, t: np.ndarray | int) -> np.ndarray:
        """1 where the outcome value at hour t is above the D0 median at t."""
        med = np.asarray(self.medians[outcome])[t]
        return (values > med).astype(np.int64)


def fit_state_bins(d0: pd.DataFrame, outcomes=OUTCOMES, t_max: int = T_MAX) -> StateBins:
    x = to_array(d0, FEATURES, t_max)
    age = x[:, 0, FEATURES.index("age")]
    edges = tuple(float(q) for q in np.quantile(age, [0.25, 0.5, 0.75]))
    medians = {
        k: tuple(float(m) for m in np.median(x[:, :, FEATURES.index(k)], axis=0)) for k in outcomes
    }
    return StateBins(edges, medians)  # type: ignore[arg-type]


def subgroup_parts(code: int) -> tuple[int, int, int]:
    """(sex, age quartile 0-3, outcome above its D0 median 0/1) of a B code, the inverse of
    ``8 sex + 2 age_quartile + above`` (:meth:`StateBins.base_codes`, :func:`state_codes`);
    not defined for ``WHOLE_SPACE``."""
    code = int(code)
    return code // 8, (code % 8) // 2, code % 2


def state_codes(x: np.ndarray, bins: StateBins, outcome: str) -> np.ndarray:
    """B codes (n, t_max + 1) of trajectories x (n, t_max + 1, F) for one outcome."""
    base = bins.base_codes(x[:, 0, :])
    t = np.arange(x.shape[1])
    return base[:, None] + bins.above(outcome, x[:, :, FEATURES.index(outcome)], t)


def _key(arr: np.ndarray) -> np.ndarray:
    """Rows of small non-negative ints -> one string key per row."""
    return np.array(["-".join(map(str, r)) for r in arr.tolist()], dtype=object)


def build_hypotheses(
    d0: pd.DataFrame,
    actions: ActionBins,
    states: StateBins,
    *,
    outcomes=OUTCOMES,
    quantiles: tuple[float, float] = (0.2, 0.8),
    min_support: int = 1,
    kinds: tuple[str, ...] = ("causal", "manski"),
    t_max: int = T_MAX,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Hypothesis parameter sets from D0, and a report of how many were kept/dropped.

    Returns (hypotheses, report). hypotheses: hyp_id, kind, outcome, t, actions
    (list of t codes), bins (list of t + 1 codes, -1 = whole space), y_lo, y_up,
    support (D0 trajectories in the subset).
    """
    x = to_array(d0, FEATURES, t_max)
    a = action_codes(d0, actions, t_max)
    rows, report = [], []
    for outcome in outcomes:
        b = state_codes(x, states, outcome)
        y = x[:, :, FEATURES.index(outcome)]
        for t in range(1, t_max + 1):
            akey = _key(a[:, :t])
            for kind in kinds:
                if kind == "causal":
                    key = akey + "|" + _key(b[:, : t + 1])
                elif kind == "manski":
                    key = akey
                else:
                    raise ContractError(f"design.kinds: unknown kind {kind!r} (causal | manski)")
                frame = pd.DataFrame({"key": key, "y": y[:, t], "i": np.arange(len(y))})
                g = frame.groupby("key", sort=True)
                stats = g["y"].quantile(quantiles[0]).rename("y_lo").to_frame()
                stats["y_up"] = g["y"].quantile(quantiles[1])
                stats["support"] = g["y"].size()
                stats["first"] = g["i"].first()
                keep = (stats["support"] >= min_support) & (stats["y_up"] > stats["y_lo"])
                report.append(
                    {
                        "outcome": outcome,
                        "t": t,
                        "kind": kind,
                        "parameter_sets": len(stats),
                        "kept": int(keep.sum()),
                        "dropped_low_support": int((stats["support"] < min_support).sum()),
                        "dropped_degenerate": int(
                            (
                                (stats["support"] >= min_support) & (stats["y_up"] <= stats["y_lo"])
                            ).sum()
                        ),
                    }
                )
                for _, r in stats[keep].iterrows():
                    i = int(r["first"])
                    rows.append({
                        "kind": kind, "outcome": outcome, "t": t,
                        "actions": [int(v) for v in a[i, :t]],
                        "bins": ([int(v) for v in b[i, : t + 1]] if kind == "causal"
                                 else [WHOLE_SPACE] * (t + 1)),
                        "y_lo": float(r["y_lo"]), "y_up": float(r["y_up"]),
                        "support": int(r["support"]),
                    })  # fmt: skip
    hyps = pd.DataFrame(rows)
    if hyps.empty:
        raise ContractError(
            "design: no hypothesis could be formed on D0 (every parameter set had y_up <= y_lo "
            "or too little support); enlarge split.d0_fraction or lower design.min_support"
        )
    order = {k: i for i, k in enumerate(outcomes)}
    hyps["_o"] = hyps["outcome"].map(order)
    hyps["_k"] = hyps["kind"].map({"causal": 0, "manski": 1})
    hyps["_a"] = hyps["actions"].map(lambda v: "-".join(f"{c:02d}" for c in v))
    hyps["_b"] = hyps["bins"].map(lambda v: "-".join(f"{c:02d}" for c in v))
    hyps = hyps.sort_values(["_k", "_o", "t", "_a", "_b"], kind="stable").drop(
        columns=["_o", "_k", "_a", "_b"]
    )
    hyps.insert(0, "hyp_id", np.arange(len(hyps), dtype=np.int64))
    return hyps.reset_index(drop=True), pd.DataFrame(report)


def restrict_hypotheses(
    hyps: pd.DataFrame,
    report: pd.DataFrame,
    *,
    horizon: int | None = None,
    sequences: list[list[int]] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Keep the hypotheses with t <= ``horizon`` whose a_1:t is a prefix of one of
    ``sequences`` (action codes): a study sized to a twin budget (every kept hypothesis is
    unchanged; only which ones are tested changes, fixed before any twin run). hyp_id is
    renumbered; the report gains ``dropped_outside_design`` and ``kept`` is updated."""
    if horizon is None and not sequences:
        return hyps, report
    keep = np.ones(len(hyps), dtype=bool)
    if horizon is not None:
        keep &= hyps["t"].to_numpy() <= horizon
    if sequences:
        allowed = {tuple(seq[:k]) for seq in sequences for k in range(1, len(seq) + 1)}
        keep &= np.array([tuple(a) in allowed for a in hyps["actions"]], dtype=bool)
    out = hyps[keep].drop(columns="hyp_id").reset_index(drop=True)
    if out.empty:
        raise ContractError(
            f"design: no hypothesis left with horizon {horizon} and sequences {sequences} "
            "(each sequence lists action codes 0..24 = 5 x IV bin + vasopressor bin; see "
            "tables/action_space.csv for those seen in D0)"
        )
    out.insert(0, "hyp_id", np.arange(len(out), dtype=np.int64))
    kept = out.groupby(["outcome", "t", "kind"]).size()
    rep = report.copy()
    idx = pd.MultiIndex.from_frame(rep[["outcome", "t", "kind"]])
    new_kept = kept.reindex(idx, fill_value=0).to_numpy()
    rep["dropped_outside_design"] = rep["kept"].to_numpy() - new_kept
    rep["kept"] = new_kept
    return out, rep


def design_on_d0(
    d0: pd.DataFrame,
    *,
    outcomes=OUTCOMES,
    quantiles: tuple[float, float] = (0.2, 0.8),
    min_support: int = 10,
    kinds: tuple[str, ...] = ("causal", "manski"),
    t_max: int = T_MAX,
    horizon: int | None = None,
    sequences: list[list[int]] | None = None,
) -> tuple[ActionBins, StateBins, pd.DataFrame, pd.DataFrame]:
    """Every data-dependent choice, made on D0 only (sample splitting): action bins, B-sets,
    and the hypotheses with their kept/dropped report (optionally restricted to a horizon and
    to given action sequences: ``restrict_hypotheses``)."""
    actions = fit_action_bins(d0, t_max)
    states = fit_state_bins(d0, outcomes, t_max)
    hyps, report = build_hypotheses(
        d0, actions, states, outcomes=outcomes, quantiles=quantiles, min_support=min_support,
        kinds=kinds, t_max=t_max,
    )  # fmt: skip
    hyps, report = restrict_hypotheses(hyps, report, horizon=horizon, sequences=sequences)
    return actions, states, hyps, report


def padded(hyps: pd.DataFrame, column: str, width: int, fill: int = -2) -> np.ndarray:
    """List column -> (H, width) int array padded with ``fill``."""
    out = np.full((len(hyps), width), fill, dtype=np.int64)
    for i, v in enumerate(hyps[column].tolist()):
        out[i, : len(v)] = v
    return out


def action_space_table(traj: pd.DataFrame, bins: ActionBins, t_max: int = T_MAX) -> pd.DataFrame:
    """Paper's Table 4: the 25 actions, their dose ranges, twin doses and frequency in ``traj``."""
    codes = action_codes(traj, bins, t_max).ravel()
    counts = np.bincount(codes, minlength=N_DOSE_BINS**2)

    def rng(edges, k):
        lo = 0.0 if k <= 1 else edges[k - 2]
        return "0" if k == 0 else (f"> {lo:.4g}" if k == 4 else f"({lo:.4g}, {edges[k - 1]:.4g}]")

    rows = []
    for a in range(N_DOSE_BINS**2):
        i, v = divmod(a, N_DOSE_BINS)
        rows.append({
            "action": a, "iv_bin": i, "vaso_bin": v,
            "iv_range_ml_h": rng(bins.iv_edges, i), "vaso_range_ug_kg_min": rng(bins.vaso_edges, v),
            "iv_twin_dose_ml_h": bins.iv_medians[i],
            "vaso_twin_dose_ug_kg_min": bins.vaso_medians[v],
            "n_hours": int(counts[a]), "share": counts[a] / max(1, counts.sum()),
        })  # fmt: skip
    return pd.DataFrame(rows)


__all__ = [
    "ActionBins",
    "StateBins",
    "WHOLE_SPACE",
    "action_codes",
    "action_space_table",
    "build_hypotheses",
    "design_on_d0",
    "fit_action_bins",
    "fit_state_bins",
    "padded",
    "state_codes",
    "STAY_ID",
]
