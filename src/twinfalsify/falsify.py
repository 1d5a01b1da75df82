"""Run every configured test method on every hypothesis and correct for multiplicity."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.bounds import hypothesis_paths, reachable, twin_runs_indexed
from twinfalsify.design import StateBins
from twinfalsify.inference import registry
from twinfalsify.inference.capital import C_TRUNC
from twinfalsify.inference.failures import MODES as FAILED_RUN_MODES
from twinfalsify.inference.failures import failure_pvalues
from twinfalsify.inference.multiple_testing import correct_within
from twinfalsify.inference.samples import HypothesisSamples, ObservationalSide, TwinRuns
from twinfalsify.inference.sequential import (
    HOLM_AWARE,
    AdaptiveOutcome,
    SequentialState,
    correct_by_family,
    node_needs,
    node_runs,
    paper_hours,
    run_to_stop,
)
from twinfalsify.schema import ContractError, TwinNodes

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]

RESULT_COLUMNS = (
    "hyp_id", "kind", "outcome", "t", "side", "method", "n", "n_follow", "nhat", "n_failed",
    "failed_runs", "y_lo", "y_up", "q_lo_hat", "q_up_hat", "q_twin_hat", "q_obs_hat", "propensity",
    "p_value", "p_floor", "refused", "rejected", "correction", "alpha",
)  # fmt: skip


def make_methods(spec: Mapping[str, Mapping[str, Any]], seed: int,
                 alpha: float = 0.05) -> dict[str, Method]:
    """Config ``testing.methods: {name: {options}}`` -> callables (see inference.registry);
    ``alpha``: the family's level ``testing.alpha``, which the betting test tunes to."""
    return {name: registry.make(name, opts, seed, alpha) for name, opts in spec.items()}


def run_tests(
    hyps: pd.DataFrame,
    samples: HypothesisSamples,
    n_failed: np.ndarray,
    methods: Mapping[str, Method],
    *,
    alpha: float = 0.05,
    correction: str = "holm",
    failed_runs: str = "conservative",
) -> pd.DataFrame:
    """Long results table: one row per (hypothesis, side, method).

    failed_runs: how the n_failed twin runs per hypothesis count
    (``inference.failures``): "conservative" = worst case over what they could
    have produced (default), "drop" = left out (the paper's behaviour).

    The correction runs within each family = (method, kind): causal-bound and
    Manski hypotheses are two separate analyses (the paper's two columns), and
    both sides H_lo, H_up of every parameter set are in the family.
    """
    if failed_runs not in FAILED_RUN_MODES:
        raise ContractError(
            f"testing.failed_runs: unknown mode {failed_runs!r}; choose one of "
            f"{', '.join(FAILED_RUN_MODES)}"
        )
    base = pd.DataFrame({
        "hyp_id": hyps["hyp_id"].to_numpy(), "kind": hyps["kind"].to_numpy(),
        "outcome": hyps["outcome"].to_numpy(), "t": hyps["t"].to_numpy(),
        "n": samples.n, "n_follow": samples.n_follow, "nhat": samples.nhat,
        "n_failed": np.asarray(n_failed), "failed_runs": failed_runs,
        "y_lo": samples.y_lo, "y_up": samples.y_up,
        "q_lo_hat": samples.q_lo_hat, "q_up_hat": samples.q_up_hat,
        "q_twin_hat": samples.q_twin_hat, "q_obs_hat": samples.q_obs_hat,
        "propensity": samples.propensity,
    })  # fmt: skip
    parts = []
    for name, method in methods.items():
        p_lo, p_up = failure_pvalues(method, samples, np.asarray(n_failed), failed_runs,
                                     families=hyps["kind"].to_numpy())
        for side, p in (("lo", p_lo), ("up", p_up)):
            part = base.copy()
            part.insert(4, "side", side)
            part.insert(5, "method", name)
            part["p_value"] = np.asarray(p, float)
            # True: p is a reporting floor (bootstrap: every resample separated)
            part["p_floor"] = registry.floored(name, method, part["p_value"].to_numpy())
            # True: the method did not test it (p = 1 by rule: too few samples)
            part["refused"] = registry.refused(name, method, samples.n, samples.nhat)
            parts.append(part)
    out = pd.concat(parts, ignore_index=True)
    families = (out["method"].astype(str) + "\x00" + out["kind"].astype(str)).to_numpy()
    out["rejected"] = correct_within(out["p_value"].to_numpy(), families, alpha, correction)
    out["correction"] = correction
    out["alpha"] = alpha
    return out.loc[:, list(RESULT_COLUMNS)]


def adaptive_test(
    hyps: pd.DataFrame,
    obs: ObservationalSide,
    nodes: TwinNodes,
    states: StateBins,
    *,
    batch_size: int,
    alpha: float = 0.05,
    correction: str = "holm",
    budget: int | None = None,
    seed: int = 0,
    c: float = C_TRUNC,
    holm_aware: bool | None = None,
    shards: np.ndarray | None = None,
    curtail: float = 0.0,
    combine: str = "union",
    failed_runs: str = "conservative",
) -> AdaptiveOutcome:
    """The adaptive procedure on in-memory twin nodes, runs revealed batch by batch.

    Twin-hours with prefix reuse: node a_1:s costs one hour per run simulated for it, i.e.
    per run revealed to a hypothesis whose path uses it and whose B_0 holds that run's X_0
    (``node_needs``); the fixed scheme simulates every node for the budget.
    ``holm_aware`` (default: on for Holm and Bonferroni, off otherwise): futility at the
    Holm threshold a side can still face (``SequentialState``); ``shards`` (H,): count the
    futile sides per shard as the workflow's parallel shards do (default: whole family);
    ``combine``: "union" (the only rule; "product" was withdrawn, ``PRODUCT_REMOVED``);
    ``failed_runs``: "conservative" (default: valid whatever the failed runs would have
    produced) or "drop".
    """
    m = nodes.x0.shape[0]
    budget = m if budget is None else int(budget)
    if not 0 <= budget <= m:
        raise ValueError(f"adaptive_test: budget must be in [0, {m}] runs, got {budget}")
    runs = twin_runs_indexed(hyps, nodes, states)
    if holm_aware is None:
        holm_aware = correction in HOLM_AWARE
    st = SequentialState(hyps, obs, states, budget, int(batch_size), alpha, seed, c,
                         holm_aware=bool(holm_aware), holm_scope=shards, curtail=curtail,
                         combine=combine, failed_runs=failed_runs)
    run_to_stop(st, runs)
    return outcome(hyps, nodes, states, st, runs, alpha, correction)


def outcome(hyps: pd.DataFrame, nodes: TwinNodes, states: StateBins, st: SequentialState,
            runs: TwinRuns, alpha: float, correction: str) -> AdaptiveOutcome:
    """The :class:`AdaptiveOutcome` of a state run to its stops on in-memory ``nodes``."""
    p_lo, p_up, nhat = st.p_values(runs)
    per_hyp = st.runs_used()
    paths = hypothesis_paths(hyps, nodes.index)
    n_nodes = len(nodes.index)
    used = node_needs(paths, per_hyp, runs.in_b0, n_nodes,
                      reachable(hyps, nodes, states)).sum(axis=1)
    whole = node_needs(paths, per_hyp, runs.in_b0, n_nodes).sum()
    rej_lo, rej_up = correct_by_family(hyps, p_lo, p_up, alpha, correction)
    return AdaptiveOutcome(
        p_lo, p_up, st.stop_batch.copy(), used, per_hyp, st.side.copy(), nhat, rej_lo, rej_up,
        int(used.sum()), int(n_nodes * st.budget),
        int(node_runs(paths, per_hyp, n_nodes).sum()), paper_hours(hyps, st.budget), int(whole),
    )
