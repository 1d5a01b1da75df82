"""Anytime-valid sequential testing of H_lo / H_up with early rejection and exact futility.

Twin side: a betting confidence *sequence* (CS) for Q_twin (Waudby-Smith & Ramdas 2024,
JRSS-B 86(1):1-27, Sec. 3-4, predictable plug-in bets for a CS), observed run by run in
the order of the plan's seeded X_0 permutation. Rescale x = (clip(y) - y_lo) / R in [0, 1];
for a candidate mean m,

    K+_t(m) = prod_{i<=t} (1 + min(lambda_i, c/m) (x_i - m)),
    K-_t(m) = prod_{i<=t} (1 - min(lambda_i, c/(1-m)) (x_i - m)),
    lambda_i = sqrt(2 log(1/delta0) / (sigma2_{i-1} i log(1 + i))),

(truncated only at c/m, c/(1-m), WSR 2024 Thm 3) with mu_i, sigma2_i the running plug-in
estimates of ``betting.plugin_bets`` (sigma2_0 = 1/4).
Unlike the fixed-n bets, lambda_i depends on neither n nor the final sample: it uses
x_1..x_{i-1} and i only. Time runs over *all* runs in X_0 order (a run that does not enter
contributes the factor 1), so K is a non-negative supermartingale in the filtration of the
runs revealed so far whenever the true mean is <= m (K+) or >= m (K-), and Ville's
inequality (Ville 1939; Howard et al. 2021, Ann. Stat. 49(2):1055-1080) gives
P(exists t: K_t >= 1/delta) <= delta: the bounds hold uniformly over time, hence at any
stopping time, however data-dependent.

Observational side: the fixed-sample betting bound (``betting.ordered_sides``, the fixed
test's default target-recalculating bets in its data order, keyed by the study seed:
``betting`` module doc "Order" and "STaR bets"; running maximum; Ville).
Union rule: reject H_lo at level a when some m has max_t K+_lo(m) >= 2/a and
max_{t<=tau} K-_twin,t(m) >= 2/a; p = min(1, 2/K*) with K* the crossing of the two curves
(``betting.crossing``), evaluated with the twin data revealed
at the stopping time tau. Mirror for H_up.

Decisions after each batch (one-sided hypotheses; the family is the hypothesis kind, as in
``falsify.run_tests``, 2H_f one-sided hypotheses):

(a) early rejection: the rule rejects at a* = alpha / (2 H_f), the most stringent threshold
    Holm can use. Because K+_lo(m) is non-increasing and K-_twin(m) non-decreasing in m,
    this holds iff K-_twin(L*) >= 2/a* with L* = sup{m : max_t K+_lo(m) >= 2/a*} (one
    evaluation, no search).
(b) futility: no continuation of the twin data up to the budget can make the rule reject at
    alpha (the most lenient Holm threshold). Every future factor of K-_twin(L) is at most
    1 + min(lambda_bar, c/(1-L)) L (x = 0, i.e. the outcome at y_lo, with lambda_bar >= every
    future bet, ``future_bet_bound``: the bets shrink with the accumulated variance; the K-
    bet at L is truncated at c/(1-L)), and only runs whose
    real X_0 lies in B_0 can ever enter, so the best reachable capital is
    max(max_{t<=tau} K-_t(L), K-_tau(L) (1 + min(lambda_bar, c/(1-L)) L)^r), r = remaining
    runs with X_0 in B_0.
    This bounds the path where every remaining run gives y_lo (and every other path), so
    stopping never loses a rejection the full budget could have made. Mirror for H_up with
    factor 1 + min(lambda_bar, c/U) (1 - U), U = inf{m : max_t K-_up(m) >= 2/alpha}.

A parameter set keeps receiving runs while either side is undecided; its p-values are
computed at its stopping time. Holm / BY then run on these p-values as usual. Why the
family-wise error stays controlled: docs/explanation/sequential.md.

Failed twin runs (``failed_runs``; a run whose X_0 lies in B_0 and whose path failed before
it could be seen to leave B_1:t). ``drop`` leaves them out (the paper). ``conservative`` (the
default, as in the fixed scheme) rejects only what would be rejected whatever they would have
produced: let every bet be computed from the successful entering runs only (the plug-in
estimates and the index i count those; still predictable). A failed run would have either not
entered (factor 1) or entered with some x in [0, 1], factor 1 - lambda (x - m) >=
1 - lambda (1 - m) for K-. So K-_cons, which puts the factor 1 - lambda (1 - m) at every failed
run, is at most the capital K-_true of the true completion with those same bets, at every time
and every m; K-_true is a test supermartingale under the null (the completed runs are i.i.d.
across X_0; failures may depend on anything, e.g. on the outcome), so Ville's inequality holds
for K-_true and a fortiori for K-_cons: the p-values stay valid under informative failures.
K+ mirrors it with x = 0. Without failures K_cons is the drop capital exactly; with them it is
never larger, so conservative p >= drop p.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.special import erfc

from twinfalsify.design import StateBins
from twinfalsify.inference.betting import ordered_sides
from twinfalsify.inference.capital import (
    C_TRUNC,
    OrderedSide,
    capital_bound,
    crossing,
    flat_layout,
    log_capital,
    running_moments,
    segment_cumsum,
)
from twinfalsify.inference.multiple_testing import correct_within
from twinfalsify.inference.samples import HypothesisSamples, ObservationalSide, Ragged, TwinRuns

UNDECIDED, REJECTED, FUTILE, CURTAILED = 0, 1, 2, 3
FAILED_RUNS = ("conservative", "drop")  # failed twin runs: worst case or left out (doc)
HOLM_AWARE = ("holm", "bonferroni")  # corrections whose thresholds Holm-aware futility bounds
COMBINES = ("union",)  # how the observational and twin capitals combine (doc)
# The product rule (inf_m G_lo(m) K-_twin(m) >= 1/a) was withdrawn: its proof needs a twin
# sample independent of the observational one, and with shared X_0 it exceeded its level
# (CHANGELOG.md, 0.2.0, "Adaptive twin runs"; the union rule's proof is in
# docs/explanation/sequential.md, "Why the family-wise error stays controlled").
PRODUCT_REMOVED = ("combine: product was removed: it can exceed its level when the twin's X_0 "
                   "come from the observational sample (measured 0.0020 at a = 0.001); "
                   "use combine: union")
# entering rate among runs with X_0 in B_0, shrunk: rho = (E + RATE_A) / (S + RATE_A + RATE_B)
# (Krichevsky-Trofimov; any constants >= 0 keep the bets predictable, hence valid)
RATE_A, RATE_B = 0.5, 0.5


def cs_bets(x: np.ndarray, offsets: np.ndarray, delta0: np.ndarray, c: float = C_TRUNC,
            index: np.ndarray | None = None) -> np.ndarray:
    """WSR's predictable plug-in bets for a confidence sequence of unknown horizon, per group.

    lambda_i = sqrt(2 log(1/delta0) / (sigma2_{i-1} i log(1 + i))) (WSR 2024, the
    "predictable plug-in" CS; the c/m, c/(1-m) truncation is applied per m later);
    ``i`` is the 1-based position among the group's values (``index`` overrides it;
    positions only, never the group size). delta0: one per group. Not the adaptive test's
    twin bets (:func:`horizon_bets`); kept as the unknown-horizon reference.
    """
    gid, t = flat_layout(offsets)
    _, prev = running_moments(x, offsets, (gid, t))
    i = t if index is None else index
    k = 2.0 * np.log(1.0 / np.asarray(delta0, float))[gid] / (i * np.log1p(i))
    return np.sqrt(k / prev)


def horizon(entered: np.ndarray, seen_b0: np.ndarray, left_b0: np.ndarray) -> np.ndarray:
    """Predictable estimate n_i of the entering runs at the budget, at a run with X_0 in B_0.

    n_i = max(i, E + rho R), i = E + 1, rho = (E + RATE_A) / (S + RATE_A + RATE_B): E
    successful entering runs before it, S runs with X_0 in B_0 before it, R runs with X_0 in
    B_0 from it to the budget (itself included; known from the plan).
    """
    e = np.asarray(entered, float)
    rho = (e + RATE_A) / (np.asarray(seen_b0, float) + RATE_A + RATE_B)
    return np.maximum(e + 1.0, e + rho * np.asarray(left_b0, float))


def horizon_bet(sig2_prev: np.ndarray, entered: np.ndarray, seen_b0: np.ndarray,
                left_b0: np.ndarray, log_term: np.ndarray) -> np.ndarray:
    """lambda = sqrt(2 log(1/delta0) / (sigma2_{i-1} n_i)); ``log_term`` = log(1/delta0)."""
    return np.sqrt(2.0 * log_term / (sig2_prev * horizon(entered, seen_b0, left_b0)))


def horizon_bets(x: np.ndarray, offsets: np.ndarray, delta0: np.ndarray, seen_b0: np.ndarray,
                 left_b0: np.ndarray) -> np.ndarray:
    """The twin side's bets, per group: the fixed-n plug-in bet (WSR 2024, eq. 26-27) at the
    predictable horizon n_i of :func:`horizon` (module doc; the c/m, c/(1-m) truncation is
    applied per m later). ``seen_b0``, ``left_b0``: per value, S and R of its run."""
    gid, t = flat_layout(offsets)
    _, prev = running_moments(x, offsets, (gid, t))
    return horizon_bet(prev, t - 1, seen_b0, left_b0,
                       np.log(1.0 / np.asarray(delta0, float))[gid])


@dataclass(frozen=True)
class TwinSides:
    """The twin sample of each group at one time, as the rules read it.

    ``succ``: the successful entering runs with their CS bets (the plug-in estimates and the
    future-bet bound read these). ``lo`` / ``up``: the sides H_lo / H_up are tested on. With
    ``failed_runs: drop`` both are ``succ``; with ``conservative`` each failed run sits at its
    place in X_0 order at the value least favourable to rejection (x = 1 for H_lo, whose K-
    it lowers most; x = 0 for H_up), with the bet the next successful run would get. Why that
    is valid whatever the failed runs would have produced: module doc.
    """

    succ: OrderedSide
    lo: OrderedSide
    up: OrderedSide

    def take(self, groups: np.ndarray) -> TwinSides:
        if self.lo is self.succ and self.up is self.succ:
            one = self.succ.take(groups)
            return TwinSides(one, one, one)
        return TwinSides(self.succ.take(groups), self.lo.take(groups), self.up.take(groups))


def family_sizes(hyps: pd.DataFrame) -> np.ndarray:
    """Number of one-sided hypotheses (2 H_f) in each hypothesis' family (its kind)."""
    kind = hyps["kind"] if "kind" in hyps else pd.Series(["all"] * len(hyps))
    return 2 * kind.map(kind.value_counts()).to_numpy(np.int64)


@dataclass
class SequentialState:
    """Decisions of a sequential test; updated batch by batch (see module doc).

    ``budget``: runs per sequence at most (the plan's m by default); ``n_family``: 2 H_f per
    hypothesis (defaults to :func:`family_sizes`). ``only``: a shard runs its own hypotheses
    but builds the state on the whole study, so the observational order and bets (hashed
    over all hypotheses) and hence every decision equal the unsharded ones.
    """

    hyps: pd.DataFrame
    obs: ObservationalSide
    states: StateBins
    budget: int
    batch_size: int
    alpha: float = 0.05
    seed: int = 0
    c: float = C_TRUNC
    n_family: np.ndarray | None = None
    only: np.ndarray | None = None  # (H,) bool: hypotheses to run (others never receive runs)
    holm_aware: bool = True  # futility at the Holm threshold a side can still face (doc (c))
    # (H,) labels: primary-futile sides are counted within (kind, label), e.g. the shard that
    # runs the hypothesis (shards share nothing); None: within the kind (the whole family)
    holm_scope: np.ndarray | None = None
    # opt-in curtailment (doc (d)): stop a side when the predictive probability that the
    # full budget rejects it early (at a*) is below this epsilon (0: off)
    curtail: float = 0.0
    # "union" (the fixed scheme's rule; the only one: PRODUCT_REMOVED says why)
    combine: str = "union"
    # failed twin runs: "conservative" (worst case, module doc) or "drop" (left out)
    failed_runs: str = "conservative"
    side: np.ndarray = field(init=False)  # (H, 2) UNDECIDED | REJECTED | FUTILE (lo, up)
    stop_batch: np.ndarray = field(init=False)  # (H,) batch count at stop (-1: running)

    def __post_init__(self) -> None:
        h = len(self.hyps)
        if self.batch_size < 1 or self.budget < 0:
            raise ValueError(f"sequential: batch_size must be >= 1 and budget >= 0, got "
                             f"{self.batch_size}, {self.budget}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"sequential: alpha must be in (0, 1), got {self.alpha}")
        if self.combine == "product":
            raise ValueError(f"sequential: {PRODUCT_REMOVED}")
        if self.combine not in COMBINES:
            raise ValueError(f"sequential: combine must be one of {', '.join(COMBINES)}, "
                             f"got {self.combine!r}")
        if self.failed_runs not in FAILED_RUNS:
            raise ValueError(f"sequential: failed_runs must be one of {', '.join(FAILED_RUNS)}, "
                             f"got {self.failed_runs!r}")
        nf = family_sizes(self.hyps) if self.n_family is None else np.asarray(self.n_family)
        self.n_family = np.broadcast_to(nf, (h,)).astype(np.int64)
        self.a_star = self.alpha / self.n_family  # most stringent Holm threshold
        # bets tuned where Holm decides (as betting_test's default), per family
        self.delta0 = self.a_star / 2
        self.y_lo = self.hyps["y_lo"].to_numpy(float)
        self.y_up = self.hyps["y_up"].to_numpy(float)
        if np.any(~(self.y_up > self.y_lo)):
            raise ValueError("sequential: y_up must exceed y_lo for every hypothesis")
        empty = Ragged(np.zeros(0), np.zeros(h + 1, dtype=np.int64))
        self.obs_samples = HypothesisSamples(self.y_lo, self.y_up, self.obs.n,
                                             self.obs.follow, empty,
                                             follow_pos=self.obs.follow_pos)
        # the fixed test's default bets: target-recalculating, in the data order, running
        # maximum (the observational sample is whole from the start; the grid mixture of the
        # fixed scheme, measured too: same decisions, ~5x the compute;
        # docs/explanation/sequential.md)
        self.lo, self.up, _ = ordered_sides(self.obs_samples, self.delta0, self.seed, self.c,
                                            orders=1, order="data", star=True)
        lev_star, lev = np.log(2.0 / self.a_star), np.full(h, np.log(2.0 / self.alpha))
        # L = sup{m: max K+_lo(m) >= 2/a}; U = inf{m: max K-_up(m) >= 2/a}
        # bounds are per hypothesis: compute them only where they are used (a shard's own);
        # elsewhere L = 0, U = 1 (never rejectable; those hypotheses never receive runs)
        g = np.arange(h) if self.only is None else np.flatnonzero(self.only)
        lo, up = self.lo.take(g), self.up.take(g)
        self.l_star, self.l_fut = np.zeros(h), np.zeros(h)
        self.u_star, self.u_fut = np.ones(h), np.ones(h)
        self.l_star[g] = capital_bound(lo, lev_star[g], +1, True, self.c)
        self.u_star[g] = capital_bound(up, lev_star[g], -1, True, self.c)
        self.l_fut[g] = capital_bound(lo, lev[g], +1, True, self.c)
        self.u_fut[g] = capital_bound(up, lev[g], -1, True, self.c)
        self.side = np.zeros((h, 2), dtype=np.int8)
        # level at which a side was found futile: alpha ("primary": p > alpha for sure) or a
        # Holm-aware level alpha / 2^q < alpha (p > that level for sure); 0 if not futile
        self.fut_level = np.zeros((h, 2))
        # Holm-aware futility: bounds at level alpha / 2^q (q = 0: the alpha bounds above)
        self.q_hol = np.zeros((h, 2), dtype=np.int64)
        self.l_hol, self.u_hol = self.l_fut.copy(), self.u_fut.copy()
        kind = self.hyps["kind"].to_numpy() if "kind" in self.hyps else np.zeros(h)
        scope = np.zeros(h, np.int64) if self.holm_scope is None else np.asarray(self.holm_scope)
        label = pd.Series(kind).astype(str) + "|" + pd.Series(scope).astype(str)
        self.family = pd.factorize(label)[0]
        self.stop_batch = np.full(h, -1, dtype=np.int64)
        no_obs = self.obs.n == 0  # p = 1 by rule: nothing to learn from the twin
        self.side[no_obs] = FUTILE
        self.fut_level[no_obs] = self.alpha
        self.stop_batch[no_obs] = 0
        if self.only is not None:
            self.stop_batch[~np.asarray(self.only, bool)] = 0
        self.n_batches = -(-self.budget // self.batch_size)

    @property
    def active(self) -> np.ndarray:
        """Hypotheses still receiving runs."""
        return self.stop_batch < 0

    def revealed(self, b: int) -> int:
        return min(b * self.batch_size, self.budget)

    def _twin_prefix(self, runs: TwinRuns, upto: np.ndarray, groups: np.ndarray
                     ) -> tuple[TwinSides, np.ndarray]:
        """:class:`TwinSides` of ``groups`` (sorted) with runs < upto[group]; and nhat."""
        v = runs.values
        gid = v.group_ids()
        sel = np.isin(gid, groups) & (runs.run < upto[gid])
        g = gid[sel]
        gi = np.searchsorted(groups, g)
        sizes = np.bincount(gi, minlength=len(groups))
        offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        x = (np.clip(v.values[sel], self.y_lo[g], self.y_up[g]) - self.y_lo[g]) / (
            self.y_up[g] - self.y_lo[g])
        m = runs.failed.shape[1]
        # S (runs with X_0 in B_0 before run j) and R (from j to the budget): the plan's
        cb = self._b0_counts(runs, groups)
        j = runs.run[sel]
        log_term = np.log(1.0 / self.delta0[groups])
        fg = fj = np.zeros(0, np.int64)  # failed runs: group position, run (sorted so)
        if self.failed_runs == "conservative":
            fg, fj = np.nonzero(runs.failed[groups] & (np.arange(m) < upto[groups][:, None]))
        seen, left = cb[gi, j], cb[gi, -1] - cb[gi, j]
        if len(fg) == 0:
            succ = OrderedSide(x, horizon_bets(x, offs, self.delta0[groups], seen, left), offs)
            return TwinSides(succ, succ, succ), sizes
        lam = horizon_bets(x, offs, self.delta0[groups], seen, left)
        # a failed run gets the bet of its own place: sigma2 and E from the successful runs
        # before it (one extra slot per group holds sigma2 after the group's last one)
        offs_ext = offs + np.arange(len(groups) + 1)
        _, sig_ext = running_moments(np.insert(x, offs[1:], 0.5), offs_ext)
        key_s = gi * (m + 1) + j  # ascending: groups sorted, runs sorted within
        key_f = fg * (m + 1) + fj
        k = np.searchsorted(key_s, key_f)  # successful runs before each failed one (global)
        lam_f = horizon_bet(sig_ext[k + fg], k - offs[fg], cb[fg, fj], cb[fg, -1] - cb[fg, fj],
                            log_term[fg])
        order = np.argsort(np.concatenate([key_s, key_f]), kind="stable")
        offs_all = np.concatenate(
            [[0], np.cumsum(sizes + np.bincount(fg, minlength=len(groups)))]).astype(np.int64)
        lam_all = np.concatenate([lam, lam_f])[order]
        worst = (OrderedSide(np.concatenate([x, np.full(len(fg), w)])[order], lam_all, offs_all)
                 for w in (1.0, 0.0))
        return TwinSides(OrderedSide(x, lam, offs), *worst), sizes

    def _b0_counts(self, runs: TwinRuns, groups: np.ndarray) -> np.ndarray:
        """(len(groups), budget + 1): runs with X_0 in B_0 among runs < j, for j = 0..budget
        (known from the plan before any simulation)."""
        b0 = runs.in_b0[groups][:, :self.budget]
        out = np.zeros((len(groups), b0.shape[1] + 1), np.int32)
        np.cumsum(b0, axis=1, out=out[:, 1:])
        return out

    def update(self, runs: TwinRuns, b: int) -> None:
        """Decide with the first ``revealed(b)`` runs of every still-active hypothesis."""
        act = np.flatnonzero(self.active)
        if len(act) == 0:
            return
        j = self.revealed(b)
        upto = np.full(len(self.hyps), j)
        tw, nhat = self._twin_prefix(runs, upto, act)
        und = self.side[act] == UNDECIDED
        cb = self._b0_counts(runs, act)
        j_b = min(j, cb.shape[1] - 1)
        r = cb[:, -1] - cb[:, j_b]  # runs that can still enter
        lam = future_bet_bound(tw.succ, nhat, cb[:, j_b], r, self.delta0[act])
        rej, fut, lvl, cur_m, cur_lev = self._decide_union(tw, act, lam)
        new = np.where(rej, REJECTED, np.where(fut, FUTILE, UNDECIDED)).astype(np.int8)
        if self.curtail > 0:
            cur = self._curtailed(runs, tw, nhat, act, j, lam.largest(), cur_m, cur_lev)
            new = np.where((new == UNDECIDED) & cur, CURTAILED, new).astype(np.int8)
        newly = und & (new == FUTILE)
        self.side[act] = np.where(und, new, self.side[act])
        self.fut_level[act] = np.where(newly, lvl, self.fut_level[act])
        # stop when both sides are decided or the budget is spent (sides may stay UNDECIDED)
        done = ~(self.side[act] == UNDECIDED).any(axis=1) | (j >= self.budget)
        self.stop_batch[act[done]] = b

    def _decide_union(self, tw: TwinSides, act: np.ndarray, lam: FutureBets
                      ) -> tuple[np.ndarray, ...]:
        """Union rule: (rejected, futile, futility level, curtailment point m, its log-level),
        each (len(act), 2) for (H_lo, H_up); rules (a)-(c) of the module doc."""
        # (a) early rejection at a*: twin capital at the observational bound at a*
        lev_star = np.log(2.0 / self.a_star[act])
        rej_lo = log_capital(tw.lo, self.l_star[act], -1, True, self.c) >= lev_star
        rej_up = log_capital(tw.up, self.u_star[act], +1, True, self.c) >= lev_star
        # (b) futility at alpha: best reachable capital up to the budget
        lev = np.full(len(act), np.log(2.0 / self.alpha))
        best_lo, best_up = self._best(tw, lam, self.l_fut[act], self.u_fut[act])
        fut_lo, fut_up = best_lo < lev, best_up < lev
        lvl_lo = np.where(fut_lo, self.alpha, 0.0)
        lvl_up = np.where(fut_up, self.alpha, 0.0)
        if self.holm_aware:
            # (c) Holm-aware futility: F sides of the family are primary-futile (p > alpha
            # for sure), so a side can only be rejected at a Holm threshold <= alpha/(F+1)
            # (its rank is at most 2H_f - F); quantised to alpha/2^q >= alpha/(F+1)
            self._refresh_holm_bounds(act)
            q_lo, q_up = self.q_hol[act, 0], self.q_hol[act, 1]
            a_lo, a_up = self.alpha / 2.0 ** q_lo, self.alpha / 2.0 ** q_up
            h_lo, h_up = self._best(tw, lam, self.l_hol[act], self.u_hol[act])
            hol_lo = (q_lo > 0) & ~fut_lo & (h_lo < np.log(2.0 / a_lo))
            hol_up = (q_up > 0) & ~fut_up & (h_up < np.log(2.0 / a_up))
            fut_lo, fut_up = fut_lo | hol_lo, fut_up | hol_up
            lvl_lo = np.where(hol_lo, a_lo, lvl_lo)
            lvl_up = np.where(hol_up, a_up, lvl_up)
        # curtailment (d) aims at early rejection: at L*, U* against log(2/a*)
        cur_m = np.stack([self.l_star[act], self.u_star[act]], axis=1)
        cur_lev = np.broadcast_to(lev_star[:, None], cur_m.shape)
        return (np.stack([rej_lo, rej_up], axis=1), np.stack([fut_lo, fut_up], axis=1),
                np.stack([lvl_lo, lvl_up], axis=1), cur_m, cur_lev)

    def _best(self, tw: TwinSides, lam: FutureBets, lf: np.ndarray, uf: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """log of the best twin capital reachable up to the budget at L (H_lo) and U (H_up):
        every remaining run with X_0 in B_0 at the value most favourable to rejection with the
        largest bet it can get (module doc (b))."""
        with np.errstate(divide="ignore"):  # L = 1 or U = 0: the cap is infinite
            cap_lo, cap_up = self.c / (1 - lf), self.c / uf
        best_lo = np.maximum(
            log_capital(tw.lo, lf, -1, True, self.c),
            log_capital(tw.lo, lf, -1, False, self.c) + lam.log_growth(cap_lo, lf))
        best_up = np.maximum(
            log_capital(tw.up, uf, +1, True, self.c),
            log_capital(tw.up, uf, +1, False, self.c) + lam.log_growth(cap_up, 1 - uf))
        return best_lo, best_up

    def _curtailed(self, runs: TwinRuns, tw: TwinSides, nhat: np.ndarray, act: np.ndarray,
                   j: int, lam_bar: np.ndarray, at_m: np.ndarray, at_lev: np.ndarray
                   ) -> np.ndarray:
        """(len(act), 2) bool: P(the full budget rejects at the curtailment level) <
        ``curtail``, a predictive probability under a normal approximation.

        It aims at early rejection: at the point ``at_m`` (union: L*, U*, the observational
        bounds at a*) against the log-level ``at_lev`` (union: log(2/a*)). Aiming at
        the side's Holm-aware level instead (alpha / 2^q, far more lenient when few sides
        are futile) kept grey-zone sides running to the budget: more hours for the same
        rejections (docs/explanation/sequential.md). Each remaining run with X_0 in B_0
        enters with the
        observed rate pi = nhat / (revealed runs with X_0 in B_0) and then adds
        g(x) = log(1 - min(lam, c/(1-m)) (x - m)), x drawn from the values seen so far,
        lam = the largest future bet (``future_bet_bound``). With mu, v the mean and
        variance of the per-run increment (0 w.p. 1 - pi) over the n = seen_b0 runs so far,

            log K_budget ~ N(log K_tau + r mu, r v (1 + r / n)):

        the term r^2 v / n is the uncertainty of mu itself, i.e. predictive rather than
        conditional power (Spiegelhalter, Freedman & Blackburn 1986, Control. Clin. Trials
        7:8-17). Without it the stop is overconfident early on (r >> n) and forgoes many
        rejections with small batches (``test_curtailment_forgoes_few_rejections_the_full_
        budget_makes``). A heuristic: it never affects validity (stopping only forgoes
        power), and its power cost is measured (docs/reference/benchmarks.md, "Adaptive twin runs").
        """
        gid = np.repeat(np.arange(len(act)), tw.succ.sizes)
        seen_b0 = runs.in_b0[act][:, :j].sum(axis=1)
        r = runs.in_b0[act][:, j:self.budget].sum(axis=1)
        pi = np.where(seen_b0 > 0, nhat / np.maximum(seen_b0, 1), 0.0)
        out = np.zeros((len(act), 2), dtype=bool)
        for col, sign in ((0, -1), (1, +1)):
            m, lev = at_m[:, col], at_lev[:, col]
            cap = self.c / (1.0 - m) if sign < 0 else self.c / np.maximum(m, 1e-12)
            bet = np.minimum(lam_bar, cap)
            g = np.log1p(np.clip(sign * bet[gid] * (tw.succ.x - m[gid]), -self.c, None))
            n_ok = np.maximum(nhat, 1)
            g1 = np.bincount(gid, g, len(act)) / n_ok
            g2 = np.bincount(gid, g * g, len(act)) / n_ok
            mu, var = pi * g1, np.maximum(pi * g2 - (pi * g1) ** 2, 1e-12)
            now = log_capital(tw.lo if sign < 0 else tw.up, m, sign, False, self.c)
            # predictive: mu is itself estimated from seen_b0 runs (variance var / seen_b0)
            pred = r * var * (1.0 + r / np.maximum(seen_b0, 1))
            z = (now + r * mu - lev) / np.sqrt(pred + 1e-12)
            prob = 0.5 * erfc(-z / np.sqrt(2.0))
            out[:, col] = (nhat >= 2) & (r > 0) & (prob < self.curtail)
        return out

    def primary_futile(self) -> np.ndarray:
        """(H,) F: primary-futile sides (p > alpha for sure) in each hypothesis' family."""
        prim = ((self.side == FUTILE) & (self.fut_level >= self.alpha)).sum(axis=1)
        per_family = np.bincount(self.family, weights=prim, minlength=self.family.max() + 1)
        return per_family[self.family].astype(np.int64)

    def _refresh_holm_bounds(self, act: np.ndarray) -> None:
        """q = floor(log2(F + 1)) per active side; recompute L, U at alpha / 2^q where q grew."""
        f = self.primary_futile()[act]
        q = np.floor(np.log2(f + 1.0)).astype(np.int64)
        for col, side, sign in ((0, self.lo, +1), (1, self.up, -1)):
            grew = q > self.q_hol[act, col]
            if not grew.any():
                continue
            g = act[grew]
            self.q_hol[g, col] = q[grew]
            lev = np.log(2.0 * 2.0 ** q[grew] / self.alpha)
            b = capital_bound(side.take(g), lev, sign, True, self.c)
            if col == 0:
                self.l_hol[g] = b
            else:
                self.u_hol[g] = b

    def runs_used(self) -> np.ndarray:
        """(H,) runs revealed to each hypothesis at its stop (budget if still running)."""
        sb = np.where(self.stop_batch < 0, self.n_batches, self.stop_batch)
        return np.minimum(sb * self.batch_size, self.budget)

    def p_values(self, runs: TwinRuns) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p_lo, p_up, nhat) at each hypothesis' stopping time (p = 1 if n or nhat is 0)."""
        h = len(self.hyps)
        used = self.runs_used()
        groups = np.arange(h)
        tw, nhat = self._twin_prefix(runs, used, groups)
        p_lo, p_up = np.ones(h), np.ones(h)
        ok = (self.obs.n > 0) & (nhat > 0)
        if ok.any():
            g = np.flatnonzero(ok)
            lo, up, t = self.lo.take(g), self.up.take(g), tw.take(g)
            s = self.obs_samples
            r = s.width[g]
            q_lo = (s.q_lo_hat[g] - self.y_lo[g]) / r
            q_up = (s.q_up_hat[g] - self.y_lo[g]) / r
            q_tw = _group_means(t.succ)
            k_lo = crossing(lo, t.lo, 0.5 * (q_lo + q_tw), True, self.c, 1e-3, 100)
            k_up = crossing(t.up, up, 0.5 * (q_up + q_tw), True, self.c, 1e-3, 100)
            p_lo[g] = np.minimum(1.0, 2.0 * np.exp(-k_lo))
            p_up[g] = np.minimum(1.0, 2.0 * np.exp(-k_up))
        # an early rejection was verified exactly at a*: p <= a* (crossing may overstate by tol)
        p_lo = np.where(self.side[:, 0] == REJECTED, np.minimum(p_lo, self.a_star), p_lo)
        p_up = np.where(self.side[:, 1] == REJECTED, np.minimum(p_up, self.a_star), p_up)
        return p_lo, p_up, nhat


@dataclass(frozen=True)
class FutureBets:
    """Bounds lambdabar_s on the bet at the s-th remaining run with X_0 in B_0 (s = 1..r),
    group after group (flat, ``offsets``), whatever the future values and entering pattern."""

    lam: np.ndarray  # (sum r,)
    offsets: np.ndarray  # (G + 1,)

    def log_growth(self, cap: np.ndarray, gain: np.ndarray) -> np.ndarray:
        """(G,) sum_s log(1 + min(lambdabar_s, cap) gain): the log of the largest product of
        the remaining factors when each moves the capital by at most ``gain`` per unit bet."""
        gid, _ = flat_layout(self.offsets)
        g = len(self.offsets) - 1
        term = np.log1p(np.minimum(self.lam, cap[gid]) * gain[gid])
        return np.bincount(gid, term, g) if len(term) else np.zeros(g)

    def largest(self) -> np.ndarray:
        """(G,) max_s lambdabar_s (0 where no run can still enter)."""
        g = len(self.offsets) - 1
        out = np.zeros(g)
        nz = np.diff(self.offsets) > 0
        if nz.any():
            out[nz] = np.maximum.reduceat(self.lam, self.offsets[:-1][nz])
        return out


def future_bet_bound(side: OrderedSide, nhat: np.ndarray, seen_b0: np.ndarray, r: np.ndarray,
                     delta0: np.ndarray) -> FutureBets:
    """Upper bound on the bet at each remaining run with X_0 in B_0, whatever happens.

    At the s-th remaining run with X_0 in B_0 (s = 1..r) the bet is
    lambda^2 = 2 log(1/delta0) i / ((1/4 + V_{i-1}) n_i) with i = E + 1, V_{i-1} the sum of
    the squared deviations of the successful entering runs so far, n_i = :func:`horizon`.
    What is fixed: S = seen_b0 + s - 1 and R = r - s + 1 (the plan). What is not: E in
    [nhat, nhat + s - 1] and V_{i-1} >= V_tau (the sum only grows). i / n_i =
    min(1, (E + 1) / (E + rho(E) R)) is a Moebius function of E with its pole at E < 0, so
    monotone on E >= 0: its maximum is at an end of the interval. Hence
    lambdabar_s^2 = 2 log(1/delta0) max(i/n_i at E = nhat, at E = nhat + s - 1) /
    (1/4 + V_tau). The bet placed at m is min(lambda, c/m) (K+) or min(lambda, c/(1-m)) (K-).
    """
    gid, t = flat_layout(side.offsets)
    mu = (0.5 + segment_cumsum(side.x, side.offsets, gid)) / (t + 1)
    sq = np.concatenate([[0.0], np.cumsum((side.x - mu) ** 2)])
    v_tau = sq[side.offsets[1:]] - sq[side.offsets[:-1]]
    r = np.asarray(r, np.int64)
    offs = np.concatenate([[0], np.cumsum(r)]).astype(np.int64)
    g, s = flat_layout(offs)
    seen, left = np.asarray(seen_b0)[g] + s - 1, r[g] - s + 1
    e_lo = np.asarray(nhat, float)[g]
    e_hi = e_lo + s - 1
    ratio = np.maximum((e_lo + 1) / horizon(e_lo, seen, left),
                       (e_hi + 1) / horizon(e_hi, seen, left))
    k = 2.0 * np.log(1.0 / np.asarray(delta0, float))[g] * ratio / (0.25 + v_tau[g])
    return FutureBets(np.sqrt(k), offs)


def _group_means(side: OrderedSide) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(side.x)])
    n = side.sizes
    return np.where(n > 0, (s[side.offsets[1:]] - s[side.offsets[:-1]]) / np.maximum(n, 1), 0.5)


@dataclass(frozen=True)
class AdaptiveOutcome:
    p_lo: np.ndarray  # (H,) anytime-valid p-values at the stopping time
    p_up: np.ndarray
    stop_batch: np.ndarray  # (H,) batches revealed when the parameter set stopped
    runs_used: np.ndarray  # (n_nodes,) runs simulated per node (prefix reuse)
    runs_per_hypothesis: np.ndarray  # (H,) runs revealed to each hypothesis
    decision: np.ndarray  # (H, 2) UNDECIDED/REJECTED/FUTILE per side at the stop
    nhat: np.ndarray  # (H,) entering twin runs at the stop
    rejected_lo: np.ndarray  # (H,) after the correction (per family = kind)
    rejected_up: np.ndarray
    twin_hours_adaptive: int  # node-runs simulated: X_0 in B_0 of a running hypothesis only
    twin_hours_fixed: int  # every node for the whole budget (prefix reuse)
    twin_hours_all_x0: int  # adaptive stopping, but every revealed X_0 simulated per node
    twin_hours_paper: int  # every sequence from scratch for the whole budget
    # as twin_hours_adaptive, without depth truncation (a twin that simulates whole paths)
    twin_hours_untruncated: int


def node_runs(paths: np.ndarray, per_hyp: np.ndarray, n_nodes: int) -> np.ndarray:
    """Runs needed per node: max over hypotheses whose path uses it (prefix reuse)."""
    out = np.zeros(n_nodes, dtype=np.int64)
    on = paths >= 0
    np.maximum.at(out, paths[on], np.broadcast_to(per_hyp[:, None], paths.shape)[on])
    return out


def node_needs(paths: np.ndarray, per_hyp: np.ndarray, in_b0: np.ndarray, n_nodes: int,
               reach: np.ndarray | None = None) -> np.ndarray:
    """(n_nodes, m) bool: run j of node v is needed iff some hypothesis whose path uses v has
    j revealed (j < per_hyp[h]) and its real X_0 in B_0 (only those runs can ever enter).

    Skipping the other runs changes no decision: a run whose X_0 is outside B_0 contributes
    the factor 1 to that hypothesis whatever the twin does. The X_0 order is untouched, so
    each hypothesis' runs stay a uniformly random order of the X_0 in D. With ``reach``
    ((H, T, m), :func:`reachable`) node a_1:s of run j is needed for h only while the run
    can still enter h (depth truncation; changes no decision either).
    """
    m = in_b0.shape[1]
    need = np.zeros((n_nodes, m), dtype=bool)
    revealed = in_b0 & (np.arange(m)[None, :] < np.asarray(per_hyp)[:, None])
    for s in range(paths.shape[1]):
        on = paths[:, s] >= 0
        rows = revealed[on] if reach is None else revealed[on] & reach[on, s]
        np.logical_or.at(need, paths[on, s], rows)
    return need


def paper_hours(hyps: pd.DataFrame, budget: int) -> int:
    """Twin-hours of the paper's scheme: every action sequence simulated from scratch,
    t hours per run, ``budget`` runs per distinct sequence (no prefix reuse)."""
    seqs = {tuple(int(a) for a in seq) for seq in hyps["actions"].tolist()}
    return int(sum(len(q) for q in seqs) * budget)


def embed_runs(runs: TwinRuns, idx: np.ndarray, h: int) -> TwinRuns:
    """TwinRuns of the hypotheses ``idx`` (sorted) placed in a study of h (others empty)."""
    sizes = np.zeros(h, dtype=np.int64)
    sizes[idx] = runs.values.sizes
    m = runs.in_b0.shape[1]
    in_b0, failed = np.zeros((h, m), bool), np.zeros((h, m), bool)
    in_b0[idx], failed[idx] = runs.in_b0, runs.failed
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return TwinRuns(Ragged(runs.values.values, offs), runs.run, in_b0, failed)


def run_to_stop(st: SequentialState, runs: TwinRuns) -> None:
    """Reveal batch after batch (batch 0 = no twin run) until every hypothesis stopped."""
    for b in range(0, st.n_batches + 1):
        st.update(runs, b)
        if not st.active.any():
            break


def correct_by_family(hyps: pd.DataFrame, p_lo: np.ndarray, p_up: np.ndarray, alpha: float,
                      correction: str) -> tuple[np.ndarray, np.ndarray]:
    """Holm / BY over both sides of every hypothesis of a family (kind), as run_tests does."""
    kind = hyps["kind"].to_numpy() if "kind" in hyps else np.zeros(len(hyps))
    h = len(hyps)
    r = correct_within(np.concatenate([p_lo, p_up]), np.concatenate([kind, kind]), alpha,
                       correction)
    return r[:h], r[h:]
