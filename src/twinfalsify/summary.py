"""Data behind the figures and the study summary, recomputed from a study's results folder.

Everything here reads the files a study has written (results/<study>/...) and calls the
library (design, bounds, inference) rather than reimplementing it, so a figure shows exactly
what the tests stage tested.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify import bounds
from twinfalsify.design import WHOLE_SPACE, ActionBins, StateBins, action_codes, state_codes
from twinfalsify.inference.hoeffding import hoeffding_radius
from twinfalsify.inference.order import content_keys, tied_share
from twinfalsify.inference.samples import HypothesisSamples
from twinfalsify.io import read_json, read_parquet
from twinfalsify.provenance import software_versions
from twinfalsify.schema import FEATURE_BY_NAME, FEATURES, T_MAX, ContractError, TwinNodes, to_array
from twinfalsify.stored_runs import WORKER_STATS, failing_patients, restart_warning
from twinfalsify.tables import markdown_table
from twinfalsify.twin_tests import STORED_INPUTS, load_twin_tests, outcome_sizes, twin_samples


@dataclass(frozen=True)
class StudyTwin:
    """One twin of one study: its test inputs (``twin_tests.load_twin_tests``, the tests
    rule's own path) and what the figures add to them."""

    hyps: pd.DataFrame
    samples: HypothesisSamples
    n_failed: np.ndarray
    results: pd.DataFrame
    d0: pd.DataFrame
    d: pd.DataFrame
    actions: ActionBins
    states: StateBins
    nodes: TwinNodes
    run_status: Mapping[str, int] = None  # twin node-runs per status (runs.parquet)


STUDY_TWIN_INPUTS = (*STORED_INPUTS, "d0", "actions", "results")


def load_study_twin(paths: Mapping[str, str | Path]) -> StudyTwin:
    """One twin's test inputs (:func:`twin_tests.load_twin_tests`: the samples the tests rule
    tested, failed runs at their places) with D0, the action bins and the results table.

    paths: keys ``STUDY_TWIN_INPUTS``.
    """
    missing = set(STUDY_TWIN_INPUTS) - set(paths)
    if missing:
        raise ContractError(f"load_study_twin: missing input path(s) {sorted(missing)}")
    tt = load_twin_tests(paths)
    return StudyTwin(
        hyps=tt.hyps, samples=tt.samples, n_failed=tt.n_failed,
        results=read_parquet(paths["results"], "results"),
        d0=read_parquet(paths["d0"], "D0"), d=tt.d,
        actions=ActionBins.from_json(read_json(paths["actions"])),
        states=tt.states, nodes=tt.nodes, run_status=tt.run_status,
    )  # fmt: skip


# -- choosing what to show -------------------------------------------------------------------


def rejected_any(results: pd.DataFrame, method: str | None = None) -> pd.DataFrame:
    """Per hypothesis: min p over sides (and methods, or the given one), rejected on any side."""
    sub = results if method is None else results[results["method"] == method]
    if sub.empty:
        raise ContractError(f"results: no rows for method {method!r}")
    return (
        sub.groupby("hyp_id")
        .agg(
            p_min=("p_value", "min"),
            rejected=("rejected", "any"),
            t=("t", "first"),
            kind=("kind", "first"),
            outcome=("outcome", "first"),
            n=("n", "first"),
            nhat=("nhat", "first"),
        )  # fmt: skip
        .reset_index()
    )


def pick_hypothesis(
    results: pd.DataFrame,
    *,
    rejected: bool = True,
    kind: str = "causal",
    outcome: str | None = None,
    prefer_long: bool = True,
    exclude: tuple[int, ...] = (),
    run_status: Mapping[str, int] | None = None,
) -> int:
    """hyp_id to illustrate: a rejected (or a clearly non-rejected, testable) hypothesis.

    Rejected: the longest horizon t first (``prefer_long``), then the smallest p-value.
    Not rejected: among testable ones (n > 0, nhat > 0), the largest p-value and sample
    sizes, so the picture shows a twin inside its bounds with data behind it. Search order:
    the wanted state in ``kind``, then in any kind, then the other state (a correct twin has
    no rejection): the figure reads the hypothesis's own rejection to title it honestly.
    run_status: the twin's node-runs per status (``StudyTwin.run_status``), so that "no
    testable hypothesis" can say when the cause is that no twin run succeeded.
    """
    per = rejected_any(results)
    per = per[~per["hyp_id"].isin(list(exclude))]
    if outcome is not None:
        if outcome not in set(per["outcome"]):
            raise ContractError(f"figures: outcome {outcome!r} has no hypothesis in the results")
        per = per[per["outcome"] == outcome]
    testable = per[(per["n"] > 0) & (per["nhat"] > 0)]
    if testable.empty:
        cause = ""
        if run_status and not run_status.get("ok"):
            counts = ", ".join(f"{k} {v}" for k, v in sorted(run_status.items()))
            cause = (f": no twin run succeeded (node-runs by status: {counts}; "
                     "see the twin's run_summary.json)")
        raise ContractError(
            f"figures: no testable hypothesis (every one has n = 0 or nhat = 0){cause}")
    in_kind = testable[testable["kind"] == kind]
    for pool in (in_kind[in_kind["rejected"] == rejected],
                 testable[testable["rejected"] == rejected], in_kind, testable):  # fmt: skip
        if len(pool):
            want = pool
            break
    if rejected:
        keys = (["t"] if prefer_long else []) + ["p_min", "n"]
        asc = ([False] if prefer_long else []) + [True, False]
    else:
        want = want.assign(size=np.minimum(want["n"], want["nhat"]))
        keys, asc = ["p_min", "t", "size"], [False, False, False]
    return int(want.sort_values(keys + ["hyp_id"], ascending=asc + [True]).iloc[0]["hyp_id"])


def extend_to_horizon(results: pd.DataFrame, hyps: pd.DataFrame, hyp_id: int) -> int:
    """The hypothesis of the longest horizon whose (a, B) prefix is hyp_id's, same outcome and
    kind (smallest p-value among those), so a longitudinal figure of a rejection at t < T still
    spans t = 1..T and passes through the rejected step; hyp_id itself if none is longer."""
    row = hyps.loc[hyps["hyp_id"] == hyp_id]
    if row.empty:
        raise ContractError(f"figures: hyp_id {hyp_id} is not in the hypotheses table")
    row = row.iloc[0]
    t = int(row["t"])
    a, b = [int(v) for v in row["actions"]], [int(v) for v in row["bins"]]
    cand = hyps[(hyps["outcome"] == row["outcome"]) & (hyps["kind"] == row["kind"])
                & (hyps["t"] > t)]  # fmt: skip
    ok = [
        int(h) for h, aa, bb in zip(cand["hyp_id"], cand["actions"], cand["bins"], strict=True)
        if [int(v) for v in aa[:t]] == a and [int(v) for v in bb[: t + 1]] == b
    ]  # fmt: skip
    if not ok:
        return int(hyp_id)
    per = rejected_any(results[results["hyp_id"].isin(ok)])
    per = per[(per["n"] > 0) & (per["nhat"] > 0)]
    if per.empty:
        return int(hyp_id)
    return int(per.sort_values(["t", "p_min", "hyp_id"], ascending=[False, True, True])
               .iloc[0]["hyp_id"])  # fmt: skip


# -- longitudinal bounds (the paper's HCO3 figure) ----------------------------------------------


def _d0_range(
    d0x: np.ndarray,
    d0a: np.ndarray,
    states: StateBins,
    outcome: str,
    seq,
    bset,
    quantiles: tuple[float, float],
) -> tuple[float, float, int]:
    """Design rule for (a_1:s, B_0:s): quantiles of X_s[k] over D0 trajectories that follow
    a_1:s and stay in B_0:s (design.build_hypotheses); fallback: all of D0 at s."""
    s = len(seq)
    codes = state_codes(d0x, states, outcome)
    keep = (d0a[:, :s] == np.asarray(seq)[None, :]).all(axis=1)
    b = np.asarray(bset)
    keep &= ((codes[:, : s + 1] == b[None, :]) | (b[None, :] == WHOLE_SPACE)).all(axis=1)
    y = d0x[:, s, FEATURES.index(outcome)]
    sub = y[keep]
    if len(sub) >= 2:
        lo, up = np.quantile(sub, quantiles)
        if up > lo:
            return float(lo), float(up), int(keep.sum())
    lo, up = np.quantile(y, quantiles)
    return float(lo), float(up), int(keep.sum())


def longitudinal_frame(
    st: StudyTwin, hyp_id: int, alpha: float = 0.05, quantiles: tuple[float, float] = (0.2, 0.8)
) -> pd.DataFrame:
    """Bounds, twin mean and naive mean for every prefix s = 1..t of one hypothesis.

    For s = 1..t the parameter set (k, s, a_1:s, B_0:s) gets y_lo, y_up by the design's
    rule on D0 (the hypothesis's own values at s = t), then the library computes both
    sides on D. Intervals are one-sided (1 - alpha/2) Hoeffding radii,
    R sqrt(log(2/alpha) / (2 m)) with m = n (bounds), nhat (twin) or n_follow (naive),
    unadjusted for multiplicity (Hoeffding 1963; Cornish et al. 2026, Proposition).
    """
    row = st.hyps.loc[st.hyps["hyp_id"] == hyp_id]
    if row.empty:
        raise ContractError(f"figures: hyp_id {hyp_id} is not in the hypotheses table")
    row = row.iloc[0]
    outcome, t = row["outcome"], int(row["t"])
    seq, bset = [int(a) for a in row["actions"]], [int(b) for b in row["bins"]]
    d0x = to_array(st.d0, FEATURES, T_MAX)
    d0a = action_codes(st.d0, st.actions, T_MAX)
    rows = []
    for s in range(1, t + 1):
        if s == t:
            lo, up, support = float(row["y_lo"]), float(row["y_up"]), int(row.get("support", 0))
        else:
            lo, up, support = _d0_range(d0x, d0a, st.states, outcome, seq[:s], bset[: s + 1],
                                        quantiles)  # fmt: skip
        rows.append({"hyp_id": s, "outcome": outcome, "t": s, "actions": seq[:s],
                     "bins": bset[: s + 1], "y_lo": lo, "y_up": up,
                     "support": support})  # fmt: skip
    hyps = pd.DataFrame(rows)
    dx = to_array(st.d, FEATURES, T_MAX)
    da = action_codes(st.d, st.actions, T_MAX)
    obs = bounds.observational_side(hyps, dx, da, st.states)
    smp, n_failed = twin_samples(hyps, obs, st.nodes, st.states)
    w = smp.width
    out = hyps.drop(columns=["hyp_id"]).assign(
        n=smp.n, n_follow=smp.n_follow, nhat=smp.nhat, n_failed=n_failed,
        q_lo_hat=smp.q_lo_hat, q_up_hat=smp.q_up_hat, q_twin_hat=smp.q_twin_hat,
        q_obs_hat=smp.q_obs_hat, propensity=smp.propensity,
        r_bound=hoeffding_radius(w, smp.n, alpha), r_twin=hoeffding_radius(w, smp.nhat, alpha),
        r_obs=hoeffding_radius(w, smp.n_follow, alpha),
    )  # fmt: skip
    sizes = outcome_sizes(smp)
    out["twin_mean"] = sizes["twin_mean"].to_numpy()
    out["twin_below"] = sizes["twin_below"].to_numpy()
    out["twin_above"] = sizes["twin_above"].to_numpy()
    out["source_hyp_id"] = hyp_id
    return out


def histogram_data(st: StudyTwin, hyp_id: int, alpha: float = 0.05) -> dict:
    """Raw outcomes of one hypothesis (followers in D, entering twin runs) and its intervals.

    Intervals: [Qhat_lo - r(n), Qhat_up + r(n)] for the bounds and Qhat_twin +- r(nhat),
    r(m) = R sqrt(log(2/alpha) / (2 m)) (one-sided 1 - alpha/2 Hoeffding, unadjusted).
    """
    pos = np.flatnonzero(st.hyps["hyp_id"].to_numpy() == hyp_id)
    if len(pos) != 1:
        raise ContractError(f"figures: hyp_id {hyp_id} is not (once) in the hypotheses table")
    h = int(pos[0])
    smp = st.samples
    row = st.hyps.iloc[h]
    res = st.results[st.results["hyp_id"] == hyp_id]
    w = smp.width[h]
    return {
        "hyp_id": int(hyp_id), "outcome": row["outcome"], "t": int(row["t"]),
        "actions": [int(a) for a in row["actions"]], "bins": [int(b) for b in row["bins"]],
        "y_lo": float(smp.y_lo[h]), "y_up": float(smp.y_up[h]),
        "obs": smp.follow.group(h).copy(), "twin": smp.twin.group(h).copy(),
        "n": int(smp.n[h]), "nhat": int(smp.nhat[h]),
        "q_lo_hat": float(smp.q_lo_hat[h]), "q_up_hat": float(smp.q_up_hat[h]),
        "q_twin_hat": float(smp.q_twin_hat[h]),
        "r_bound": float(hoeffding_radius(w, smp.n[h], alpha)),
        "r_twin": float(hoeffding_radius(w, smp.nhat[h], alpha)),
        "rejected": bool(res["rejected"].any()),
        "p_min": float(res["p_value"].min()) if len(res) else 1.0,
    }  # fmt: skip


# -- confounding illustration (synthetic world only) -------------------------------------------


def confounding_frame(
    d: pd.DataFrame, world, actions: ActionBins, outcome: str = "MeanBP", seed: int = 0
) -> pd.DataFrame:
    """Per action a at hour 1: outcome X_1[k] observed among those who took a, and under
    do(A_1 = a) for everyone in D (the world's exact interventional law, twin dose = bin
    median). Long table: action, which (observed | everyone), value.

    The gap between the two is confounding bias: E[X_1 | A_1 = a] != E[X_1(a)] because the
    unmeasured severity drives both the dose and the response (Cornish et al. 2026, Sec. 2).
    """
    from twinfalsify import noise

    if outcome not in FEATURES:
        raise ContractError(f"figures.confounding.outcome: unknown feature {outcome!r}")
    x = to_array(d, FEATURES, T_MAX)
    a = action_codes(d, actions, T_MAX)[:, 0]
    x0 = d[d["t"] == 0].sort_values("stay_id")
    stay = x0["stay_id"].to_numpy(np.uint64)
    x0f = x0[list(FEATURES)].reset_index(drop=True)
    k = FEATURES.index(outcome)
    seeds = noise.combine(np.uint64(seed), stay)
    parts = []
    for code in np.unique(a):
        took = a == code
        parts.append(pd.DataFrame({"action": int(code), "which": "observed",
                                   "value": x[took, 1, k]}))  # fmt: skip
        doses = np.broadcast_to(actions.doses(np.array([code])), (len(x0f), 1, 2)).copy()
        sim = world.simulate_interventional(x0f, doses, seeds)
        parts.append(pd.DataFrame({"action": int(code), "which": "everyone",
                                   "value": sim[:, 0, k]}))  # fmt: skip
    return pd.concat(parts, ignore_index=True)


# -- study summary -----------------------------------------------------------------------------


def clamp_shares(runs: pd.DataFrame) -> pd.DataFrame:
    """Share of twin X_0 whose initial state was clamped, per feature.

    The ``clamped`` column holds JSON ``{feature: [given, used]}`` (empty for none); clamps
    are applied once at initialisation, so a stay counts once (any of its rows).
    """
    if "clamped" not in runs:
        raise ContractError("twin runs: column 'clamped' missing")
    n_x0 = runs["init_stay_id"].nunique()
    hits: dict[str, set] = {}
    for stay, text in zip(runs["init_stay_id"].to_numpy(), runs["clamped"].to_numpy(), strict=True):
        if not text or text in ("{}", "null"):
            continue
        try:
            data = json.loads(text) if isinstance(text, str) else dict(text)
        except (TypeError, ValueError) as exc:
            raise ContractError(
                f"twin runs: column 'clamped' is not JSON ({exc}): {text!r}"
            ) from None
        for feat in data or {}:
            hits.setdefault(feat, set()).add(int(stay))
    rows = [{"feature": f, "x0_clamped": len(s), "share": len(s) / max(n_x0, 1)}
            for f, s in sorted(hits.items())]  # fmt: skip
    return pd.DataFrame(rows, columns=["feature", "x0_clamped", "share"])


def refusal_lines(results: pd.DataFrame) -> list[str]:
    """One line per method that refused hypotheses (results column ``refused``: p = 1 by
    rule, not by evidence), with its count per kind: what the console and the log say, so
    that a refused hypothesis is not read as tested and not rejected."""
    out = []
    for method, part in results.groupby("method", sort=False):
        counts = part[part["refused"]].groupby("kind", sort=True).size()
        if counts.sum() == 0:
            continue
        per_kind = ", ".join(f"{int(c)} of {int((part['kind'] == k).sum())} {k}"
                             for k, c in counts.items())
        out.append(f"{method} refused {per_kind} hypotheses (too few samples: p = 1 by rule, "
                   "not tested; results column 'refused')")
    return out


CLIPPED_WARN = 0.6  # a twin share at one bound above this is warned about (data: ~0.2) ...
CLIPPED_MARGIN = 0.4  # ... when it is also this much above the data's own share there


def clipped_shares(hyps: pd.DataFrame, samples: HypothesisSamples) -> pd.DataFrame:
    """Per outcome: the share of the twin's outputs (every run entering a hypothesis) at or
    beyond y_lo and at or beyond y_up, and their unclipped median, beside the data's
    followers' (their shares and median).

    The tests clip outcomes to [y_lo, y_up] (the 0.2 / 0.8 quantiles of the D0 subset, so
    about a fifth of the data sits at each bound): a twin in the wrong unit piles up at one
    bound, where a test may not reject it, and this table shows it and how far off it is.
    """
    rows = []
    outcome = hyps["outcome"].to_numpy()
    for part, ragged in (("twin", samples.twin), ("data", samples.follow)):
        gid = ragged.group_ids()
        lo = ragged.values <= samples.y_lo[gid]
        up = ragged.values >= samples.y_up[gid]
        frame = pd.DataFrame({"outcome": outcome[gid], "lo": lo, "up": up,
                              "value": ragged.values})
        g = frame.groupby("outcome")
        rows.append(pd.DataFrame({f"{part}_outputs": g.size(),
                                  f"{part}_at_y_lo": g["lo"].mean(),
                                  f"{part}_at_y_up": g["up"].mean(),
                                  f"{part}_median": g["value"].median()}))
    out = pd.concat(rows, axis=1).reset_index().rename(columns={"index": "outcome"})
    counts = ["twin_outputs", "data_outputs"]
    out[counts] = out[counts].fillna(0).astype("int64")
    return out[list(CLIPPED_COLUMNS)]


CLIPPED_COLUMNS = ("outcome", "twin_outputs", "twin_at_y_lo", "twin_at_y_up", "twin_median",
                   "data_outputs", "data_at_y_lo", "data_at_y_up", "data_median")


def clipped_warnings(clipped: pd.DataFrame) -> list[str]:
    """One line per twin and outcome whose outputs sit at one bound more than CLIPPED_WARN
    of the time and CLIPPED_MARGIN more often than the data's followers do (a unit or scale
    error the tests may not be able to reject; a bound the data crowd too is no sign)."""
    out = []
    for r in clipped.itertuples():
        for side in ("lo", "up"):
            share = getattr(r, f"twin_at_y_{side}")
            data = getattr(r, f"data_at_y_{side}")
            data = 0.0 if pd.isna(data) else data
            if share > CLIPPED_WARN and share - data > CLIPPED_MARGIN:
                unit = FEATURE_BY_NAME[r.outcome].unit
                out.append(f"twin {r.twin}: {share:.0%} of its {r.outcome} outputs are at or "
                           f"beyond y_{side} (data: {data:.0%}); its median "
                           f"{r.twin_median:.4g} against the data's {r.data_median:.4g} "
                           f"{unit}: a unit or scale error? The tests see only the clipped "
                           "values")
    return out


def _md(df: pd.DataFrame) -> str:
    return markdown_table(df, ".3g")


def tie_table(d: pd.DataFrame, actions: ActionBins, seed: int) -> pd.DataFrame:
    """Per hour t: how many of D's trajectories share their X_0:t, A_1:t with another (ties
    the data order breaks by copy index, ``inference.order``)."""
    keys = content_keys(to_array(d, FEATURES, T_MAX), action_codes(d, actions, T_MAX), seed,
                        copies=False)
    return pd.DataFrame([{"sample": "D", "t": t, "records": len(keys),
                          "tied": f"{tied_share(keys[:, t]):.1%}"}
                         for t in range(keys.shape[1])])


def study_summary(
    study: str,
    d0: pd.DataFrame,
    d: pd.DataFrame,
    hyps: pd.DataFrame,
    twins: Mapping[str, Mapping[str, pd.DataFrame]],
    trajectories_stays: int | None = None,
    ties: pd.DataFrame | None = None,
    data: Mapping[str, object] | None = None,
) -> dict[str, pd.DataFrame]:
    """Tables of the study summary. twins: name -> {"runs": ..., "results": ...,
    optionally "clipped": clipped_shares(...)}; the results' column ``refused`` says which
    hypotheses each method did not test; data: the source's dataset record (the meds
    source's cohort/dataset.json: dataset, path, licence), shown as "data".

    Returns named tables: cohort, hypotheses, runs (status counts per twin and hour),
    clamps (share of X_0 clamped per twin and feature), rejections (per twin, method, kind:
    rejected, refused, tested),
    untestable (parameter sets with n = 0 or nhat = 0, per twin and kind), workers
    (worker restarts per twin and shard, from the runs' ``twin_workers`` attribute that
    the twin_runs rule writes; none for in-process twins), failing (warnings).
    """
    n_d0, n_d = d0["stay_id"].nunique(), d["stay_id"].nunique()
    cohort = pd.DataFrame({
        "what": ["cohort (stays)", "D0 (design)", "D (test)"],
        "count": [trajectories_stays if trajectories_stays is not None else n_d0 + n_d, n_d0, n_d],
    })  # fmt: skip
    hyp = hyps.groupby("kind").agg(parameter_sets=("hyp_id", "size")).reset_index()
    hyp["hypotheses"] = 2 * hyp["parameter_sets"]
    runs_rows, clamp_rows, rej_rows, unt_rows, clip_rows = [], [], [], [], []
    worker_rows: list[dict] = []
    failing: list[str] = []
    for name, parts in twins.items():
        runs, res = parts["runs"], parts["results"]
        counts = runs.groupby(["t", "status"]).size().rename("rows").reset_index()
        counts.insert(0, "twin", name)
        runs_rows.append(counts)
        cl = clamp_shares(runs)
        cl.insert(0, "twin", name)
        clamp_rows.append(cl)
        g = res.groupby(["method", "kind"])
        rej = pd.DataFrame({"hypotheses": g.size(), "rejected": g["rejected"].sum(),
                            "refused": g["refused"].sum()}).reset_index()
        if "seed_fragile" in res:  # decisions that change under another order seed
            rej["seed_fragile"] = g["seed_fragile"].sum().to_numpy()
        rej["tested"] = rej["hypotheses"] - rej["refused"]
        rej.insert(0, "twin", name)
        rej_rows.append(rej)
        first = res.drop_duplicates("hyp_id")
        unt = first.assign(untestable=(first["n"] == 0) | (first["nhat"] == 0),
                           n_zero=first["n"] == 0, nhat_zero=first["nhat"] == 0)  # fmt: skip
        u = unt.groupby("kind")[["untestable", "n_zero", "nhat_zero"]].sum().reset_index()
        u.insert(0, "twin", name)
        unt_rows.append(u)
        if "init_stay_id" in runs and failing_patients(runs, name):
            failing.append(failing_patients(runs, name))
        failing += [f"twin {name}: {line}" for line in refusal_lines(res)]
        workers = runs.attrs.get("twin_workers") or {}
        for shard, stats in enumerate(workers.get("per_shard", [])):
            worker_rows.append({"twin": name, "shard": shard, **stats})
        if warning := restart_warning(name, None, workers.get("total")):
            failing.append(warning)
        if parts.get("clipped") is not None:
            cp = parts["clipped"].copy()
            cp.insert(0, "twin", name)
            clip_rows.append(cp)

    def cat(frames, cols):
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=cols)

    tables = {"data": pd.DataFrame({"what": ["dataset", "folder", "licence", "code map"],
                                    "value": [str(data.get(k) or "not stated") for k in (
                                        "dataset", "path", "licence", "code_map")]})
              } if data else {}
    software = pd.DataFrame(software_versions(), columns=["package", "version"])
    return {
        **tables,
        "software": software,
        "cohort": cohort,
        "ties": ties if ties is not None else pd.DataFrame(columns=["sample", "t", "records",
                                                                     "tied"]),
        "hypotheses": hyp,
        "runs": cat(runs_rows, ["twin", "t", "status", "rows"]),
        "clamps": cat(clamp_rows, ["twin", "feature", "x0_clamped", "share"]),
        "rejections": cat(rej_rows, ["twin", "method", "kind", "hypotheses", "rejected",
                                     "refused", "tested"]),
        "untestable": cat(unt_rows, ["twin", "kind", "untestable", "n_zero", "nhat_zero"]),
        "failing": pd.DataFrame({"warning": failing}, dtype=object),
        "workers": pd.DataFrame(worker_rows, columns=["twin", "shard", *WORKER_STATS]),
        "clipped": cat(clip_rows, ["twin", *CLIPPED_COLUMNS]),
    }


_TITLES = {
    "data": "Data and licence",
    "cohort": "Cohort and split",
    "ties": "Tied records: share of D's trajectories whose X_0:t, A_1:t another trajectory "
            "shares (the data order keys each copy apart, docs/explanation/statistics.md)",
    "hypotheses": "Hypotheses (two one-sided hypotheses per parameter set)",
    "runs": "Twin runs by hour and status (rows = prefix node x X_0)",
    "clamps": "Share of twin initial states clamped, per feature",
    "rejections": "Rejections per twin, method and kind (after correction); refused: "
                  "hypotheses the method did not test (p = 1 by rule: n or nhat = 0, or "
                  "below the bootstrap's min_n; results column refused), so tested = "
                  "hypotheses - refused; seed_fragile (with testing.seed_check): decisions "
                  "that change under another order seed",
    "untestable": "Untestable parameter sets (n = 0 or nhat = 0: p = 1 by rule)",
    "workers": "Twin worker restarts per shard (served twins): crashes (died during a "
               "request), hangs (killed at timeout_s), malformed answers",
    "clipped": "Outputs at the bounds: share of twin and data outcomes at or beyond y_lo / "
               "y_up, and their unclipped medians, per twin and outcome",
    "software": "Software: the versions of the environment that ran the workflow's jobs",
}


def summary_warnings(tables: Mapping[str, pd.DataFrame]) -> list[str]:
    """The study's warnings, as the summary lists them under "Warnings" (failing runs and
    worker restarts, then outputs piled up at a bound)."""
    clipped = tables.get("clipped")
    failing = tables.get("failing")
    return ([*failing["warning"]] if failing is not None else []) + (
        clipped_warnings(clipped) if clipped is not None and len(clipped) else [])


def summary_markdown(study: str, tables: Mapping[str, pd.DataFrame]) -> str:
    out = [f"# Study `{study}`: summary", ""]
    warnings = summary_warnings(tables)
    if warnings:
        out += ["## Warnings", "", *[f"- {w}" for w in warnings], ""]
    for key, title in _TITLES.items():
        if key not in tables:
            continue
        df = tables[key]
        out += [f"## {title}", "", _md(df) if len(df) else "_none_", ""]
    return "\n".join(out)


def warnings_in_summary(md: str | Path, since: float | None = None) -> list[str]:
    """The warnings a summary.md lists (``summary_markdown``'s "## Warnings" section), one
    string each; none when the file is missing or, with ``since`` (a time.time()), was
    written before it (a summary this run did not write)."""
    path = Path(md)
    try:
        if since is not None and path.stat().st_mtime < since:
            return []
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    if "## Warnings" not in lines:
        return []
    out = []
    for line in lines[lines.index("## Warnings") + 1:]:
        if line.startswith("## "):
            break
        if line.startswith("- "):
            out.append(line[2:])
    return out


def summary_html(study: str, tables: Mapping[str, pd.DataFrame]) -> str:
    style = ("body{font-family:sans-serif;margin:1.5em;max-width:60em}"
             "table{border-collapse:collapse;margin-bottom:1.2em}"
             "td,th{border:1px solid #bbb;padding:.25em .6em;text-align:right}"
             "th{background:#eef}")  # fmt: skip
    out = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{study} summary</title>"
        f"<style>{style}</style></head><body><h1>Study <code>{study}</code>: summary</h1>"
    ]
    warnings = summary_warnings(tables)
    if warnings:
        out.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{w}</li>" for w in warnings)
                   + "</ul>")
    for key, title in _TITLES.items():
        if key not in tables:
            continue
        df = tables[key]
        body = (
            df.to_html(index=False, float_format=lambda v: f"{v:.3g}") if len(df) else "<p>none</p>"
        )
        out.append(f"<h2>{title}</h2>{body}")
    out.append("</body></html>")
    return "\n".join(out)
