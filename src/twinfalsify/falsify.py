"""Run every configured test method on every hypothesis and correct for multiplicity."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.inference import registry
from twinfalsify.inference.failures import MODES as FAILED_RUN_MODES
from twinfalsify.inference.failures import failure_pvalues
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples
from twinfalsify.schema import ContractError

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]

RESULT_COLUMNS = (
    "hyp_id", "kind", "outcome", "t", "side", "method", "n", "n_follow", "nhat", "n_failed",
    "failed_runs", "y_lo", "y_up", "q_lo_hat", "q_up_hat", "q_twin_hat", "q_obs_hat", "propensity",
    "p_value", "p_floor", "rejected", "correction", "alpha",
)  # fmt: skip


def make_methods(spec: Mapping[str, Mapping[str, Any]], seed: int) -> dict[str, Method]:
    """Config ``testing.methods: {name: {options}}`` -> callables (see inference.registry)."""
    return {name: registry.make(name, opts, seed) for name, opts in spec.items()}


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
        p_lo, p_up = failure_pvalues(method, samples, np.asarray(n_failed), failed_runs)
        for side, p in (("lo", p_lo), ("up", p_up)):
            part = base.copy()
            part.insert(4, "side", side)
            part.insert(5, "method", name)
            part["p_value"] = np.asarray(p, float)
            # True: p is a reporting floor (bootstrap: every resample separated)
            part["p_floor"] = registry.floored(name, method, part["p_value"].to_numpy())
            parts.append(part)
    out = pd.concat(parts, ignore_index=True)
    out["rejected"] = False
    for _, idx in out.groupby(["method", "kind"]).indices.items():
        out.loc[out.index[idx], "rejected"] = correct(
            out["p_value"].to_numpy()[idx], alpha, correction
        )
    out["correction"] = correction
    out["alpha"] = alpha
    return out.loc[:, list(RESULT_COLUMNS)]
