"""Run the statistical pipeline in-process on a synthetic study (no Snakemake)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from twinfalsify import bounds, design, twin_tests
from twinfalsify.falsify import make_methods, run_tests
from twinfalsify.runs import plan as tp
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURES, STAY_ID, to_array
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.split import split_stays


@dataclass
class Study:
    d0: pd.DataFrame
    d: pd.DataFrame
    actions: design.ActionBins
    states: design.StateBins
    hyps: pd.DataFrame
    obs: bounds.ObservationalSide
    plan: tp.TwinPlan
    x0: pd.DataFrame


def build_study(
    n_stays: int,
    seed: int,
    *,
    d0_fraction: float = 0.1,
    min_support: int = 10,
    runs: int | None = 2000,
    world_cfg: dict | None = None,
) -> Study:
    world = SyntheticWorld.from_config({"n_stays": n_stays, **(world_cfg or {})})
    traj = world.sample_observational(seed)
    d0, d = split_stays(traj, d0_fraction, seed)
    actions, states, hyps, _ = design.design_on_d0(d0, min_support=min_support)
    obs = bounds.observational_side(
        hyps, to_array(d, FEATURES), design.action_codes(d, actions), states, order_seed=seed
    )
    ids = d[STAY_ID].unique()
    plan = tp.plan_twin_runs(hyps, ids, runs, 2, seed,
                             x0=tp.x0_frame(d, ids.tolist())[list(FEATURES)].to_numpy(float))
    return Study(d0, d, actions, states, hyps, obs, plan, tp.x0_frame(d, plan.x0_stay_ids))


def evaluate_twin(
    study: Study, name: str, spec: dict, tmp_path, *, methods=None, alpha: float = 0.05
) -> pd.DataFrame:
    d0_path = tmp_path / "d0.parquet"
    study.d0.to_parquet(d0_path)
    ctx = {"source": {"kind": "synthetic", "synthetic": {"n_stays": 20}}, "d0": str(d0_path)}
    samples, n_failed = twin_samples(study, make_twin(name, spec, ctx))
    return run_tests(
        study.hyps, samples, n_failed, make_methods(methods or {"hoeffding": {}}, 0), alpha=alpha
    )


def twin_samples(study: Study, twin):
    """(hypothesis samples, failed runs per hypothesis) of ``twin`` run in-process on every
    shard of the study's plan."""
    import io

    runs = pd.concat(
        [
            tp.run_shard(twin, study.plan, k, study.x0, study.actions, log=io.StringIO())
            for k in range(len(study.plan.shards))
        ],
        ignore_index=True,
    )
    nodes = tp.load_nodes(runs, study.plan, study.x0)
    return twin_tests.twin_samples(study.hyps, study.obs, nodes, study.states)


class OneCellBins(design.StateBins):
    """State bins with one base cell, where 'above' means outcome > 0: hand-made B-sets for
    tests of which twin runs can enter a hypothesis."""

    def __init__(self):
        pass

    def base_codes(self, x0):
        return np.zeros(len(x0), dtype=np.int64)

    def above(self, outcome, values, t):
        return (np.asarray(values) > 0).astype(np.int64)
