"""One calibration replicate: a fresh synthetic cohort, its design, the oracle and biased twins,
every method's tests, the bound coverage, widths and the adaptive rows."""

from __future__ import annotations

import copy
import gc
import io
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from twinfalsify import bounds, design
from twinfalsify.bounds import twin_runs_indexed
from twinfalsify.calibration.config import (
    ADAPTIVE,
    ADAPTIVE_COLUMNS,
    COVERAGE_COLUMNS,
    NAIVE,
    TEST_COLUMNS,
    WIDTH_COLUMNS,
    CalibrationConfig,
)
from twinfalsify.falsify import make_methods, outcome, run_tests
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.sequential import (
    HOLM_AWARE,
    UNDECIDED,
    AdaptiveOutcome,
    SequentialState,
    run_to_stop,
)
from twinfalsify.runs import plan as tp
from twinfalsify.schema import FEATURES, OUTCOMES, STAY_ID, ContractError, to_array
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.split import split_stays
from twinfalsify.twin_tests import twin_samples
from twinfalsify.twins.builtin import OracleTwin


@dataclass
class Replicate:
    """One replicate's world, design, observational side and oracle runs."""

    seed: int
    world: SyntheticWorld
    d0: pd.DataFrame
    d: pd.DataFrame
    actions: design.ActionBins
    states: design.StateBins
    hyps: pd.DataFrame
    obs: bounds.ObservationalSide
    plan: tp.TwinPlan
    x0: pd.DataFrame
    nodes: bounds.TwinNodes  # oracle runs
    outcome_sd: dict[str, float]  # D0 SD of each outcome over hours 1..T


def build_replicate(cfg: CalibrationConfig, seed: int) -> Replicate:
    """World sample -> split -> design (D0) -> observational side (D) -> oracle runs."""
    world = SyntheticWorld(n_stays=cfg.n_stays, confounding=cfg.confounding)
    traj = world.sample_observational(seed)
    d0, d = split_stays(traj, cfg.d0_fraction, seed)
    actions, states, hyps, _ = design.design_on_d0(
        d0, quantiles=tuple(cfg.quantiles), min_support=cfg.min_support
    )
    if hyps.empty:
        raise ContractError(
            f"calibration: replicate seed {seed} has no hypotheses (n_stays {cfg.n_stays}, "
            f"min_support {cfg.min_support}); lower min_support or raise n_stays"
        )
    obs = bounds.observational_side(
        hyps, to_array(d, FEATURES), design.action_codes(d, actions), states, order_seed=seed
    )
    ids = d[STAY_ID].unique()
    plan = tp.plan_twin_runs(hyps, ids, cfg.runs_per_sequence, 1, seed,
                             x0=tp.x0_frame(d, ids.tolist())[list(FEATURES)].to_numpy(float))
    x0 = tp.x0_frame(d, plan.x0_stay_ids)
    runs = tp.run_shard(OracleTwin(world), plan, 0, x0, actions, log=io.StringIO())
    nodes = tp.load_nodes(runs, plan, x0)
    x_d0 = to_array(d0, FEATURES)
    sd = {k: float(np.std(x_d0[:, 1:, FEATURES.index(k)])) for k in OUTCOMES}
    return Replicate(seed, world, d0, d, actions, states, hyps, obs, plan, x0, nodes, sd)


def shifted_nodes(rep: Replicate, bias: float, features: tuple[str, ...]) -> bounds.TwinNodes:
    """Oracle runs with ``bias * sd_k`` added to outcome k at every simulated hour.

    Equals ``BiasedTwin(world, shift={k: bias * sd_k})`` run on the same plan
    (same seeds, X_0 untouched), without re-simulating.
    """
    if bias == 0:
        return rep.nodes
    values = rep.nodes.values.copy()
    for k in features:
        values[:, :, FEATURES.index(k)] += bias * rep.outcome_sd[k]
    return bounds.TwinNodes(index=rep.nodes.index, values=values, x0=rep.nodes.x0)


def welch_pvalues(samples: HypothesisSamples) -> np.ndarray:
    """Naive two-sided Welch t-test p-values of mean f(twin) = mean f(followers), per hypothesis.

    t = (m1 - m2) / sqrt(v1/n1 + v2/n2), Welch-Satterthwaite df
    (Welch 1947). Assumes nothing about confounding: that is the pitfall. p = 1
    when either group has fewer than 2 values or both variances are 0.
    """
    def moments(r: Ragged) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = r.sizes.astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = r.sums() / n
            dev = Ragged((r.values - np.repeat(mean, r.sizes)) ** 2, r.offsets)
            var = dev.sums() / (n - 1)
        return n, mean, var

    n1, m1, v1 = moments(samples.twin_f)
    n2, m2, v2 = moments(samples.follow_f)
    p = np.ones(len(samples))
    a, b = v1 / np.maximum(n1, 1), v2 / np.maximum(n2, 1)
    ok = (n1 >= 2) & (n2 >= 2) & ((a + b) > 0)
    se2 = (a + b)[ok]
    tstat = (m1 - m2)[ok] / np.sqrt(se2)
    df = se2**2 / (a[ok] ** 2 / (n1[ok] - 1) + b[ok] ** 2 / (n2[ok] - 1))
    p[ok] = 2 * stats.t.sf(np.abs(tstat), df)
    return p


def _methods(cfg: CalibrationConfig, seed: int):
    spec = {k: dict(v or {}) for k, v in cfg.methods.items()}
    return make_methods(spec, seed, alpha=cfg.alpha)  # betting: tuned per family (run_tests)


def fixed_results(cfg: CalibrationConfig, rep: Replicate, bias: float) -> tuple[
    pd.DataFrame, HypothesisSamples
]:
    """Fixed-scheme results of every method (``falsify.run_tests`` rows) for the biased twin."""
    nodes = shifted_nodes(rep, bias, tuple(cfg.bias_features))
    samples, n_failed = twin_samples(rep.hyps, rep.obs, nodes, rep.states)
    res = run_tests(
        rep.hyps, samples, n_failed, _methods(cfg, rep.seed),
        alpha=cfg.alpha, correction=cfg.correction,
    )  # fmt: skip
    return res, samples


def evaluate_bias(
    cfg: CalibrationConfig,
    rep: Replicate,
    bias: float,
    replicate: int,
    fixed: tuple[pd.DataFrame, HypothesisSamples] | None = None,
) -> pd.DataFrame:
    """Rejection counts per (method, kind) for the twin with the given bias (TEST_COLUMNS).

    ``fixed``: the output of :func:`fixed_results` when the caller already has it.
    """
    res, samples = fixed_results(cfg, rep, bias) if fixed is None else fixed
    res = res.assign(testable=(res["n"] > 0) & (res["nhat"] > 0))
    rows = [
        (replicate, bias, m, k, len(g), int(g["testable"].sum()), int(g["rejected"].sum()))
        for (m, k), g in res.groupby(["method", "kind"], sort=True)
    ]
    if cfg.naive:
        p = welch_pvalues(samples)
        kinds = rep.hyps["kind"].to_numpy()
        testable = (samples.n_follow >= 2) & (samples.nhat >= 2)
        for k in sorted(set(kinds)):
            sel = kinds == k
            rej = correct(p[sel], cfg.alpha, cfg.correction)
            rows.append((replicate, bias, NAIVE, k, int(sel.sum()), int(testable[sel].sum()),
                         int(rej.sum())))  # fmt: skip
    out = pd.DataFrame(rows, columns=list(TEST_COLUMNS[:-1]))
    out["any_rejected"] = out["n_rejected"] > 0
    return out


def widths(rep: Replicate, replicate: int) -> pd.DataFrame:
    """Mean and median estimated (Q_up - Q_lo)/(y_up - y_lo) = 1 - propensity per kind (n > 0)."""
    n, nf = rep.obs.n, rep.obs.follow.sizes
    rows = []
    for kind, idx in rep.hyps.groupby("kind").indices.items():
        ok = idx[n[idx] > 0]
        ratio = 1.0 - nf[ok] / n[ok]
        rows.append((replicate, kind, len(ok), float(ratio.mean()), float(np.median(ratio))))
    return pd.DataFrame(rows, columns=list(WIDTH_COLUMNS))


@dataclass
class Population:
    """Two large independent cohorts of the world: observational (for the population
    Q_lo, Q_up) and baseline X_0 (for the interventional truth)."""

    obs: pd.DataFrame
    obs_x: np.ndarray
    x0_traj: np.ndarray  # (m, T + 1, F): only hour 0 is used
    x0: pd.DataFrame

    @classmethod
    def draw(cls, cfg: CalibrationConfig) -> Population:
        world = SyntheticWorld(n_stays=cfg.coverage_population, confounding=cfg.confounding)
        obs = world.sample_observational(cfg.seed + 1)
        base = to_array(world.sample_observational(cfg.seed + 2), FEATURES)
        return cls(
            obs, to_array(obs, FEATURES), base, pd.DataFrame(base[:, 0, :], columns=list(FEATURES))
        )


def coverage(
    cfg: CalibrationConfig, rep: Replicate, pop: Population, replicate: int
) -> pd.DataFrame:
    """Monte-Carlo true Q vs population [Q_lo, Q_up] for a random sample of hypotheses.

    Q_lo, Q_up are the means of Y_lo, Y_up over the large observational cohort
    (SE = sd(Y)/sqrt(n)); Q = mean of f(X_t(a)) over the members of a fresh
    cohort, each given a_1:t by intervention, whose X_0:t(a) is in B_0:t. A check
    is skipped when fewer than ``coverage_min_inside`` members are in B or
    fewer than that many observational trajectories enter.
    """
    rng = np.random.default_rng([rep.seed, 7])
    hyps = rep.hyps
    half = max(1, cfg.coverage_per_replicate // 2)
    chosen = []
    for kind in ("causal", "manski"):
        idx = np.flatnonzero(hyps["kind"].to_numpy() == kind)
        if len(idx):
            chosen += rng.choice(idx, size=min(half, len(idx)), replace=False).tolist()
    sub = hyps.iloc[sorted(chosen)].reset_index(drop=True)
    if sub.empty:
        return pd.DataFrame(columns=list(COVERAGE_COLUMNS))
    pobs = bounds.observational_side(
        sub, pop.obs_x, design.action_codes(pop.obs, rep.actions), rep.states
    )
    seeds = np.arange(len(pop.x0), dtype=np.uint64) + np.uint64(rep.seed % 2**32)
    rows = []
    for i, h in sub.iterrows():
        n = int(pobs.n[i])
        fol = np.clip(pobs.follow.group(i), h.y_lo, h.y_up)
        seq = np.asarray(h.actions)
        sim = rep.world.simulate_interventional(
            pop.x0, np.broadcast_to(rep.actions.doses(seq), (len(pop.x0), len(seq), 2)).copy(),
            seeds,
        )  # fmt: skip
        traj = np.concatenate([pop.x0_traj[:, :1, :], sim], axis=1)
        padded = np.pad(traj, ((0, 0), (0, pop.x0_traj.shape[1] - 1 - len(seq)), (0, 0)), "edge")
        codes = design.state_codes(padded, rep.states, h.outcome)[:, : h.t + 1]
        bins = np.asarray(h.bins)
        inside = np.all((bins == design.WHOLE_SPACE) | (codes == bins), axis=1)
        m = int(inside.sum())
        if m < cfg.coverage_min_inside or n < cfg.coverage_min_inside:
            continue
        f = np.clip(traj[inside, h.t, FEATURES.index(h.outcome)], h.y_lo, h.y_up)
        q_true, se_true = float(f.mean()), float(f.std(ddof=1) / np.sqrt(m))
        y_lo = np.concatenate([fol, np.full(n - len(fol), h.y_lo)])
        y_up = np.concatenate([fol, np.full(n - len(fol), h.y_up)])
        q_lo, q_up = float(y_lo.mean()), float(y_up.mean())
        se_b = float(max(y_lo.std(ddof=1), y_up.std(ddof=1)) / np.sqrt(n))
        slack = cfg.coverage_z * np.hypot(se_true, se_b)
        rows.append((
            replicate, int(h.hyp_id), h.kind, h.outcome, int(h.t), float(h.y_lo), float(h.y_up),
            n, q_lo, q_up, se_b, m, q_true, se_true,
            bool(q_lo <= q_true <= q_up), bool(q_lo - slack <= q_true <= q_up + slack),
        ))  # fmt: skip
    return pd.DataFrame(rows, columns=list(COVERAGE_COLUMNS))


def adaptive_state(cfg: CalibrationConfig, rep: Replicate) -> SequentialState:
    """The twin-independent half of ``sequential.adaptive_test`` for this replicate.

    The observational betting bounds (L*, U*, L, U) do not depend on the twin and take
    ~80 % of ``adaptive_test``'s time, so they are built once per replicate and shared
    by every biased twin (:func:`run_adaptive` copies the decision arrays).
    Budget = the plan's X_0 per sequence (``runs_per_sequence``), as in ``adaptive_test``.
    """
    return SequentialState(
        rep.hyps, rep.obs, rep.states, budget=int(rep.nodes.x0.shape[0]),
        batch_size=cfg.adaptive_batch_size, alpha=cfg.alpha, seed=rep.seed,
        holm_aware=cfg.correction in HOLM_AWARE, curtail=cfg.adaptive_curtail,
        combine=cfg.adaptive_combine,
    )  # fmt: skip


def run_adaptive(
    cfg: CalibrationConfig,
    rep: Replicate,
    nodes: bounds.TwinNodes,
    base: SequentialState | None = None,
) -> AdaptiveOutcome:
    """``adaptive_test(rep.hyps, rep.obs, nodes, rep.states, batch_size=adaptive_batch_size,
    alpha, correction, seed=rep.seed)``, step by step with a shared :func:`adaptive_state`.

    Identical outcome to ``adaptive_test`` (tested: p-values, decisions, runs, hours).
    """
    base = adaptive_state(cfg, rep) if base is None else base
    st = copy.copy(base)  # shallow: the bounds are read-only, the decisions are copied
    st.side, st.stop_batch = base.side.copy(), base.stop_batch.copy()
    st.fut_level, st.q_hol = base.fut_level.copy(), base.q_hol.copy()
    st.l_hol, st.u_hol = base.l_hol.copy(), base.u_hol.copy()
    runs = twin_runs_indexed(rep.hyps, nodes, rep.states)
    run_to_stop(st, runs)
    return outcome(rep.hyps, nodes, rep.states, st, runs, cfg.alpha, cfg.correction)


def _fixed_rejections(res: pd.DataFrame, method: str, hyp_ids: np.ndarray):
    """(H, 2) Holm rejections (lo, up) of a fixed-scheme method in ``hyp_ids`` order, or
    None when the method was not run."""
    sel = res[res["method"] == method]
    if sel.empty:
        return None
    out = np.zeros((len(hyp_ids), 2), dtype=bool)
    pos = pd.Index(hyp_ids).get_indexer(sel["hyp_id"])
    out[pos, (sel["side"] == "up").to_numpy().astype(int)] = sel["rejected"].to_numpy(bool)
    return out


def adaptive_rows(
    cfg: CalibrationConfig,
    rep: Replicate,
    bias: float,
    replicate: int,
    outcome: AdaptiveOutcome,
    fixed: pd.DataFrame,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Rows of the adaptive test for one twin: (TEST_COLUMNS rows, one ADAPTIVE_COLUMNS row).

    Test rows (method ``betting_sequential``) count as ``evaluate_bias`` does: both sides
    of every parameter set of the kind; testable = n > 0 and nhat > 0 at the stop.
    The adaptive row: twin-hours with prefix reuse (``adaptive_test``: a node costs one
    hour per run simulated for it, i.e. revealed to a running hypothesis using it whose B_0
    holds the run's X_0; fixed = nodes x budget), the same without B_0 skipping
    (``twin_hours_all_x0``) and for the paper's scheme (``twin_hours_paper``), the ratio,
    rejections of both kinds, and how many of the fixed betting / Hoeffding test's rejections
    (same replicate, same twin, ``fixed`` = ``run_tests`` rows) the
    adaptive test also makes ("kept": same parameter set and side).
    """
    hyps = rep.hyps
    kinds = hyps["kind"].to_numpy()
    testable = (rep.obs.n > 0) & (outcome.nhat > 0)
    rej = np.stack([outcome.rejected_lo, outcome.rejected_up], axis=1)
    rows = [
        (replicate, bias, ADAPTIVE, k, 2 * int(sel.sum()), 2 * int(testable[sel].sum()),
         int(rej[sel].sum()))
        for k in sorted(set(kinds)) for sel in [kinds == k]
    ]  # fmt: skip
    tests = pd.DataFrame(rows, columns=list(TEST_COLUMNS[:-1]))
    tests["any_rejected"] = tests["n_rejected"] > 0
    ids = hyps["hyp_id"].to_numpy()
    counts = []
    for method in ("betting", "hoeffding"):
        f = _fixed_rejections(fixed, method, ids)
        counts += [pd.NA, pd.NA] if f is None else [int(f.sum()), int((f & rej).sum())]
    budget = int(rep.nodes.x0.shape[0])
    row = (
        replicate, bias, cfg.adaptive_batch_size, budget, len(rep.nodes.index),
        outcome.twin_hours_adaptive, outcome.twin_hours_fixed,
        outcome.twin_hours_adaptive / outcome.twin_hours_fixed, int(rej.sum()), *counts,
        int((outcome.decision == UNDECIDED).sum()),
        float(np.mean(outcome.runs_per_hypothesis / budget)),
        outcome.twin_hours_all_x0, outcome.twin_hours_paper,
    )  # fmt: skip
    out = pd.DataFrame([row], columns=list(ADAPTIVE_COLUMNS))
    for col in ("n_rejected_betting", "n_kept_betting", "n_rejected_hoeffding", "n_kept_hoeffding"):
        out[col] = out[col].astype("Int64")  # NA when the fixed method was not configured
    return tests, out



def run_replicates(
    cfg: CalibrationConfig, replicates: list[int], pop: Population | None = None, log=None
) -> dict[str, pd.DataFrame]:
    """Run the listed replicates: {"tests", "coverage", "widths", "timing", "adaptive"}
    tables ("adaptive" is empty unless ``cfg.adaptive``)."""
    tests, covs, wids, times, adapt = [], [], [], [], []
    if pop is None and cfg.coverage_per_replicate > 0:
        pop = Population.draw(cfg)
    for r in replicates:
        start = time.perf_counter()
        rep = build_replicate(cfg, cfg.replicate_seed(r))
        # statsmodels' multipletests calls gc.collect() on every family; freezing the
        # replicate's long-lived objects keeps those collections cheap (~60 ms -> ~1 ms).
        gc.freeze()
        base = adaptive_state(cfg, rep) if cfg.adaptive else None
        for bias in cfg.bias_sizes:
            fixed = fixed_results(cfg, rep, float(bias))
            tests.append(evaluate_bias(cfg, rep, float(bias), r, fixed=fixed))
            if base is not None:
                nodes = shifted_nodes(rep, float(bias), tuple(cfg.bias_features))
                out = run_adaptive(cfg, rep, nodes, base)
                rows, hours = adaptive_rows(cfg, rep, float(bias), r, out, fixed[0])
                tests.append(rows)
                adapt.append(hours)
        wids.append(widths(rep, r))
        if cfg.coverage_per_replicate > 0 and pop is not None:
            covs.append(coverage(cfg, rep, pop, r))
        gc.unfreeze()
        secs = time.perf_counter() - start
        times.append((r, len(rep.hyps), len(rep.plan.nodes), secs))
        if log is not None:
            log.info("replicate %d: %d parameter sets, %.1f s", r, len(rep.hyps), secs)
    return {
        "tests": pd.concat(tests, ignore_index=True),
        "coverage": (
            pd.concat(covs, ignore_index=True)
            if covs
            else pd.DataFrame(columns=list(COVERAGE_COLUMNS))
        ),
        "widths": pd.concat(wids, ignore_index=True),
        "timing": pd.DataFrame(times, columns=["replicate", "n_hyps", "n_nodes", "seconds"]),
        "adaptive": (
            pd.concat(adapt, ignore_index=True)
            if adapt
            else pd.DataFrame(columns=list(ADAPTIVE_COLUMNS))
        ),
    }


# -- aggregation ----------------------------------------------------------------


