"""Plan, run and collect twin simulations in prefix-tree form.

Every action sequence a_1:t used by a hypothesis gets runs from the same m
initial states: the first m stays of D in the order of a keyed hash of their X_0
(``inference.order.x0_keys``, keyed by the study seed), i.e. a uniformly random
m-subset of D's stays in a uniformly random order that no stay id and no row
order can change (so the runs of one sequence have distinct X_0, are i.i.d., and
their X_0 law is D's stays' law, repeat stays of a patient included). Because a twin is
non-anticipating (hour s depends on a_1:s only), the runs of a_1:s are the
first s hours of the runs of any extension a_1:t from the same X_0. Results
are therefore stored per node = (prefix a_1:s, X_0): one row holding hour s.
Only the leaves of the prefix tree are simulated; their hours fill every node
on their path. Shards group leaves by first action, so no node is split
across shards.
"""

from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np
import pandas as pd

from twinfalsify.design import ActionBins
from twinfalsify.inference.order import x0_keys
from twinfalsify.schema import FEATURES, STAY_ID, ContractError, mark_implausible
from twinfalsify.stored_runs import (  # noqa: F401 - the stored runs' contract, re-exported
    FAILING_WARN,
    NODE_COLUMNS,
    WORKER_STATS,
    TwinPlan,
    failing_patients,
    load_nodes,
    node_name,
    parse_node,
    restart_warning,
    status_summary,
    worker_summary,
    x0_frame,
)
from twinfalsify.twins.base import Twin

log = logging.getLogger("twinfalsify")
def plan_twin_runs(
    hyps: pd.DataFrame,
    d_stay_ids: np.ndarray,
    runs_per_sequence: int | None,
    n_shards: int,
    seed: int,
    x0: np.ndarray | None = None,
    x0_stays: list[int] | None = None,
) -> TwinPlan:
    """X_0: the first m of D's stays in the order of a keyed hash of their X_0 (``x0``: the
    (len(d_stay_ids), F) t = 0 features aligned with ``d_stay_ids``; module doc). Equal X_0
    tie and are listed by stay id (their runs are interchangeable for a deterministic twin).
    Without ``x0`` (plans built by hand): the first m of a seeded permutation of the sorted
    stay ids. Either way every stay is drawn with the same probability m / |D|, so the X_0
    law is D's stays' law; a patient with several stays is drawn as often as those stays.
    ``x0_stays`` (``twin_runs.x0_stays``): exactly these stays of D, in this order, no draw
    (the X_0 a recording of a real engine covers); ``runs_per_sequence`` must be None.
    """
    ids = np.asarray(d_stay_ids, dtype=np.int64)
    if len(np.unique(ids)) != len(ids):
        raise ContractError("twin plan: the stay ids of D must be distinct")
    if x0_stays is not None:
        if runs_per_sequence:
            raise ContractError("twin_runs.x0_stays names the X_0 stays: set "
                                "twin_runs.runs_per_sequence to null")
        missing = sorted(set(int(s) for s in x0_stays) - set(ids.tolist()))
        if missing:
            raise ContractError(f"twin_runs.x0_stays: stay(s) {missing} are not in D "
                                f"(the test set of the split)")
        return _plan(hyps, [int(s) for s in x0_stays], n_shards, seed)
    m = len(ids) if not runs_per_sequence else min(int(runs_per_sequence), len(ids))
    if runs_per_sequence and int(runs_per_sequence) > len(ids):
        log.warning(
            "twin_runs.runs_per_sequence: %d asked, but D has only %d stays (X_0 are drawn "
            "without replacement): using %d runs per sequence",
            int(runs_per_sequence), len(ids), len(ids),
        )
    if x0 is None:
        perm = np.random.default_rng(seed).permutation(np.sort(ids))
    else:
        x0 = np.asarray(x0, dtype=float)
        if x0.ndim != 2 or len(x0) != len(ids):
            raise ContractError(f"twin plan: x0 must have one row per stay of D ({len(ids)}), "
                                f"got shape {x0.shape}")
        perm = ids[np.lexsort((ids, x0_keys(x0, seed)))]
    return _plan(hyps, [int(s) for s in perm[:m]], n_shards, seed)


def _plan(hyps: pd.DataFrame, x0: list[int], n_shards: int, seed: int) -> TwinPlan:
    """The plan for the X_0 stays ``x0``: the prefix tree of the hypotheses' sequences, its
    leaves grouped by first action and balanced over the shards."""
    seqs = {tuple(int(a) for a in s) for s in hyps["actions"].tolist()}
    nodes = {s[:k] for s in seqs for k in range(1, len(s) + 1)}
    leaves = sorted(s for s in nodes if not any(o[: len(s)] == s and o != s for o in nodes))
    by_first: dict[int, list[tuple[int, ...]]] = {}
    for leaf in leaves:
        by_first.setdefault(leaf[0], []).append(leaf)
    n_shards = max(1, int(n_shards))
    shards: list[list[str]] = [[] for _ in range(n_shards)]
    load = np.zeros(n_shards)
    for _, group in sorted(by_first.items(), key=lambda kv: (-sum(map(len, kv[1])), kv[0])):
        j = int(np.argmin(load))
        shards[j].extend(node_name(s) for s in group)
        load[j] += sum(map(len, group))
    return TwinPlan(
        x0_stay_ids=list(x0),
        seed=int(seed),
        shards=shards,
        nodes=sorted(node_name(s) for s in nodes),
    )


def shard_runtime_minutes(plan: dict, shard: int, seconds_per_hour: float,
                          timeout_s: float | None, workers: int) -> int:
    """Cluster time limit (minutes) for one twin shard job, from the plan.

    Each leaf sequence of the shard is simulated for every planned X_0 (m runs of len(leaf)
    hours; the prefix tree shares prefixes, so this is an upper bound). A run is budgeted
    ``seconds_per_hour`` x its hours, but never more than ``timeout_s`` (a twin served over
    the protocol: the runner kills a run at that limit, and retries are rare). The total
    is spread over ``workers``, doubled for safety, and at least 10 minutes.
    """
    m = len(plan["x0_stay_ids"])
    per_run = [len(str(leaf).split("-")) * float(seconds_per_hour)
               for leaf in plan["shards"][int(shard)]]
    if timeout_s is not None:
        per_run = [min(s, float(timeout_s)) for s in per_run]
    seconds = m * sum(per_run) / max(int(workers), 1)
    return max(10, int(2 * seconds / 60) + 1)


def plausible(res) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features, status, message) of a SimResult with every run that returned a value
    outside the trajectory contract's ranges failed as ``implausible``
    (schema.mark_implausible): the one place every stored run of every twin passes."""
    feats = np.array(res.features, dtype=float)
    status = np.array(res.status, dtype=object)
    message = np.array(res.message, dtype=object)
    mark_implausible(feats, status, message)
    return feats, status, message


def implausible_warning(twin: str, shard: int, n_bad: int, n_runs: int,
                        example: str) -> str | None:
    """One console line when ``n_bad`` > 0 of a shard's ``n_runs`` runs are ``implausible``.

    A twin answering in the wrong unit (temperature in F) fails every run this way; saying
    so at the shard saves finding it in the study's summary. ``example``: one run's message.
    """
    if not n_bad:
        return None
    return (f"WARNING: twin {twin} shard {shard}: {n_bad} of {n_runs} runs implausible "
            f"(counted as failed), e.g. {example}")


def simulate_jobs(
    twin: Twin, jobs: list[tuple[tuple[int, ...], np.ndarray]], x0: pd.DataFrame,
    seeds: np.ndarray, actions: ActionBins, log, continue_while: list | None = None,
) -> list:
    """One SimResult-like (features, status, message, clamped) per job (sequence, rows):
    the rows (positions in x0 / seeds) simulated along the action sequence, implausible
    values failed (``plausible``).

    A ProtocolTwin gets every job in one call (shorter sequences padded with all-NaN
    hours, which the runner reads as a shorter run): one worker pool, and the runner's
    seed-grouped, prefix-ordered schedule lets a save/restore twin (Pulse) branch shared
    prefixes instead of simulating them again for every sequence. In-process twins get one
    vectorised call per job. ``continue_while`` (per job, per row: ``runs.truncation`` box
    paths) goes to a protocol twin that can truncate; in-process twins ignore it.
    """
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    jobs = [(seq, np.asarray(rows, dtype=np.int64)) for seq, rows in jobs]
    if not all(rows.size for _, rows in jobs):  # a job without rows: an empty result
        full = [k for k, (_, rows) in enumerate(jobs) if rows.size]
        cw = None if continue_while is None else [continue_while[k] for k in full]
        got = dict(zip(full, simulate_jobs(twin, [jobs[k] for k in full], x0, seeds, actions,
                                           log, cw), strict=True))
        none = np.empty(0, dtype=object)
        return [got.get(k, (np.empty((0, len(seq), len(FEATURES))), none, none, none))
                for k, (seq, _) in enumerate(jobs)]
    if isinstance(twin, ProtocolTwin) and jobs:
        t = max(len(seq) for seq, _ in jobs)
        n = sum(rows.size for _, rows in jobs)
        doses = np.full((n, t, 2), np.nan)
        cuts = np.cumsum([0] + [rows.size for _, rows in jobs])
        for (seq, _), a, b in zip(jobs, cuts[:-1], cuts[1:], strict=True):
            doses[a:b, : len(seq)] = actions.doses(np.asarray(seq))
        every = np.concatenate([rows for _, rows in jobs])
        kw = {}
        if continue_while is not None:
            kw["continue_while"] = [paths for job in continue_while for paths in job]
        res = twin.simulate(x0.iloc[every].reset_index(drop=True), doses, seeds[every], **kw)
        if res.features.shape[:2] != (n, t):
            raise ContractError(
                f"twin {twin.name}: simulate returned features of shape {res.features.shape}, "
                f"expected {(n, t, len(FEATURES))}"
            )
        feats, status, message = plausible(res)
        clamped = np.asarray(res.clamped, dtype=object)
        return [(feats[a:b, : len(seq)], status[a:b], message[a:b], clamped[a:b])
                for (seq, _), a, b in zip(jobs, cuts[:-1], cuts[1:], strict=True)]
    out = []
    start = time.monotonic()
    done = 0
    for i, (seq, rows) in enumerate(jobs, 1):
        doses = np.broadcast_to(actions.doses(np.asarray(seq)), (rows.size, len(seq), 2)).copy()
        res = twin.simulate(x0.iloc[rows].reset_index(drop=True), doses, seeds[rows])
        if res.features.shape != (rows.size, len(seq), len(FEATURES)):
            raise ContractError(
                f"twin {twin.name}: simulate returned features of shape {res.features.shape}, "
                f"expected {(rows.size, len(seq), len(FEATURES))}"
            )
        feats, status, message = plausible(res)
        out.append((feats, status, message, np.asarray(res.clamped, dtype=object)))
        done += rows.size
        if log is not None:
            rate = done / max(time.monotonic() - start, 1e-9)
            print(f"[twin {twin.name}] sequence {i}/{len(jobs)} ({node_name(seq)}): "
                  f"{rows.size} runs, {rate:,.0f} runs/s", file=log, flush=True)
    return out


def run_shard(
    twin: Twin,
    plan: TwinPlan,
    shard: int,
    x0: pd.DataFrame,
    actions: ActionBins,
    log=sys.stderr,
) -> pd.DataFrame:
    """Simulate the shard's leaves for all planned X_0; one row per (node, X_0).

    Node a_1:s of run i holds hour s of any simulated leaf extending a_1:s
    (a twin is non-anticipating). A run that failed at hour h > s still gives
    a usable node a_1:s (status ok); nodes from hour h on carry the failure
    (status, message). When several leaves share a node, an ok value wins
    over a failure (e.g. one leaf's run timed out, another's did not); for a
    deterministic twin all ok values agree.
    """
    if not 0 <= shard < len(plan.shards):
        raise ContractError(f"twin shard {shard} does not exist (plan has {len(plan.shards)})")
    seeds = plan.run_seeds()
    m = len(x0)
    frames: dict[str, pd.DataFrame] = {}
    leaves = plan.shards[shard]  # may be empty: fewer first actions than shards
    jobs = [(parse_node(leaf), np.arange(m)) for leaf in leaves]
    results = simulate_jobs(twin, jobs, x0, seeds, actions, log)
    status = np.concatenate([r[1] for r in results]) if results else np.empty(0, object)
    bad = np.flatnonzero(status == "implausible")
    if bad.size:
        message = np.concatenate([r[2] for r in results])
        line = implausible_warning(twin.name, shard, bad.size, status.size, message[bad[0]])
        if log is None or log is sys.stderr:  # in a rule: its log file and the console
            logging.getLogger("twinfalsify").warning(line)
        else:
            print(line, file=log, flush=True)
    for (seq, _), (feats, status, message, clamped) in zip(jobs, results, strict=True):
        for s in range(1, len(seq) + 1):
            name = node_name(seq[:s])
            vals = feats[:, s - 1, :]
            done = np.isfinite(vals).all(axis=1)
            f = pd.DataFrame(vals, columns=list(FEATURES))
            f.insert(0, "clamped", np.asarray(clamped, dtype=object))
            f.insert(0, "message", np.where(done, "", np.asarray(message, dtype=object)))
            f.insert(0, "status", np.where(done, "ok", np.where(status == "ok", "error", status)))
            f.insert(0, "init_stay_id", x0[STAY_ID].to_numpy(np.int64))
            f.insert(0, "t", s)
            f.insert(0, "node", name)
            old = frames.get(name)
            if old is None:
                frames[name] = f
            else:  # shared node: fill the old failures this leaf completed
                fill = (old["status"] != "ok").to_numpy() & done
                for col in ("status", "message", "clamped", *FEATURES):
                    old.loc[fill, col] = f.loc[fill, col].to_numpy()
    if not frames:
        return pd.DataFrame(columns=list(NODE_COLUMNS))
    return pd.concat(frames.values(), ignore_index=True)


def twin_hellos(hellos: list[dict | None]) -> dict:
    """What the twin said it is, per shard (``{"twin": {name, version}}``, None entries:
    in-process twins), for run_summary.json; a warning when shards disagree (a shard kept
    from before the twin changed while others were rerun)."""
    known = [h for h in hellos if h]
    if not known:
        return {}
    distinct = {json.dumps(h, sort_keys=True) for h in known}
    if len(distinct) == 1:
        return {"twin": known[0]}
    log.warning("WARNING: twin runs come from different twin versions: %s", sorted(distinct))
    return {"twin": {"per_shard": hellos}}


