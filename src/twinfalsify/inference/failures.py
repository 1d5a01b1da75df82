"""Failed twin runs in the tests: conservative (worst case) or dropped (the paper).

A twin run that failed (init_failed, irreversible, timeout, error) at or before
hour t of a hypothesis whose B_0 its X_0 lies in has no outcome: we do not know
whether it would have entered B_1:t nor what it would have produced. Counted
per hypothesis as F = n_failed (``bounds.twin_runs``).

- ``drop`` (the paper's behaviour, Cornish et al. 2026, Sec. 6: failed Pulse
  runs are left out): the test sees only the nhat successful runs.
- ``conservative`` (default): a p-value that is valid whatever the failed runs would have
  produced: it is at least a valid p-value of the true completion. Exactly what it
  dominates depends on the method. Hoeffding (a symmetric closed form): every completion,
  so a rejection is a rejection of the completed sample however the failed runs had ended.
  Betting with plug-in bets (the default, "in place" below): every completion scored with
  the conservative sequence's own bets (the successful runs' plug-in bets, each failed run
  at its place), the true completion among them; it is not the maximum over completions of
  the ordinary test rerun on a completed sample, which would tune and place its bets on the
  completed values, so a conservative rejection can coexist with a completion that the
  ordinary test would not reject (such cases exist: a brute force over small cases finds
  them; the level holds regardless). Bootstrap and the grid mixture: a maximum over a
  few k (approximate, "Evaluation" below). Each failed run either fails B_1:t
  (excluded from the twin sample) or enters with some outcome in
  [y_lo, y_up]. For H_lo: Q_twin >= Q_lo the test rejects when the twin mean
  is low, so among the outcomes a failed run could take the least favourable
  to rejection is y_up; for H_up it is y_lo. With k of the F failed runs
  entering (k = 0..F, k = 0 is ``drop``),

      p_cons = max_{k = 0..F} p(twin sample + k copies of the least favourable value).

  Why this is the worst case over all completions: for the Hoeffding p-value
  (and any test whose p-value is non-increasing in the distance
  Qhat_lo - Qhat_twin at fixed sample sizes) moving an entering failed run's
  value to y_up can only raise p_lo, so for each k the worst completion puts
  every entering failed run at y_up; what is left is the maximum over k.
  So for these tests validity holds for every completion, in particular the true
  one (assuming the successful runs are i.i.d. draws of the runs the twin
  would produce; failures need not be at random).

Evaluation. Hoeffding's p (``inference.hoeffding``) is a closed form, so it is
evaluated at every k = 0..F and the maximum is exact. For the betting test with plug-in bets
(the default method) the order matters, and each failed run is placed where its run stands
(below). For any other method (bootstrap, the betting grid mixture, ...) each k costs a full
evaluation, so ``conservative_pvalues`` evaluates k = 0, k = F and the k that
maximises the Hoeffding p-value (plus ``extra_points`` evenly spaced k) and
takes the maximum. That maximum is always >= the drop p-value (k = 0 is
included) but it is exact only when the method's p(k) peaks at one of those
points: it does when p(k) is monotone in k (k = 0 or k = F: the usual case,
adding y_up both moves the mean against rejection and narrows the interval)
or follows Hoeffding's shape (Hoeffding-argmax); an interior peak elsewhere is
possible in principle for resampling methods and would be missed. Pass
``extra_points`` to search a grid when that matters. These methods are symmetric in
the twin sample, so where a completion stands does not matter to them.

Failed runs in place (betting, plug-in bets; ``samples.failed_run`` from
``bounds.twin_runs``). The running maximum of the capital depends on where each value
stands, so completions appended after the successful runs would sit at places chosen by
which runs failed, which may depend on the outcome. Instead the twin sequence is every run
that entered or failed, in the plan's run order (the keyed X_0 order, ``inference.order``),
permuted by the data order's hash over its size n_c = nhat + F (``betting.worst_twin_sides``).
The bets are the plug-in bets of the successful runs only, tuned for n_c: each reads only
the successful values before it, and a failed run gets the bet the next successful run would
get. A failed run enters the H_lo side (K- of the twin) with x = 1 and the H_up side (K+)
with x = 0. Why this is valid whatever the failed runs would have produced:

- given n_c, the runs that entered or failed are i.i.d. (each run's X_0, outcome, entry
  and failure are a function of its own X_0 and noise; the plan order is a random
  permutation independent of them), and a fixed permutation keeps them so;
- the true completion gives each failed run either no entry (factor 1) or an outcome
  x in [0, 1] (factor 1 - b (x - m) >= 1 - b (1 - m) for K-, b >= 0, m <= 1). With the bets
  above, which are predictable in this sequence, the capital K-_true of the true completion
  is a test supermartingale under H_lo (the mean of an entering run's outcome is >= m), and
  K-_cons <= K-_true at every time and every m, so max_t K-_cons <= max_t K-_true;
- the union rule's crossing is monotone in the twin's capital, so p_cons >= p_true, and
  p_true is valid by Ville's inequality. K+ mirrors it with x = 0.

The reported p-value is max(p_cons, p_drop): >= a valid p-value, so valid, and never below
the drop p-value. Without failed runs the sequence and bets are the drop test's (bit for
bit). The same construction is the sequential mode's (``inference.sequential``). Tested:
``tests/inference/test_failed_places.py`` (placement, a brute-force loop, dominance over random
completions, level under outcome-dependent failures).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np

from twinfalsify.inference.betting import (
    DEFAULT_BETS,
    PLACING_BETS,
    betting_test,
    default_tune_alpha,
)
from twinfalsify.inference.hoeffding import hoeffding_pvalue, hoeffding_test
from twinfalsify.inference.samples import HypothesisSamples, Ragged

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]
MODES = ("conservative", "drop")
_MAX_CELLS = 5_000_000  # (hypothesis, k) pairs per vectorised Hoeffding chunk


def augment(samples: HypothesisSamples, k: np.ndarray, value: np.ndarray) -> HypothesisSamples:
    """The samples with k[h] extra twin outcomes equal to value[h] in hypothesis h."""
    k = np.asarray(k, dtype=np.int64)
    if k.shape != (len(samples),) or (k < 0).any():
        raise ValueError(f"augment: k must be {len(samples)} non-negative counts")
    groups = [
        np.concatenate([samples.twin.group(h), np.full(int(k[h]), float(value[h]))])
        for h in range(len(samples))
    ]
    return HypothesisSamples(
        y_lo=samples.y_lo, y_up=samples.y_up, n=samples.n, follow=samples.follow,
        twin=Ragged.from_groups(groups), keys=samples.keys, follow_pos=samples.follow_pos,
    )  # fmt: skip


def hoeffding_factor(method: Method) -> float | None:
    """The constant c if ``method`` is the closed-form Hoeffding test, else None."""
    if method is hoeffding_test:
        return 2.0
    if isinstance(method, partial) and method.func is hoeffding_test and not method.args:
        return float(method.keywords.get("factor", 2.0))
    return None


def hoeffding_worst_k(
    samples: HypothesisSamples, n_failed: np.ndarray, factor: float = 2.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(p_lo, p_up, k_lo, k_up): max over k = 0..F of Hoeffding's p, and the maximising k.

    Side lo adds k outcomes y_up to the twin sample (mean (S + k y_up)/(nhat + k)),
    side up adds k outcomes y_lo; S = sum of the clipped twin outcomes. Exact:
    every k is evaluated (the p-value is a closed form, see inference.hoeffding).
    Ties go to the smallest k.
    """
    f = np.asarray(n_failed, dtype=np.int64)
    h_total = len(samples)
    if f.shape != (h_total,) or (f < 0).any():
        raise ValueError(f"n_failed must be {h_total} non-negative counts, got shape {f.shape}")
    s = samples.twin_f.sums()
    nhat = samples.nhat.astype(float)
    q_lo, q_up, width, n = samples.q_lo_hat, samples.q_up_hat, samples.width, samples.n
    out = {
        "p_lo": np.ones(h_total), "p_up": np.ones(h_total),
        "k_lo": np.zeros(h_total, np.int64), "k_up": np.zeros(h_total, np.int64),
    }  # fmt: skip
    if h_total == 0:
        return out["p_lo"], out["p_up"], out["k_lo"], out["k_up"]
    cum = np.cumsum(f + 1)
    cuts = np.searchsorted(cum, np.arange(_MAX_CELLS, cum[-1], _MAX_CELLS), side="right")
    for idx in np.split(np.arange(h_total), np.unique(cuts[(cuts > 0) & (cuts < h_total)])):
        reps = f[idx] + 1
        hh = np.repeat(idx, reps)
        offs = np.concatenate([[0], np.cumsum(reps)])
        kk = np.arange(offs[-1]) - np.repeat(offs[:-1], reps)
        m = nhat[hh] + kk
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_lo = (s[hh] + kk * samples.y_up[hh]) / m
            mean_up = (s[hh] + kk * samples.y_lo[hh]) / m
        p_lo = hoeffding_pvalue(q_lo[hh] - mean_lo, width[hh], n[hh], m, factor)
        p_up = hoeffding_pvalue(mean_up - q_up[hh], width[hh], n[hh], m, factor)
        for p, name in ((p_lo, "lo"), (p_up, "up")):
            best = np.maximum.reduceat(p, offs[:-1])
            hit = p == np.repeat(best, reps)  # first k reaching the maximum
            first = np.minimum.reduceat(np.where(hit, kk, np.iinfo(np.int64).max), offs[:-1])
            out[f"p_{name}"][idx] = best
            out[f"k_{name}"][idx] = first
    return out["p_lo"], out["p_up"], out["k_lo"], out["k_up"]


def conservative_pvalues(
    method: Method,
    samples: HypothesisSamples,
    n_failed: np.ndarray,
    *,
    extra_points: int = 0,
    base: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Worst case over the failed runs: (p_lo, p_up) = max over k of p(sample + k values).

    method: any test ``samples -> (p_lo, p_up)``. base: the method's p-values
    on ``samples`` (k = 0) if already computed. Exact for the Hoeffding test
    (every k); for other methods k in {0, F, Hoeffding-argmax} plus
    ``extra_points`` evenly spaced k (see the module docstring). Always
    >= the drop-failures p-values.
    """
    f = np.asarray(n_failed, dtype=np.int64)
    if f.shape != (len(samples),) or (f < 0).any():
        raise ValueError(f"n_failed must be {len(samples)} non-negative counts")
    placed = samples.failed_run is not None
    if placed and not np.array_equal(samples.failed_run.sizes, f):
        raise ValueError("n_failed does not match the failed runs' places (failed_run)")
    in_place = placed and _places_failed_runs(method)
    samples_drop = samples.without_failed()
    factor = hoeffding_factor(method)
    if factor is not None:
        p_lo, p_up, _, _ = hoeffding_worst_k(samples_drop, f, factor)
        return p_lo, p_up
    method = family_tuned(method, len(samples))
    p0_lo, p0_up = base if base is not None else method(samples_drop)
    p_lo, p_up = np.asarray(p0_lo, float).copy(), np.asarray(p0_up, float).copy()
    idx = np.flatnonzero(f > 0)
    if idx.size == 0:
        return p_lo, p_up
    if in_place:  # each failed run's worst case at its own place; >= drop by the max
        c_lo, c_up = method(samples.take(idx))
        p_lo[idx], p_up[idx] = np.maximum(p_lo[idx], c_lo), np.maximum(p_up[idx], c_up)
        return p_lo, p_up
    sub = samples_drop.take(idx)
    fs = f[idx]
    _, _, k_lo, k_up = hoeffding_worst_k(sub, fs)
    candidates_lo = [fs, k_lo]
    candidates_up = [fs, k_up]
    for j in range(1, extra_points + 1):
        kj = np.round(fs * j / (extra_points + 1)).astype(np.int64)
        candidates_lo.append(kj)
        candidates_up.append(kj)
    for k in _unique_rows(candidates_lo):
        p_lo[idx] = np.maximum(p_lo[idx], method(augment(sub, k, sub.y_up))[0])
    for k in _unique_rows(candidates_up):
        p_up[idx] = np.maximum(p_up[idx], method(augment(sub, k, sub.y_lo))[1])
    return p_lo, p_up


def family_tuned(method: Method, h: int) -> Method:
    """The method with the tuning of a family of h parameter sets fixed. Betting tunes its
    bets by default at alpha / (2H) of the samples it is given (one family per call,
    :func:`failure_pvalues`' ``families``); completions (below) and
    sensitivity widenings are evaluated on subsets or tilings, so the tuning of the whole
    family is bound (the orders are per hypothesis already, ``betting._order_keys``)."""
    if isinstance(method, partial) and method.func is betting_test and \
            method.keywords.get("tune_alpha") is None:
        return partial(method, tune_alpha=default_tune_alpha(h, method.keywords.get("alpha",
                                                                                     0.05)))
    if method is betting_test:
        return partial(betting_test, tune_alpha=default_tune_alpha(h))
    return method


def _places_failed_runs(method: Method) -> bool:
    """True for the betting test with bets that place failed runs (``betting.PLACING_BETS``:
    plug-in and STaR, the default, whether named or not; module doc)."""
    if method is betting_test:
        return True
    return (isinstance(method, partial) and method.func is betting_test
            and method.keywords.get("bets", DEFAULT_BETS) in PLACING_BETS)


def _unique_rows(rows: list[np.ndarray]) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for r in rows:
        if not any(np.array_equal(r, o) for o in out):
            out.append(r)
    return out


def failure_pvalues(
    method: Method,
    samples: HypothesisSamples,
    n_failed: np.ndarray,
    mode: str = "conservative",
    families: np.ndarray | None = None,
    **kwargs,
) -> tuple[np.ndarray, np.ndarray]:
    """p-values under the chosen handling of failed runs (``MODES``).

    ``families``: each parameter set's family (the correction's, e.g. the bound kind). A
    method tuned to its family's size (the betting test: :func:`family_tuned`) is then
    called once per family, so its bets aim at that family's smallest Holm level; every
    other method sees all parameter sets at once. A hypothesis' betting order depends on
    its own key only, so the split changes nothing but the tuning.
    """
    if families is not None and family_tuned(method, 1) is not method:
        fam = np.asarray(families)
        if fam.shape != (len(samples),):
            raise ValueError(f"families must label each of the {len(samples)} parameter sets")
        labels, inv = np.unique(fam.astype(str), return_inverse=True)
        f = np.asarray(n_failed)
        p_lo, p_up = np.ones(len(samples)), np.ones(len(samples))
        for j in range(len(labels)):
            idx = np.flatnonzero(inv == j)
            sub = samples if len(labels) == 1 else samples.take(idx)
            p_lo[idx], p_up[idx] = failure_pvalues(family_tuned(method, len(idx)), sub, f[idx],
                                                   mode, **kwargs)
        return p_lo, p_up
    if mode == "drop":
        return method(samples.without_failed())
    if mode == "conservative":
        return conservative_pvalues(method, samples, n_failed, **kwargs)
    raise ValueError(f"testing.failed_runs: unknown mode {mode!r}; choose one of {MODES}")
