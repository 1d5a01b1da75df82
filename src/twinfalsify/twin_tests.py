"""One path from a study's stored files to the tests' inputs and p-values.

Every consumer of a twin's tests — the tests rule, the study summary, ``explain``, the
figures (sensitivity, longitudinal, histograms), the calibration harness — builds its
hypothesis samples with :func:`twin_samples` (in memory) or :func:`load_twin_tests` (from a
study's files), and its p-values with :func:`study_results`, so what each of them shows is
what the tests rule tested: the same entry rule (``bounds.path_boxes``), the failed twin
runs at their places (``inference.failures``), the same methods, level and correction.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify import bounds
from twinfalsify.design import StateBins
from twinfalsify.falsify import RESULT_COLUMNS, make_methods, run_tests
from twinfalsify.inference.order import hypothesis_keys
from twinfalsify.inference.samples import HypothesisSamples, ObservationalSide
from twinfalsify.inference.sensitivity import sensitivity_sweep
from twinfalsify.io import read_json, read_parquet
from twinfalsify.schema import ContractError, TwinNodes
from twinfalsify.stored_runs import TwinPlan, load_nodes, x0_frame

# the columns of a study's results.parquet: run_tests' and the order seed's
STUDY_RESULT_COLUMNS = (*RESULT_COLUMNS, "order_seed", "seed_fragile")
# tests whose p-values depend on a seed (the betting test's order, the bootstrap's resamples)
SEEDED_METHODS = ("betting", "bootstrap")
# the files of a study a twin's tests read (keys of the rules' ``input``)
STORED_INPUTS = ("d", "bins", "hypotheses", "counts", "follow", "plan", "runs")


@dataclass(frozen=True)
class TwinTests:
    """The inputs of one twin's tests, as the tests rule builds them."""

    hyps: pd.DataFrame
    samples: HypothesisSamples  # failed runs at their places
    n_failed: np.ndarray  # (H,) failed runs that could have entered
    states: StateBins
    nodes: TwinNodes
    d: pd.DataFrame
    run_status: Mapping[str, int]  # twin node-runs per status (runs.parquet)

    def results(self, testing: Mapping[str, Any], seed: int,
                samples: HypothesisSamples | None = None) -> pd.DataFrame:
        """The results table of these tests (``samples``: e.g. a widened range instead)."""
        return study_results(self.hyps, self.samples if samples is None else samples,
                             self.n_failed, testing, seed)


def twin_samples(hyps: pd.DataFrame, obs: ObservationalSide, nodes: TwinNodes,
                 states: StateBins) -> tuple[HypothesisSamples, np.ndarray]:
    """(samples, n_failed): both sides of every hypothesis, the failed runs at their places."""
    twin = bounds.twin_runs(hyps, nodes, states)
    return bounds.hypothesis_samples(hyps, obs, twin), twin.n_failed


def study_results(hyps: pd.DataFrame, samples: HypothesisSamples, n_failed: np.ndarray,
                  testing: Mapping[str, Any], seed: int) -> pd.DataFrame:
    """The results table for the config's ``testing`` section (validated: every key set).

    ``testing.order_seed`` (None: the study's data order) keys the order-dependent tests'
    randomisation and is recorded in column ``order_seed``; with ``testing.seed_check`` K > 0
    those tests are rerun under K other order seeds and column ``seed_fragile`` marks the
    decisions that change under any of them (False for tests that use no randomisation).
    """
    order_seed = testing["order_seed"]
    res = _results(hyps, samples, n_failed, testing, seed, order_seed)
    res["order_seed"] = pd.array([order_seed] * len(res), dtype="Int64")
    fragile = np.zeros(len(res), dtype=bool)
    seeded = res["method"].isin(SEEDED_METHODS).to_numpy()
    if testing["seed_check"] and seeded.any():
        base = int(seed) if order_seed is None else int(order_seed)
        spec = {k: v for k, v in testing["methods"].items() if k in SEEDED_METHODS}
        for k in range(1, int(testing["seed_check"]) + 1):
            other = (base + k) % (1 << 32)
            again = _results(hyps, samples, n_failed, {**testing, "methods": spec}, other,
                             other)
            flip = res.loc[seeded, ["hyp_id", "side", "method"]].merge(
                again[["hyp_id", "side", "method", "rejected"]], how="left", validate="1:1")
            fragile[seeded] |= flip["rejected"].to_numpy(bool) != res.loc[
                seeded, "rejected"].to_numpy(bool)
    res["seed_fragile"] = fragile
    return res


def order_seeded(samples: HypothesisSamples, seed: int, order_seed: int | None
                 ) -> tuple[HypothesisSamples, int]:
    """(samples, methods' seed) under an order seed: the hypotheses keyed by it and the
    seeded methods seeded by it (None: the study's data order and seed)."""
    if order_seed is None:
        return samples, int(seed)
    return (replace(samples, keys=hypothesis_keys(len(samples), int(order_seed))),
            int(order_seed))


def _results(hyps, samples, n_failed, testing, seed, order_seed) -> pd.DataFrame:
    """run_tests under an order seed (None: the study's order and seed)."""
    samples, seed = order_seeded(samples, seed, order_seed)
    return run_tests(
        hyps, samples, n_failed,
        make_methods(testing["methods"], seed, alpha=float(testing["alpha"])),
        alpha=float(testing["alpha"]), correction=testing["correction"],
        failed_runs=testing["failed_runs"],
    )  # fmt: skip


def outcome_sizes(samples: HypothesisSamples) -> pd.DataFrame:
    """Per hypothesis (rows in the samples' order), the size of a difference the clipped
    tests cannot show: the twin's unclipped mean and median and its shares strictly below
    y_lo and above y_up, beside the same of the data's followers (NaN without outcomes)."""
    out = {}
    for part, ragged in (("twin", samples.twin), ("data", samples.follow)):
        gid = ragged.group_ids()
        h = len(samples.y_lo)
        v = ragged.values
        size = np.bincount(gid, minlength=h).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[f"{part}_mean"] = np.bincount(gid, weights=v, minlength=h) / size
            out[f"{part}_below"] = np.bincount(gid, weights=v < samples.y_lo[gid],
                                               minlength=h) / size
            out[f"{part}_above"] = np.bincount(gid, weights=v > samples.y_up[gid],
                                               minlength=h) / size
        out[f"{part}_median"] = np.array(
            [float(np.median(ragged.group(k))) if size[k] else np.nan for k in range(h)])
    cols = [f"{p}_{s}" for p in ("twin", "data") for s in ("mean", "median", "below", "above")]
    return pd.DataFrame(out)[cols]


def load_twin_tests(paths: Mapping[str, str | Path]) -> TwinTests:
    """One twin's test inputs from a study's files (keys :data:`STORED_INPUTS`)."""
    missing = set(STORED_INPUTS) - set(paths)
    if missing:
        raise ContractError(f"load_twin_tests: missing input path(s) {sorted(missing)}")
    hyps, obs = bounds.read_observational_side(paths["hypotheses"], paths["counts"],
                                               paths["follow"])
    d = read_parquet(paths["d"], "D")
    plan = TwinPlan.from_json(read_json(paths["plan"]))
    states = StateBins.from_json(read_json(paths["bins"]))
    runs = read_parquet(paths["runs"], "twin runs")
    nodes = load_nodes(runs, plan, x0_frame(d, plan.x0_stay_ids))
    samples, n_failed = twin_samples(hyps, obs, nodes, states)
    return TwinTests(
        hyps=hyps, samples=samples, n_failed=n_failed, states=states, nodes=nodes, d=d,
        run_status={str(k): int(v) for k, v in runs["status"].value_counts().items()},
    )  # fmt: skip


def sensitivity(tt: TwinTests, testing: Mapping[str, Any], seed: int, deltas: list[float],
                progress=None, results: pd.DataFrame | None = None) -> pd.DataFrame:
    """The sensitivity sweep (``inference.sensitivity``) of these tests: at Delta = 0 exactly
    the decisions of :meth:`TwinTests.results`; counted per family (kind) and outcome.

    ``results``: the tests' results table for the same ``testing`` (the study's
    results.parquet); its p-values are the sweep's at Delta = 0 instead of testing again.
    """
    alpha = float(testing["alpha"])
    samples, seed = order_seeded(tt.samples, seed, testing["order_seed"])
    methods = make_methods(testing["methods"], seed, alpha=alpha)
    t0 = time.perf_counter()
    if progress is not None:
        progress(f"sensitivity sweep: {len(deltas)} Delta values x {len(methods)} methods "
                 f"({', '.join(methods)}), corrected within each kind")
    table = sensitivity_sweep(
        samples, deltas, methods, alpha, testing["correction"],
        group=tt.hyps["outcome"].to_numpy(), n_failed=tt.n_failed,
        failed_runs=testing["failed_runs"], family=tt.hyps["kind"].to_numpy(),
        progress=progress, at_zero=None if results is None else stored_pvalues(
            results, tt.hyps["hyp_id"].to_numpy(), list(methods)),
    )  # fmt: skip
    if progress is not None:
        progress(f"sensitivity sweep done in {time.perf_counter() - t0:.1f} s")
    return table.rename(columns={"family": "kind"})


def stored_pvalues(results: pd.DataFrame, hyp_ids: np.ndarray, methods: list[str]
                   ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per method, (p_lo, p_up) of a results table in the order of ``hyp_ids``; one error
    when a (hypothesis, side, method) is missing or listed twice."""
    p = results.set_index(["method", "side", "hyp_id"])["p_value"].sort_index()
    if not p.index.is_unique:
        raise ContractError("results: a (method, side, hyp_id) is listed twice")
    out = {}
    for name in methods:
        try:
            out[name] = tuple(p.loc[(name, side)].reindex(hyp_ids).to_numpy(float)
                              for side in ("lo", "up"))
        except KeyError:
            raise ContractError(f"results: no p-values of method {name!r}") from None
        if any(np.isnan(v).any() for v in out[name]):
            raise ContractError(f"results: method {name!r} misses some hypotheses' p-values")
    return out
