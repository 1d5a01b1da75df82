"""Adaptive twin runs: simulate a shard batch by batch, stop what is decided.

The shard holds the plan's leaves with some first actions (``plan.shards``); its hypotheses
are those whose sequence starts with one of them (so no node is shared across shards).
Batch b (b = 1, 2, ...) is the slice [(b-1) s, b s) of the plan's seeded X_0 permutation
(s = batch size, capped at the budget). Before batch 1 the observational side alone can
settle a hypothesis (futility: its bound at alpha is uninformative). At each batch run j of
node v is simulated only if some still-running hypothesis whose path uses v has X_0 j in
its B_0 (``inference.sequential.node_needs``: other runs can never enter it); deepest nodes
first, each simulation filling every node on its path (prefix reuse). After the batch,
``inference.sequential.SequentialState.update`` decides early rejection / futility.

Outputs (every simulated run accounted for): the node rows actually simulated (the fixed
scheme's shape, ``plan.NODE_COLUMNS``), and one decision row per hypothesis of the shard
(stop batch, runs used, decision per side, anytime-valid p-values at the stop, nhat,
n_failed). Runs never simulated are not rows: ``runs_used`` says how many X_0 each
hypothesis received, and ``runs_saved`` in the summary counts node-runs not simulated.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import pandas as pd

from twinfalsify.bounds import (
    ObservationalSide,
    TwinNodes,
    hypothesis_paths,
    reachable,
    twin_runs_indexed,
)
from twinfalsify.design import ActionBins, StateBins
from twinfalsify.inference.sequential import (
    CURTAILED,
    FUTILE,
    HOLM_AWARE,
    REJECTED,
    UNDECIDED,
    SequentialState,
    embed_runs,
    family_sizes,
    node_needs,
)
from twinfalsify.runs.plan import (
    NODE_COLUMNS,
    TwinPlan,
    implausible_warning,
    node_name,
    parse_node,
    simulate_jobs,
)
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.truncation import JobBoxes
from twinfalsify.schema import FEATURES, STAY_ID, ContractError
from twinfalsify.twins.base import Twin

DECISION_NAMES = {UNDECIDED: "undecided", REJECTED: "rejected", FUTILE: "futile",
                  CURTAILED: "curtailed"}
DECISION_COLUMNS = (
    "hyp_id", "stop_batch", "runs_used", "decision_lo", "decision_up", "p_lo", "p_up",
    "nhat", "n_failed",
)  # fmt: skip


def shard_hypotheses(hyps: pd.DataFrame, plan: TwinPlan, shard: int) -> np.ndarray:
    """(H,) bool: hypotheses whose first action is one of the shard's."""
    if not 0 <= shard < len(plan.shards):
        raise ContractError(f"twin shard {shard} does not exist (plan has {len(plan.shards)})")
    firsts = {parse_node(leaf)[0] for leaf in plan.shards[shard]}
    return np.array([int(seq[0]) in firsts for seq in hyps["actions"].tolist()], dtype=bool)


def _rows(name: str, s: int, vals: np.ndarray, res_status: np.ndarray, msg: np.ndarray,
          clamped: np.ndarray, stays: np.ndarray) -> pd.DataFrame:
    done = np.isfinite(vals).all(axis=1)
    f = pd.DataFrame(vals, columns=list(FEATURES))
    f.insert(0, "clamped", clamped)
    f.insert(0, "message", np.where(done, "", msg))
    f.insert(0, "status", np.where(done, "ok", np.where(res_status == "ok", "error", res_status)))
    f.insert(0, "init_stay_id", stays)
    f.insert(0, "t", s)
    f.insert(0, "node", name)
    return f


def run_adaptive_shard(
    twin: Twin,
    plan: TwinPlan,
    shard: int,
    x0: pd.DataFrame,
    actions: ActionBins,
    hyps: pd.DataFrame,
    obs: ObservationalSide,
    states: StateBins,
    *,
    batch_size: int,
    alpha: float = 0.05,
    seed: int = 0,
    budget: int | None = None,
    correction: str = "holm",
    curtail: float = 0.0,
    combine: str = "union",
    failed_runs: str = "conservative",
    log=sys.stderr,
) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """Simulate one shard adaptively: (node rows simulated, decisions, summary).

    Holm-aware futility (``correction`` holm or bonferroni) counts the primary-futile sides of
    this shard's own hypotheses only (shards run in parallel and share nothing): fewer than
    the whole family's, so a more lenient, still valid, threshold bound.
    """
    m = len(plan.x0_stay_ids)
    budget = m if budget is None else min(int(budget), m)
    mine = shard_hypotheses(hyps, plan, shard)
    idx = np.flatnonzero(mine)
    index = {parse_node(n): i for i, n in enumerate(plan.nodes)}
    nodes = TwinNodes(index=index, values=np.full((len(index), m, len(FEATURES)), np.nan),
                      x0=x0[list(FEATURES)].to_numpy(float))
    st = SequentialState(hyps, obs, states, budget, int(batch_size), alpha, seed,
                         n_family=family_sizes(hyps), only=mine,
                         holm_aware=correction in HOLM_AWARE, holm_scope=mine, curtail=curtail,
                         combine=combine, failed_runs=failed_runs)
    sub = hyps.iloc[idx]
    seqs = [tuple(int(a) for a in s) for s in sub["actions"].tolist()]
    seeds = plan.run_seeds()
    stays = x0[STAY_ID].to_numpy(np.int64)
    frames: list[pd.DataFrame] = []
    start = time.monotonic()
    h_total = len(hyps)

    def runs_now():
        return embed_runs(twin_runs_indexed(sub, nodes, states), idx, h_total)

    # depth truncation (docs/explanation/sequential.md): hours of a run that already left
    # every B-set
    # needing them are not kept. In-process twins compute whole paths at no cost, so their
    # node rows are what a truncating engine would simulate; a protocol twin advertising
    # `truncate` gets the box paths and stops such runs; others simulate whole paths.
    send_boxes = isinstance(twin, ProtocolTwin) and twin.truncates
    truncate = send_boxes or not isinstance(twin, ProtocolTwin)
    runs0 = runs_now()
    in_b0 = runs0.in_b0  # real X_0 in B_0: known before any simulation
    boxes = JobBoxes(sub, in_b0[idx], states, nodes.x0) if send_boxes else None
    st.update(runs0, 0)
    sim_node_runs = 0
    requested = 0  # hours asked of the twin: a twin without prefix reuse simulates these
    shard_nodes = {q[:k] for q in seqs for k in range(1, len(q) + 1)}
    fixed = len(shard_nodes) * budget
    depth_first = sorted(shard_nodes, key=len, reverse=True)
    paths = hypothesis_paths(sub, index)
    n_runs = n_implausible = 0  # simulated runs, and those implausible (one warning at the end)
    first_implausible = ""
    for b in range(1, st.n_batches + 1):
        act = st.active[idx]
        if not act.any():
            break
        j0, j1 = st.revealed(b - 1), st.revealed(b)
        # runs needed per node this batch: X_0 in B_0 of a running hypothesis using the node
        need = node_needs(paths, np.where(act, j1, 0), in_b0[idx], len(index))[:, j0:j1]
        # deepest node first, each simulation filling every node on its path; the whole
        # batch in one call, so a protocol twin can branch shared prefixes (Pulse)
        covered = np.zeros_like(need)
        jobs, fresh = [], []  # fresh[k][s-1]: rows of job k that fill node a_1:s first
        for node in depth_first:
            rows = np.flatnonzero(need[index[node]] & ~covered[index[node]])
            if rows.size:
                jobs.append((node, rows))
                fresh.append([~covered[index[node[:s]], rows] for s in range(1, len(node) + 1)])
                for s in range(1, len(node) + 1):
                    covered[index[node[:s]], rows] = True
        cw = None
        if send_boxes:  # per job and row: box paths of the hypotheses it serves
            cw = [boxes.for_job(leaf, j0 + rows, new_at, act) for (leaf, rows), new_at
                  in zip(jobs, fresh, strict=True)]
        results = simulate_jobs(twin, [(node, j0 + rows) for node, rows in jobs], x0, seeds,
                                actions, None, cw)
        for _, status, message, _ in results:
            n_runs += len(status)
            bad = np.flatnonzero(status == "implausible")
            if bad.size and not n_implausible:
                first_implausible = str(message[bad[0]])
            n_implausible += bad.size
        # each (node, run) from the first job that knows it: a value, or a failure (a run
        # truncated by the twin knows nothing past its last hour: another job may)
        got = []  # (node, batch rows, values, status, message, clamped)
        filled = np.zeros((len(index), j1 - j0), dtype=bool)
        for (leaf, rows), (feats, status, message, clamped) in zip(jobs, results, strict=True):
            requested += rows.size * len(leaf)
            for s in range(1, len(leaf) + 1):
                v = index[leaf[:s]]
                have = np.isfinite(feats[:, s - 1, :]).all(axis=1) | (status != "ok")
                new = have & ~filled[v, rows]
                if new.any():
                    filled[v, rows[new]] = True
                    got.append((leaf[:s], rows[new], feats[new, s - 1, :], status[new],
                                message[new], clamped[new]))
                    nodes.values[v, j0 + rows[new]] = feats[new, s - 1, :]
        if truncate:  # keep the hours a depth-truncating twin simulates; forget the rest
            batch = TwinNodes(index=index, values=nodes.values[:, j0:j1], x0=nodes.x0[j0:j1])
            keep = node_needs(paths, np.where(act, j1 - j0, 0), in_b0[idx][:, j0:j1],
                              len(index), reachable(sub, batch, states))
            if (keep & ~filled).any():
                raise ContractError(
                    f"twin {twin.name}: runs truncated before hours still needed (adaptive "
                    f"shard {shard}, batch {b}); the caller's truncation check should have "
                    "caught this")
        done_runs = 0
        for node, rows, vals, status, message, clamped in got:
            k = keep[index[node], rows] if truncate else np.ones(rows.size, bool)
            nodes.values[index[node], j0 + rows[~k]] = np.nan
            if k.any():
                frames.append(_rows(node_name(node), len(node), vals[k], status[k],
                                    message[k], clamped[k], stays[j0 + rows[k]]))
                done_runs += int(k.sum())
        sim_node_runs += done_runs
        st.update(runs_now(), b)
        running = int(st.active[idx].sum())
        print(f"[adaptive {twin.name} shard {shard}] batch {b}/{st.n_batches} (X_0 {j1}/{budget})"
              f": {len(idx) - running} decided, {running} undecided parameter sets; "
              f"node-runs {sim_node_runs:,} of {fixed:,} ({fixed - sim_node_runs:,} saved), "
              f"{time.monotonic() - start:.1f} s", file=log, flush=True)
    if n_implausible:
        print(implausible_warning(twin.name, shard, n_implausible, n_runs, first_implausible),
              file=log, flush=True)
    runs = runs_now()
    p_lo, p_up, nhat = st.p_values(runs)
    used = st.runs_used()
    n_failed = (runs.failed & (np.arange(m)[None, :] < used[:, None])).sum(axis=1)
    dec = pd.DataFrame({
        "hyp_id": hyps["hyp_id"].to_numpy()[idx], "stop_batch": st.stop_batch[idx],
        "runs_used": used[idx],
        "decision_lo": [DECISION_NAMES[int(v)] for v in st.side[idx, 0]],
        "decision_up": [DECISION_NAMES[int(v)] for v in st.side[idx, 1]],
        "p_lo": p_lo[idx], "p_up": p_up[idx], "nhat": nhat[idx], "n_failed": n_failed[idx],
    })  # fmt: skip
    rows = (pd.concat(frames, ignore_index=True) if frames
            else pd.DataFrame(columns=list(NODE_COLUMNS)))
    per_node = node_needs(paths, used[idx], in_b0[idx], len(index),
                          reachable(sub, nodes, states) if truncate else None).sum(axis=1)
    summary = {
        "shard": shard, "batch_size": int(batch_size), "budget": budget,
        "parameter_sets": len(idx), "node_rows": len(rows),
        "twin_hours_adaptive": int(per_node.sum()),
        "twin_hours_fixed": fixed,
        "twin_hours_requested": requested,
        "runs_saved": fixed - len(rows),
        "depth_truncation": truncate,
        # parameter sets decided futile on both sides before any run: no outcome of the
        # budget could reach the level (all of them = the budget is too small to test)
        "futile_without_runs": int(((st.side[idx] == FUTILE).all(axis=1)
                                    & (used[idx] == 0)).sum()),
        "decisions": {
            side: pd.Series(dec[f"decision_{side}"]).value_counts().to_dict()
            for side in ("lo", "up")
        },
    }
    if len(rows) != summary["twin_hours_adaptive"]:
        raise AssertionError(
            f"adaptive shard {shard}: {len(rows)} node rows but {per_node.sum()} node-runs "
            "revealed: accounting broken")
    return rows, dec.loc[:, list(DECISION_COLUMNS)], summary


def budget_warning(summary: dict) -> str | None:
    """One line for the shard's log when every parameter set was futile before any twin run
    (the budget cannot reject anything at the configured level), else None."""
    n = summary["parameter_sets"]
    if n == 0 or summary["futile_without_runs"] < n:
        return None
    return (f"shard {summary['shard']}: all {n} parameter sets were futile before any twin run: "
            f"no outcome of {summary['budget']} runs per sequence can reach the test level, so "
            "no twin time was spent and nothing can be rejected; raise "
            "twin_runs.runs_per_sequence to test these hypotheses")


def load_simulated(rows: pd.DataFrame, plan: TwinPlan, x0: pd.DataFrame) -> TwinNodes:
    """Simulated node rows -> TwinNodes (NaN for runs never simulated or failed)."""
    names = plan.nodes
    m = len(plan.x0_stay_ids)
    values = np.full((len(names), m, len(FEATURES)), np.nan)
    node_idx = rows["node"].map({n: i for i, n in enumerate(names)})
    run_idx = rows["init_stay_id"].map({s: j for j, s in enumerate(plan.x0_stay_ids)})
    if node_idx.isna().any() or run_idx.isna().any():
        raise ContractError("adaptive twin runs hold node(s) or X_0 not in the plan")
    if rows.duplicated(["node", "init_stay_id"]).any():
        raise ContractError("adaptive twin runs: duplicated (node, X_0) rows across shards")
    ok = (rows["status"] == "ok").to_numpy()
    values[node_idx.to_numpy(int)[ok], run_idx.to_numpy(int)[ok], :] = rows.loc[
        ok, list(FEATURES)].to_numpy(float)
    return TwinNodes(index={parse_node(n): i for i, n in enumerate(names)}, values=values,
                     x0=x0[list(FEATURES)].to_numpy(float))


def adaptive_results(
    hyps: pd.DataFrame, obs: ObservationalSide, nodes: TwinNodes, states: StateBins,
    decisions: pd.DataFrame, *, alpha: float = 0.05, correction: str = "holm",
    failed_runs: str = "conservative",
) -> pd.DataFrame:
    """The tests stage's long results table from adaptive decisions (method betting_sequential).

    Descriptive columns (nhat, q_twin_hat, ...) use the twin runs revealed at the stop;
    p-values are the shards' anytime-valid ones; the correction runs per kind on them.
    """
    from twinfalsify.falsify import RESULT_COLUMNS
    from twinfalsify.inference.samples import HypothesisSamples, Ragged
    from twinfalsify.inference.sequential import correct_by_family

    dec = decisions.set_index("hyp_id")
    missing = set(hyps["hyp_id"]) - set(dec.index)
    if missing:
        raise ContractError(f"adaptive decisions: {len(missing)} hypothesis(es) missing, e.g. "
                            f"{sorted(missing)[:3]}")
    dec = dec.loc[hyps["hyp_id"]]
    runs = twin_runs_indexed(hyps, nodes, states)
    used = dec["runs_used"].to_numpy(np.int64)
    keep = runs.run < used[runs.values.group_ids()]
    twin = Ragged(runs.values.values[keep], np.concatenate(
        [[0], np.cumsum(np.bincount(runs.values.group_ids()[keep], minlength=len(hyps)))]
    ).astype(np.int64))
    if not np.array_equal(twin.sizes, dec["nhat"].to_numpy()):
        raise ContractError("adaptive decisions: nhat disagrees with the simulated runs")
    s = HypothesisSamples(hyps["y_lo"].to_numpy(float), hyps["y_up"].to_numpy(float), obs.n,
                          obs.follow, twin)
    p_lo, p_up = dec["p_lo"].to_numpy(float), dec["p_up"].to_numpy(float)
    rej_lo, rej_up = correct_by_family(hyps, p_lo, p_up, alpha, correction)
    parts = []
    for side, p, rej in (("lo", p_lo, rej_lo), ("up", p_up, rej_up)):
        parts.append(pd.DataFrame({
            "hyp_id": hyps["hyp_id"].to_numpy(), "kind": hyps["kind"].to_numpy(),
            "outcome": hyps["outcome"].to_numpy(), "t": hyps["t"].to_numpy(), "side": side,
            "method": "betting_sequential", "n": s.n, "n_follow": s.n_follow, "nhat": s.nhat,
            "n_failed": dec["n_failed"].to_numpy(),
            # how the shards' p-values treated failed runs (sequential module doc)
            "failed_runs": failed_runs, "y_lo": s.y_lo, "y_up": s.y_up,
            "q_lo_hat": s.q_lo_hat, "q_up_hat": s.q_up_hat, "q_twin_hat": s.q_twin_hat,
            "q_obs_hat": s.q_obs_hat, "propensity": s.propensity, "p_value": p,
            # refused: no observational follower, p = 1 by rule (inference.sequential)
            "p_floor": False, "refused": s.n == 0, "rejected": rej, "correction": correction,
            "alpha": alpha,
            "stop_batch": dec["stop_batch"].to_numpy(), "runs_used": used,
            "decision": dec[f"decision_{side}"].to_numpy(),
        }))  # fmt: skip
    out = pd.concat(parts, ignore_index=True)
    return out.loc[:, [*RESULT_COLUMNS, "stop_batch", "runs_used", "decision"]]
