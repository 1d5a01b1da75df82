"""A study's stored twin runs read back: the plan, the node table as arrays, run summaries.

The twin stage (``runs``) writes these files; the tests, the summary and the figures read
them here, without importing the executor that made them.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from twinfalsify import noise
from twinfalsify.schema import FEATURES, STAY_ID, ContractError, TwinNodes

NODE_COLUMNS = ("node", "t", "init_stay_id", "status", "message", "clamped", *FEATURES)


def node_name(seq: Iterable[int]) -> str:
    return "-".join(str(int(a)) for a in seq)


def parse_node(name: str) -> tuple[int, ...]:
    return tuple(int(a) for a in name.split("-"))


@dataclass(frozen=True)
class TwinPlan:
    x0_stay_ids: list[int]
    seed: int
    shards: list[list[str]]  # leaf sequences (node names) per shard
    nodes: list[str]  # every node, sorted

    def to_json(self) -> dict:
        return {
            "x0_stay_ids": self.x0_stay_ids,
            "seed": self.seed,
            "shards": self.shards,
            "nodes": self.nodes,
        }

    @classmethod
    def from_json(cls, data: dict) -> TwinPlan:
        return cls(**data)

    def run_seeds(self) -> np.ndarray:
        """One uint64 seed per X_0, shared by every sequence (so prefixes coincide).

        Keyed by the run's position in the plan's X_0 list, not by its stay id: the list is
        ordered by a keyed hash of X_0 (``plan_twin_runs``), so a stochastic twin gets the
        same noise for the same X_0 under any numbering of the stays (two stays with equal
        X_0 may swap positions, which leaves the set of (X_0, seed) pairs unchanged)."""
        return noise.combine(np.uint64(self.seed), np.arange(len(self.x0_stay_ids),
                                                             dtype=np.uint64))

    def hours(self) -> dict[str, int]:
        """Simulated twin-hours: paper's scheme (every sequence from scratch), leaves only
        (what in-process twins do), and the prefix-tree minimum (each node once)."""
        m = len(self.x0_stay_ids)
        leaves = [leaf for shard in self.shards for leaf in shard]
        return {
            "from_scratch": m * sum(len(parse_node(n)) for n in self.nodes),
            "leaves": m * sum(len(parse_node(n)) for n in leaves),
            "prefix_tree": m * len(self.nodes),
        }


def x0_frame(d: pd.DataFrame, stay_ids: list[int]) -> pd.DataFrame:
    """Real t = 0 rows of the given stays, in that order."""
    first = d[d["t"] == 0].set_index(STAY_ID)
    missing = set(stay_ids) - set(first.index)
    if missing:
        raise ContractError(
            f"twin plan: {len(missing)} initial stay(s) not in D, e.g. {sorted(missing)[:3]}"
        )
    return first.loc[stay_ids, list(FEATURES)].reset_index()


def load_nodes(runs: pd.DataFrame, plan: TwinPlan, x0: pd.DataFrame) -> TwinNodes:
    """Node table -> TwinNodes arrays aligned to the plan's X_0 order."""
    names = plan.nodes
    index = {parse_node(n): i for i, n in enumerate(names)}
    m = len(plan.x0_stay_ids)
    values = np.full((len(names), m, len(FEATURES)), np.nan)
    pos = {s: j for j, s in enumerate(plan.x0_stay_ids)}
    node_idx = runs["node"].map({n: i for i, n in enumerate(names)})
    if node_idx.isna().any():
        raise ContractError(
            f"twin runs hold node(s) not in the plan, e.g. "
            f"{runs.loc[node_idx.isna(), 'node'].iloc[0]}"
        )
    run_idx = runs["init_stay_id"].map(pos)
    ok = (runs["status"] == "ok").to_numpy()
    values[node_idx.to_numpy(int)[ok], run_idx.to_numpy(int)[ok], :] = runs.loc[
        ok, list(FEATURES)
    ].to_numpy(float)
    missing = len(names) * m - len(runs)
    if missing:
        raise ContractError(f"twin runs: {missing} (node, X_0) row(s) missing from the shards")
    return TwinNodes(index=index, values=values, x0=x0[list(FEATURES)].to_numpy(float))


WORKER_STATS = ("restarts", "crashes", "hangs", "protocol_breaks")


def restart_warning(twin: str, shard: int | None, stats: dict | None) -> str:
    """'' or one line when a shard (None: all shards) restarted its twin's workers.

    Retries hide a twin that crashes on some requests (every run may still end ok), so a
    restart is always worth a line: the twin is unstable, or its timeout_s is too short.
    """
    if not stats or not stats.get("restarts"):
        return ""
    where = f"shard {shard}" if shard is not None else "its shards"
    return (f"twin {twin}: {where} restarted the twin's workers {stats['restarts']} time(s) "
            f"(crashes {stats.get('crashes', 0)}, hangs {stats.get('hangs', 0)}, malformed "
            f"answers {stats.get('protocol_breaks', 0)}); see the shard logs for the stderr "
            "tails")


def worker_summary(per_shard: list[dict | None]) -> dict:
    """Worker restarts of a twin, per shard and in total, for run_summary.json ({} for an
    in-process twin, whose shards record none): {"per_shard": [...], "total": {...}}."""
    if not any(per_shard):
        return {}
    rows = [{k: int((st or {}).get(k, 0)) for k in WORKER_STATS} for st in per_shard]
    return {"per_shard": rows,
            "total": {k: sum(r[k] for r in rows) for k in WORKER_STATS}}


def status_summary(runs: pd.DataFrame) -> dict:
    counts = runs.groupby(["t", "status"]).size().unstack(fill_value=0)
    return json.loads(counts.to_json(orient="index"))


FAILING_WARN = 0.5  # a twin failing every run of more than this share of X_0 is warned about


def failing_patients(runs: pd.DataFrame, twin: str) -> str:
    """'' or a warning when more than FAILING_WARN of the X_0 got no ok run at all (a twin
    that refuses most patients tests little, however clean its exit)."""
    ok = runs["status"].eq("ok").groupby(runs["init_stay_id"]).any()
    failed = int((~ok).sum())
    if not len(ok) or failed / len(ok) <= FAILING_WARN:
        return ""
    top = runs.loc[runs["status"] != "ok", "status"].value_counts()
    what = ", ".join(f"{k} {v}" for k, v in top.head(3).items())
    return (f"twin {twin}: {failed} of {len(ok)} patients ({failed / len(ok):.0%}) got no ok "
            f"run (failed runs: {what}); its tests see the failures only as worst cases")
