"""Calibration harness: validity and power of every test method on the synthetic world.

The synthetic world (``sources.synthetic``) knows the truth: its oracle twin is
an exact sampler of the interventional law, so every null hypothesis about the
oracle is true, and a twin whose outcomes are shifted is wrong. A *replicate*
r draws a fresh observational cohort (seed r), splits it, fits the design on
D0, computes the observational side on D once, runs the oracle once on the
prefix-tree plan, and derives each biased twin from the same runs by adding
``bias * sd_k`` to every simulated hour of each outcome k (exactly what
``twins.builtin.BiasedTwin(shift=...)`` does with the same seeds; tested).
Every method then tests every hypothesis of every twin, with Holm (or the
configured correction) within each (method, kind) family, as ``falsify.run_tests``.

Measured (aggregated over R replicates by :func:`summarise`):

* FWER of the oracle: P(at least one rejection in a family) with a Clopper-
  Pearson 95 % interval (scipy.stats.binomtest). Exact methods (Hoeffding,
  betting, Bernstein) must have FWER <= alpha up to Monte-Carlo error; the
  bootstrap is asymptotic and is reported as measured.
* Power against biased twins: P(at least one rejection) and the mean share of
  hypotheses rejected, per bias size (in units of each outcome's D0 SD).
* Coverage of the bounds (Cornish et al. 2026, Theorem): for a sample of
  hypotheses, the true Q = E[f(X_t(a)) | X_0:t(a) in B_0:t] by Monte Carlo
  from a fresh population given a_1:t by intervention
  (``SyntheticWorld.simulate_interventional``), and the population
  Q_lo, Q_up estimated on a large observational cohort; reports the share with
  Q_lo <= Q <= Q_up strictly and up to ``z`` combined Monte-Carlo SEs.
* The naive-comparison pitfall: Welch's t-test of the twin's mean of f against
  the observational mean of f among followers (A_1:t = a_1:t, X in B), no
  bounds; with confounding it rejects the oracle.
* Widths: mean (Q_up - Q_lo) / (y_up - y_lo) = 1 - propensity, causal vs Manski.
* Adaptive twin runs (``adaptive: true``; issue 11): ``inference.sequential.adaptive_test``
  on the same runs revealed in batches (method ``betting_sequential``): its FWER and power
  as above, and per twin the simulated twin-hours (prefix reuse) adaptive vs fixed and the
  share of the fixed betting / Hoeffding rejections it keeps (:func:`adaptive_summary`).

Caveat shared with the study: the twin receives the median dose of each action
bin while the observational followers of a bin received varied doses, so the
oracle is exact for "median dose" rather than for "some dose in the bin".
"""

from __future__ import annotations

import copy
import gc
import io
import time
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from twinfalsify import bounds, design
from twinfalsify.falsify import make_methods, run_tests
from twinfalsify.inference.betting import default_tune_alpha
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.sequential import (
    UNDECIDED,
    AdaptiveOutcome,
    SequentialState,
    correct_by_family,
    hypothesis_paths,
    node_runs,
    run_to_stop,
    twin_runs_indexed,
)
from twinfalsify.schema import FEATURES, OUTCOMES, STAY_ID, ContractError, to_array
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.split import split_stays
from twinfalsify.tables import markdown_table
from twinfalsify.twins import plan as tp
from twinfalsify.twins.builtin import OracleTwin

ADAPTIVE = "betting_sequential"  # inference.sequential.adaptive_test (anytime-valid, exact)
EXACT_METHODS = ("hoeffding", "betting", "bernstein", ADAPTIVE)
NAIVE = "naive_welch"
HOURS_TARGET = 0.1  # issue 11: at most 1/10 of the fixed scheme's twin-hours ...
KEPT_TARGET = 0.9  # ... while keeping >= 90 % of its rejections

# Column contracts of the per-replicate tables.
TEST_COLUMNS = (
    "replicate", "bias", "method", "kind", "n_tests", "n_testable", "n_rejected", "any_rejected",
)  # fmt: skip
COVERAGE_COLUMNS = (
    "replicate", "hyp_id", "kind", "outcome", "t", "y_lo", "y_up", "n_pop", "q_lo_pop",
    "q_up_pop", "se_bounds", "n_inside", "q_true", "se_true", "covered", "covered_mc",
)  # fmt: skip
WIDTH_COLUMNS = ("replicate", "kind", "n_hyps", "mean_width_ratio", "median_width_ratio")
ADAPTIVE_COLUMNS = (
    "replicate", "bias", "batch_size", "budget", "n_nodes", "twin_hours_adaptive",
    "twin_hours_fixed", "hours_ratio", "n_rejected", "n_rejected_betting", "n_kept_betting",
    "n_rejected_hoeffding", "n_kept_hoeffding", "undecided_sides", "mean_stop_fraction",
)  # fmt: skip


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of a calibration run (``config/calibration.yaml``; see docs/calibration.md)."""

    replicates: int = 200
    seed: int = 2026
    n_stays: int = 2500
    confounding: float = 1.0
    d0_fraction: float = 0.15
    min_support: int = 10
    quantiles: tuple[float, float] = (0.2, 0.8)
    runs_per_sequence: int = 400
    alpha: float = 0.05
    correction: str = "holm"
    methods: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {
            "hoeffding": {},
            "bootstrap": {"n_resamples": 100},
            "betting": {},
            "bernstein": {},
        }
    )
    bias_sizes: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 2.0)  # in SD units; 0 = oracle
    bias_features: tuple[str, ...] = OUTCOMES
    naive: bool = True
    coverage_per_replicate: int = 4  # hypotheses checked per replicate (half causal, half Manski)
    coverage_population: int = 60_000  # stays of each population cohort (bounds, truth)
    coverage_min_inside: int = 200  # skip a check when fewer population members are in B
    coverage_z: float = 4.0  # MC slack in combined SEs for the "up to MC error" coverage
    chunks: int = 4  # Snakemake jobs the replicates are spread over (r % chunks)
    adaptive: bool = True  # also run inference.sequential.adaptive_test (betting_sequential)
    adaptive_batch_size: int = 25  # X_0 revealed per batch (budget = runs_per_sequence)

    @classmethod
    def from_dict(cls, cfg: dict[str, Any] | None, source: str = "calibration config"):
        """Validated config; unknown keys and bad values raise ContractError naming them."""
        cfg = dict(cfg or {})
        names = {f.name for f in fields(cls)}
        unknown = set(cfg) - names
        if unknown:
            raise ContractError(
                f"{source}: unknown key(s) {sorted(unknown)}; allowed: {sorted(names)}"
            )
        for key in ("quantiles", "bias_sizes", "bias_features"):
            if key in cfg:
                cfg[key] = tuple(cfg[key])
        out = replace(cls(), **cfg)
        out.validate(source)
        return out

    def validate(self, source: str = "calibration config") -> None:
        def bad(key: str, why: str) -> ContractError:
            return ContractError(f"{source}: {key} {why}")

        if self.replicates < 1:
            raise bad("replicates", f"must be >= 1, got {self.replicates}")
        if not 0 < self.d0_fraction < 1:
            raise bad("d0_fraction", f"must be in (0, 1), got {self.d0_fraction}")
        if not 0 < self.alpha < 1:
            raise bad("alpha", f"must be in (0, 1), got {self.alpha}")
        if not self.bias_sizes or 0.0 not in self.bias_sizes:
            raise bad("bias_sizes", "must include 0 (the oracle, for the FWER)")
        if any(b < 0 for b in self.bias_sizes):
            raise bad("bias_sizes", f"must be >= 0, got {list(self.bias_sizes)}")
        wrong = set(self.bias_features) - set(OUTCOMES)
        if wrong:
            raise bad("bias_features", f"holds unknown outcome(s) {sorted(wrong)}")
        if not self.methods:
            raise bad("methods", "must name at least one method")
        if self.chunks < 1:
            raise bad("chunks", f"must be >= 1, got {self.chunks}")
        if self.runs_per_sequence < 2:
            raise bad("runs_per_sequence", f"must be >= 2, got {self.runs_per_sequence}")
        if not isinstance(self.adaptive, bool):
            raise bad("adaptive", f"must be true or false, got {self.adaptive!r}")
        if not 1 <= self.adaptive_batch_size <= self.runs_per_sequence:
            raise bad(
                "adaptive_batch_size",
                f"must be in [1, runs_per_sequence = {self.runs_per_sequence}], "
                f"got {self.adaptive_batch_size}",
            )

    def replicate_seed(self, r: int) -> int:
        """Seed of replicate r: independent streams per r, reproducible whatever the chunking."""
        return int(np.random.SeedSequence([self.seed, r]).generate_state(1)[0])


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
        hyps, to_array(d, FEATURES), design.action_codes(d, actions), states
    )
    plan = tp.plan_twin_runs(hyps, d[STAY_ID].unique(), cfg.runs_per_sequence, 1, seed)
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


def _methods(cfg: CalibrationConfig, n_hyps: int, seed: int):
    spec = {k: dict(v or {}) for k, v in cfg.methods.items()}
    if "betting" in spec:
        spec["betting"].setdefault("tune_alpha", default_tune_alpha(n_hyps))
    return make_methods(spec, seed)


def fixed_results(cfg: CalibrationConfig, rep: Replicate, bias: float) -> tuple[
    pd.DataFrame, HypothesisSamples
]:
    """Fixed-scheme results of every method (``falsify.run_tests`` rows) for the biased twin."""
    nodes = shifted_nodes(rep, bias, tuple(cfg.bias_features))
    twin_vals, n_failed = bounds.twin_side(rep.hyps, nodes, rep.states)
    samples = bounds.hypothesis_samples(rep.hyps, rep.obs, twin_vals)
    res = run_tests(
        rep.hyps, samples, n_failed, _methods(cfg, len(rep.hyps), rep.seed),
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
    runs = twin_runs_indexed(rep.hyps, nodes, rep.states)
    run_to_stop(st, runs)
    p_lo, p_up, nhat = st.p_values(runs)
    per_hyp = st.runs_used()
    used = node_runs(hypothesis_paths(rep.hyps, nodes.index), per_hyp, len(nodes.index))
    rej_lo, rej_up = correct_by_family(rep.hyps, p_lo, p_up, cfg.alpha, cfg.correction)
    return AdaptiveOutcome(
        p_lo, p_up, st.stop_batch.copy(), used, per_hyp, st.side.copy(), nhat, rej_lo, rej_up,
        int(used.sum()), int(len(nodes.index) * st.budget),
    )  # fmt: skip


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
    hour per run revealed to any hypothesis using it; fixed = nodes x budget) and their
    ratio, rejections of both kinds, and how many of the fixed betting / Hoeffding
    test's rejections (same replicate, same twin, ``fixed`` = ``run_tests`` rows) the
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
    )  # fmt: skip
    out = pd.DataFrame([row], columns=list(ADAPTIVE_COLUMNS))
    for col in ("n_rejected_betting", "n_kept_betting", "n_rejected_hoeffding", "n_kept_hoeffding"):
        out[col] = out[col].astype("Int64")  # NA when the fixed method was not configured
    return tests, out


def chunk_replicates(cfg: CalibrationConfig, chunk: int) -> list[int]:
    """Replicates of Snakemake job ``chunk``: r = chunk, chunk + chunks, ... (< replicates)."""
    if not 0 <= chunk < cfg.chunks:
        raise ContractError(f"calibration: chunk {chunk} out of range (chunks: {cfg.chunks})")
    return list(range(chunk, cfg.replicates, cfg.chunks))


def load_config(path: str) -> CalibrationConfig:
    """Read and validate a calibration YAML file (errors name the file and key)."""
    import yaml

    try:
        with open(path) as fh:
            data = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ContractError(f"{path}: cannot read calibration config ({exc})") from None
    if data is not None and not isinstance(data, dict):
        raise ContractError(f"{path}: calibration config must be a mapping of keys to values")
    return CalibrationConfig.from_dict(data, source=str(path))


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


def _binom_ci(k: int, n: int) -> tuple[float, float]:
    """Clopper-Pearson 95 % interval (scipy.stats.binomtest(...).proportion_ci)."""
    ci = stats.binomtest(int(k), int(n)).proportion_ci(0.95, method="exact")
    return float(ci.low), float(ci.high)


def summarise(tests: pd.DataFrame, alpha: float = 0.05) -> pd.DataFrame:
    """Per (method, kind, bias): rate of >= 1 rejection over replicates with its 95 % CI,
    and the mean share of hypotheses rejected. At bias 0 the rate is the oracle's FWER.

    ``valid`` (bias 0 only): the CI's lower end is <= alpha, i.e. FWER <= alpha is
    not contradicted at the 95 % level (a method whose whole CI is above alpha fails).
    """
    rows = []
    for (method, kind, bias), g in tests.groupby(["method", "kind", "bias"], sort=True):
        k, n = int(g["any_rejected"].sum()), len(g)
        lo, hi = _binom_ci(k, n)
        share = (g["n_rejected"] / g["n_tests"].clip(lower=1)).mean()
        rows.append({
            "method": method, "kind": kind, "bias": float(bias), "replicates": n,
            "any_rejection_rate": k / n, "ci_low": lo, "ci_high": hi,
            "mean_rejections": float(g["n_rejected"].mean()),
            "mean_share_rejected": float(share), "mean_tests": float(g["n_tests"].mean()),
            "exact": method in EXACT_METHODS,
            "valid": bool(lo <= alpha) if bias == 0 else pd.NA,
        })  # fmt: skip
    return pd.DataFrame(rows)


def dominance(summary: pd.DataFrame, better: str = "betting", than: str = "hoeffding"):
    """Per (kind, bias > 0): does ``better`` reject at least as often as ``than``?

    Compared on the mean number of rejections per replicate and on the rate of
    >= 1 rejection (both from the same replicates, so the comparison is paired).
    """
    s = summary[summary["bias"] > 0].set_index(["kind", "bias", "method"])
    if better not in s.index.get_level_values("method") or than not in s.index.get_level_values(
        "method"
    ):
        return pd.DataFrame()
    a, b = s.xs(better, level="method"), s.xs(than, level="method")
    out = pd.DataFrame({
        f"{better}_mean_rejections": a["mean_rejections"],
        f"{than}_mean_rejections": b["mean_rejections"],
        f"{better}_rate": a["any_rejection_rate"], f"{than}_rate": b["any_rejection_rate"],
    })  # fmt: skip
    out["at_least_as_often"] = (a["mean_rejections"] >= b["mean_rejections"]) & (
        a["any_rejection_rate"] >= b["any_rejection_rate"]
    )
    return out.reset_index()


def coverage_summary(cov: pd.DataFrame) -> pd.DataFrame:
    """Per kind: hypotheses checked, share strictly inside, share inside up to MC error."""
    if cov.empty:
        return pd.DataFrame(columns=["kind", "checked", "covered", "covered_mc"])
    g = cov.groupby("kind")
    out = pd.DataFrame({
        "checked": g.size(), "covered": g["covered"].mean(), "covered_mc": g["covered_mc"].mean(),
        "mean_width_ratio": g.apply(
            lambda x: ((x.q_up_pop - x.q_lo_pop) / (x.y_up - x.y_lo)).mean(), include_groups=False
        ),
    })  # fmt: skip
    return out.reset_index()


def adaptive_summary(adaptive: pd.DataFrame) -> pd.DataFrame:
    """Per bias: twin-hours adaptive vs fixed and rejections kept, with the issue-11 target.

    hours_ratio = sum_r hours_adaptive / sum_r hours_fixed (pooled over replicates: the
    share of the whole calibration's twin-hours; ``hours_ratio_max`` = the worst
    replicate). kept_share_<m> = sum_r kept_r / sum_r rejected_r(fixed m), where kept_r
    counts the fixed test's rejections (parameter set, side) the adaptive test also makes
    (NA when the fixed test made none: nothing to keep). Target (issue 11):
    hours_ratio <= 1/10 and kept_share_betting >= 0.9 — the fixed betting test is the
    like-for-like comparison (same statistic at the full budget); Hoeffding (the paper's
    test) is reported alongside.
    """
    rows = []
    for bias, g in adaptive.groupby("bias", sort=True):
        ha, hf = float(g["twin_hours_adaptive"].sum()), float(g["twin_hours_fixed"].sum())
        row = {
            "bias": float(bias), "replicates": len(g), "batch_size": int(g["batch_size"].iloc[0]),
            "mean_twin_hours_adaptive": ha / len(g), "mean_twin_hours_fixed": hf / len(g),
            "hours_ratio": ha / hf, "hours_ratio_max": float(g["hours_ratio"].max()),
            "mean_rejections_adaptive": float(g["n_rejected"].mean()),
        }  # fmt: skip
        for m in ("betting", "hoeffding"):
            fixed, kept = g[f"n_rejected_{m}"], g[f"n_kept_{m}"]
            ran = bool(fixed.notna().all())  # the fixed method was configured
            tot = int(fixed.sum()) if ran else 0
            row[f"mean_rejections_{m}"] = float(fixed.mean()) if ran else np.nan
            row[f"kept_share_{m}"] = float(kept.sum()) / tot if tot > 0 else np.nan
        row["mean_undecided_sides"] = float(g["undecided_sides"].mean())
        row["mean_stop_fraction"] = float(g["mean_stop_fraction"].mean())
        row["target_hours"] = bool(row["hours_ratio"] <= HOURS_TARGET)
        kept = row["kept_share_betting"]
        row["target_rejections"] = pd.NA if np.isnan(kept) else bool(kept >= KEPT_TARGET)
        rows.append(row)
    return pd.DataFrame(rows)


def attach_hours(summary: pd.DataFrame, asum: pd.DataFrame) -> pd.DataFrame:
    """The calibration table with the adaptive rows' twin-hours (per bias; the hours are
    the twin's, shared by both kinds) and kept share; NaN for the fixed-scheme methods."""
    cols = ["mean_twin_hours_adaptive", "mean_twin_hours_fixed", "hours_ratio",
            "kept_share_betting"]  # fmt: skip
    out = summary.copy()
    for c in cols:
        out[c] = np.nan
    if asum.empty:
        return out
    sel = out["method"] == ADAPTIVE
    by_bias = asum.set_index("bias")[cols]
    out.loc[sel, cols] = by_bias.reindex(out.loc[sel, "bias"]).to_numpy()
    return out


def width_summary(w: pd.DataFrame) -> pd.DataFrame:
    g = w.groupby("kind")
    return pd.DataFrame({
        "replicates": g.size(), "mean_hyps": g["n_hyps"].mean(),
        "mean_width_ratio": g["mean_width_ratio"].mean(),
        "sd_width_ratio": g["mean_width_ratio"].std(ddof=1),
    }).reset_index()  # fmt: skip


# -- figures and the Markdown summary ---------------------------------------------


def plot_power(summary: pd.DataFrame, png: str, pdf: str) -> None:
    """Power curves: rate of >= 1 rejection (95 % CI bars) and mean share rejected vs bias,
    one column per kind, one line per method; bias 0 is the oracle (its FWER)."""
    from twinfalsify.figures import plt, save

    kinds = sorted(pd.unique(summary["kind"]))
    fig, axes = plt.subplots(2, len(kinds), figsize=(5.2 * len(kinds), 7), squeeze=False)
    for j, kind in enumerate(kinds):
        sub = summary[summary["kind"] == kind]
        for method, d in sub.groupby("method", sort=True):
            d = d.sort_values("bias")
            style = dict(marker="o", ms=3, ls="--" if method == NAIVE else "-", label=method)
            yerr = np.vstack([d["any_rejection_rate"] - d["ci_low"],
                              d["ci_high"] - d["any_rejection_rate"]])  # fmt: skip
            axes[0][j].errorbar(d["bias"], d["any_rejection_rate"], yerr=yerr, capsize=2, **style)
            axes[1][j].plot(d["bias"], d["mean_share_rejected"], **style)
        axes[0][j].axhline(0.05, color="grey", lw=0.8, ls=":")
        axes[0][j].set_title(f"{kind}: P(>= 1 Holm rejection)")
        axes[1][j].set_title(f"{kind}: mean share of hypotheses rejected")
        for i in range(2):
            axes[i][j].set_xlabel("twin bias (outcome SDs; 0 = oracle)")
            axes[i][j].set_ylim(-0.02, 1.02)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.tight_layout()
    save(fig, png)
    save(fig, pdf)
    plt.close(fig)


def plot_coverage(cov: pd.DataFrame, png: str, pdf: str) -> None:
    """Position of the true Q within the population bounds, (Q - Q_lo)/(Q_up - Q_lo):
    the theorem says every value lies in [0, 1]."""
    from twinfalsify.figures import plt, save

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for kind, d in cov.groupby("kind", sort=True):
        pos = (d["q_true"] - d["q_lo_pop"]) / (d["q_up_pop"] - d["q_lo_pop"]).where(
            lambda w: w > 0
        )
        ax.hist(pos.dropna(), bins=30, range=(-0.25, 1.25), alpha=0.6, label=f"{kind} ({len(d)})")
    for x in (0, 1):
        ax.axvline(x, color="k", lw=0.8)
    ax.set_xlabel(r"$(Q - Q_{lo}) / (Q_{up} - Q_{lo})$ (true Q by Monte Carlo)")
    ax.set_ylabel("hypotheses")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save(fig, png)
    save(fig, pdf)
    plt.close(fig)


def _md_table(df: pd.DataFrame, floatfmt: str = ".3f") -> str:
    return markdown_table(df, floatfmt)


def markdown_summary(
    cfg: CalibrationConfig,
    summary: pd.DataFrame,
    dom: pd.DataFrame,
    cov: pd.DataFrame,
    wid: pd.DataFrame,
    timing: pd.DataFrame,
    adaptive: pd.DataFrame | None = None,
) -> str:
    """The run's findings in Markdown: every number is read from the tables passed in
    (``adaptive``: the per-replicate ADAPTIVE_COLUMNS table, when the adaptive test ran)."""
    r = int(summary["replicates"].max())
    fw = summary[summary["bias"] == 0].copy()
    fw["FWER (95 % CI)"] = [
        f"{a:.3f} [{lo:.3f}, {hi:.3f}]"
        for a, lo, hi in zip(fw["any_rejection_rate"], fw["ci_low"], fw["ci_high"], strict=True)
    ]
    fw["verdict"] = [
        ("ok" if v else "FAILS") if e else ("ok" if v else "above alpha (reported)")
        for v, e in zip(fw["valid"], fw["exact"], strict=True)
    ]
    fw = fw[["method", "kind", "FWER (95 % CI)", "mean_rejections", "exact", "verdict"]]
    pw = summary[summary["bias"] > 0].pivot_table(
        index=["method", "kind"], columns="bias", values="any_rejection_rate"
    )
    pw.columns = [f"bias {b:g}" for b in pw.columns]
    sh = summary[summary["bias"] > 0].pivot_table(
        index=["method", "kind"], columns="bias", values="mean_rejections"
    )
    sh.columns = [f"bias {b:g}" for b in sh.columns]
    cs = coverage_summary(cov)
    ws = width_summary(wid)
    exact_bad = fw[(fw["exact"]) & (fw["verdict"] != "ok")]
    parts = [
        "# Calibration on the synthetic world",
        "",
        f"{r} replicates; {cfg.n_stays} stays each (D0 {cfg.d0_fraction:.0%}, min_support "
        f"{cfg.min_support}), {cfg.runs_per_sequence} twin runs per action sequence, "
        f"alpha {cfg.alpha}, correction {cfg.correction} within each (method, kind) family. "
        f"Biased twins: every outcome in {len(cfg.bias_features)} shifted by bias x its D0 SD. "
        f"Mean {timing['n_hyps'].mean():.0f} parameter sets per replicate; "
        f"{timing['seconds'].sum():.0f} s of replicate compute in total.",
        "",
        "## Family-wise error of the oracle twin",
        "",
        _md_table(fw),
        "",
        "Exact methods failing calibration: "
        + (", ".join(f"{m} ({k})" for m, k in exact_bad[["method", "kind"]].itertuples(index=False))
           or "none") + ".",  # fmt: skip
        "",
        "## Power against biased twins: P(>= 1 rejection)",
        "",
        _md_table(pw.reset_index()),
        "",
        "Mean number of rejections per replicate:",
        "",
        _md_table(sh.reset_index(), ".1f"),
        "",
    ]
    if not dom.empty:
        ok = bool(dom["at_least_as_often"].all())
        parts += [
            f"Betting rejects at least as often as Hoeffding at every bias level: **{ok}**",
            "",
            _md_table(dom),
            "",
        ]
    if adaptive is not None and not adaptive.empty:
        parts += adaptive_markdown(adaptive_summary(adaptive))
    parts += ["## Coverage of the bounds", "", _md_table(cs) if not cs.empty else "(not run)", ""]
    naive = summary[(summary["method"] == NAIVE)]
    if not naive.empty:
        o = naive[naive["bias"] == 0]
        parts += [
            "## The naive-comparison pitfall (Welch t-test, twin vs followers, no bounds)",
            "",
            "Oracle (a correct twin) rejected in "
            + ", ".join(
                f"{k}: {a:.0%} of replicates (mean {m:.1f} rejections)"
                for k, a, m in o[["kind", "any_rejection_rate", "mean_rejections"]].itertuples(
                    index=False
                )
            )
            + ".",
            "",
        ]
    parts += ["## Width of the bounds: mean (Q_up - Q_lo)/(y_up - y_lo)", "", _md_table(ws), ""]
    return "\n".join(parts)


def adaptive_markdown(asum: pd.DataFrame) -> list[str]:
    """Summary section of the adaptive test: twin-hours and kept rejections per bias, and
    the issue-11 target read off the table (never asserted)."""

    def share(x: float) -> str:
        return "n/a" if np.isnan(x) else f"{x:.0%}"

    def verdict(v) -> str:
        return "n/a (no fixed rejection)" if v is pd.NA else ("met" if v else "missed")

    t = pd.DataFrame({
        "bias": asum["bias"],
        "twin-hours adaptive / fixed (mean)": [
            f"{a:,.0f} / {f:,.0f}"
            for a, f in zip(asum["mean_twin_hours_adaptive"], asum["mean_twin_hours_fixed"],
                            strict=True)
        ],
        "hours ratio (pooled, worst)": [
            f"{r:.3f} ({m:.3f})" for r, m in zip(asum["hours_ratio"], asum["hours_ratio_max"],
                                                 strict=True)
        ],
        "rejections adaptive / betting / Hoeffding": [
            f"{a:.1f} / {b:.1f} / {h:.1f}"
            for a, b, h in zip(asum["mean_rejections_adaptive"], asum["mean_rejections_betting"],
                               asum["mean_rejections_hoeffding"], strict=True)
        ],
        "kept (betting, Hoeffding)": [
            f"{share(b)}, {share(h)}"
            for b, h in zip(asum["kept_share_betting"], asum["kept_share_hoeffding"], strict=True)
        ],
        "undecided sides": asum["mean_undecided_sides"].map(lambda x: f"{x:.1f}"),
        "hours <= 1/10": asum["target_hours"].map(lambda v: "met" if v else "missed"),
        "kept >= 90 %": asum["target_rejections"].map(verdict),
    })  # fmt: skip
    return [
        f"## Adaptive twin runs ({ADAPTIVE}, batches of {int(asum['batch_size'].iloc[0])})",
        "",
        "Its FWER and power are the betting_sequential rows of the tables above. Twin-hours "
        "with prefix reuse, means per replicate; the ratio is pooled over replicates (worst "
        "replicate in brackets). Kept = share of the fixed test's rejections (same replicate, "
        "parameter set and side) that the adaptive test also makes. Per-replicate means of "
        "rejections over both kinds.",
        "",
        _md_table(t),
        "",
        f"Target (<= {HOURS_TARGET:g} of the fixed twin-hours while keeping >= "
        f"{KEPT_TARGET:.0%} of the fixed betting test's rejections; the hours alone where the "
        "fixed test rejects nothing) met at bias level(s): "
        + (", ".join(
            f"{b:g}" for b, h, k in zip(asum["bias"], asum["target_hours"],
                                        asum["target_rejections"], strict=True)
            if h and k is not False
        ) or "none") + ".",
        "",
    ]  # fmt: skip
