"""Exact test of H_lo / H_up from betting confidence bounds (Waudby-Smith & Ramdas 2024).

Bounds. Rescale a side's sample to x_i = (clip(y_i) - y_lo) / R in [0, 1] (R = y_up - y_lo),
put it in its data order (see "Order" below) and, for a candidate mean m, form the
capital processes (WSR 2024, Sec. 4, "hedged capital", one-sided halves):

    K+_t(m) = prod_{i<=t} (1 + lambda+_i(m) (x_i - m)),   lambda+_i(m) = min(lambda_i, c / m),
    K-_t(m) = prod_{i<=t} (1 - lambda-_i(m) (x_i - m)),   lambda-_i(m) = min(lambda_i, c / (1 - m)),

with the predictable plug-in bet tuned for a fixed sample size n (WSR 2024, Sec. 5.1
and Remark "fixed-n"): lambda_i = sqrt(2 log(1/delta0) / (n sigma2_{i-1})),
mu_i = (1/2 + sum_{j<=i} x_j) / (i + 1), sigma2_i = (1/4 + sum_{j<=i} (x_j - mu_j)^2) / (i + 1),
sigma2_0 = 1/4, c = 0.9 (WSR use 1/2 or 3/4; any c < 1 is valid, 0.9 is
tighter at the small levels Holm needs, measured in docs/reference/benchmarks.md).
As in WSR's
Theorem 3 the bet is truncated only at c/m (c/(1-m)), never at c itself: near a
boundary (m small for K+) bets above 1 are allowed and still keep every factor
>= 1 - c > 0, which is what makes small skewed samples near 0 or 1 tight.
lambda_i depends on x_1..x_{i-1} only, so when the true
mean is <= m (resp. >= m) K+ (K-) is a non-negative supermartingale with K_0 = 1
and Ville's inequality gives P(max_{t<=n} K_t >= 1/delta) <= delta. Hence the
one-sided (1 - delta) bounds

    lower(delta) = sup{m : max_t K+_t(m) >= 1/delta},
    upper(delta) = inf{m : max_t K-_t(m) >= 1/delta},

valid in finite samples for every delta. Each factor of K+ is non-increasing in m
(K- non-decreasing), so the bounds are monotone in delta and the sets are intervals.

p-value. Because lambda_i does not depend on the level being tested (it is tuned
once, at delta0), the union rule at alpha (delta = alpha/2 per side) rejects H_lo
iff some m has max_t K+_lo,t(m) >= 2/alpha and max_t K-_twin,t(m) >= 2/alpha, so

    p_lo = min(1, 2 / K*),   K* = max_m min(max_t K+_lo,t(m), max_t K-_twin,t(m)),

attained where the decreasing and the increasing curve cross; found by a
vectorised safeguarded false-position search on m (p is reported at a bracket end,
so never understated). Mirror for H_up (K+ of the twin against K- of Y_up).
Validity: under H_lo (Q_twin >= Q_lo) any such m is either >= Q_lo (then
K+_lo(Q_lo) >= 2/alpha, probability <= alpha/2) or < Q_twin (then K-_twin(Q_twin) >=
2/alpha, probability <= alpha/2).

Order (plug-in and STaR bets). The bound depends on the order of the sample; the
argument above needs only that the sequence be i.i.d., i.e. that the order not depend on the
values. ``order: data`` (default) takes it from the data's content (``inference.order``):

- observational side: the n entering trajectories listed by a keyed hash of their own
  X_0:t, A_1:t (key: the recorded study seed; ``samples.follow_pos``: each follower's rank
  among them; the n - n_follow others carry the fill value), then permuted by a fixed hash
  of (hypothesis key, position) (splitmix64). The keyed hash is a uniformly random
  permutation independent of the values (``inference.order``), and a permutation that
  depends on (hypothesis, n) only keeps the sequence i.i.d. No stay id and no row order
  enters.
- twin side: the entering runs in the plan's X_0 order (D's stays listed by the same keyed
  hash of their X_0, ``runs.plan``), permuted by the same fixed hash. Under
  ``failed_runs: conservative`` each failed run stands at its own place in that order with
  its worst case (:func:`worst_twin_sides`; why it is valid: ``inference.failures``).

Hence a p-value is a function of the data's values and the recorded seed only: renumbering
the stays or reordering the input rows changes no order (p-values can differ in the last
bits, as sums run over rows in another order), and another seed is another valid
randomisation. ``bets: mixture`` is order-free, at a measured price in width (below).
Without ``follow_pos`` (samples built by hand) the followers are taken as listed first and
the hash permutation stands in for a random one. ``order: seed``: a uniformly random
permutation of the listing seeded by the config seed instead. ``orders`` K > 1 averages the
terminal capital over K hash (or seeded) orders (an average of e-values is an e-value,
Markov).

Why not an order-free default. An order-free (symmetric) p-value cannot use the running
maximum over t, which depends on the order, so it rests on the terminal capital. Measured
(``benchmarks/bench_betting_wsr.py``, docs/reference/benchmarks.md): even the constant bet
tuned at the TRUE variance, the best any bet tuned on independent data (D0, a pilot) can
approach, is wider than WSR's running-maximum interval (1.10-1.19x at alpha = 0.05, n >= 50);
the grid mixture, 16 averaged orders, D0-tuned and pilot-tuned constant bets are as wide or
wider.
The plug-in in data order is WSR's interval itself (ratio 1.00) and seed-free.

Order-free mixture ("mixture" bets). Replace the predictable bet by a
uniform mixture over a fixed grid of J constant bets,

    E+(m) = (1/J) sum_j prod_{i<=n} (1 + min(lambda_j, c/m) (x_i - m)),   E- mirrored,
    lambda_j = lambda_min r^j (j = 0..J-1),  lambda_min = sqrt(8 log(1/delta0) / n),

lambda_min being the fixed-n plug-in bet at the largest variance 1/4 (in the Gaussian
approximation log K ~ n (lambda gap - lambda^2 sigma2 / 2), a bet below lambda_min is best only
for gaps too small to reach 1/delta0 at n samples whatever the bet) and r^(J-1) spanning
variances down to 1/(4 r^(2(J-1))). The bets depend on n, m and delta0 only, never on the
values, so each product is a product of independent factors with mean <= 1 under mean <= m
(K+): E[E+(m)] <= 1, and Markov gives P(E+(m) >= 1/delta) <= delta. A product does not depend
on the order of its factors: the p-value is a symmetric function of each sample, so no seed
enters and no decision can flip with one. Each factor is monotone in m as above, so E+ is
non-increasing (E- non-decreasing) and the crossing and union arguments below hold with E in
place of max_t K. The price of the fixed grid, when the best constant bet lies inside the
grid [lambda_min, lambda_min r^(J-1)]: log J nats (J = 6: 1.8) and a discretisation of the
best bet by at most a factor sqrt(r); a best bet outside the grid (variance below
1/(4 r^(2(J-1))), or a gap needing a bet below lambda_min) costs more, without bound.
Measured in docs/reference/benchmarks.md.

STaR bets ("star", the default). Target-recalculating bets after STaR-Bets (Voracek &
Orabona 2025): in the same data order, each bet is sized so that the values left could still
raise the capital to the target 1/delta0 (its own capital at m so far), at the current
variance:

    b_i(m) = min( sqrt(2 max(r_i, r0) / ((n - i + 1) S_i(m))) exp(min(r_i - r0, 0)), c / m ),
    r_i = R - log K+_{i-1}(m),   S_i(m) = min(sigma2_{i-1}, m (1 - m)),
    R = log(1/delta0),   r0 = 1/2,

sigma2_{i-1} the plug-in variance above (K- mirrored: 1 - x at 1 - m). In a Gaussian
approximation n' values at bet b and variance S grow log K by n' (b gap - b^2 S / 2), whose
largest value reaches a remaining need r exactly when b = sqrt(2 r / (n' S)); WSR's bet is
this with r = R and n' = n throughout. m (1 - m) is the largest variance of a value in
[0, 1] with mean m, the cap STaR-Bets put on S. Below a need of r0 the bet decays as
exp(r_i - r0) where STaR-Bets' goes as sqrt(r_i) to 0 (their bet freezes at the target):
the same slope at r0, and the steepest decay that keeps the capital monotone in m (below).
Other differences to STaR-Bets' code: the plug-in variance around the running mean (theirs:
the second moment about m, plus a prior term), the truncation c < 1 and the running maximum
(theirs: the terminal capital).
Validity: b_i(m) reads x_1..x_{i-1}, n, delta0 and m only, so for a true mean <= m every
factor has conditional mean 1 + b_i (mean - m) <= 1 and K+ is a non-negative supermartingale
(every factor >= 1 - c > 0): Ville's inequality applies as above.
Monotonicity in m (what the crossing and the bound search need): write log K_i = h(log
K_{i-1}, m), h(l, m) = l + log(1 + b(l, m) (x - m)). (a) h is non-decreasing in l:
d h / d l = (1 + (x - m) (b + d b / d l)) / (1 + b (x - m)). Where the square root binds with
need r = R - l >= r0, d b / d l = -b / (2 r) >= -b; where the exponential binds (r < r0),
d b / d l = -b exactly; where c/m binds, 0. So b + d b / d l is in [0, b]: for x >= m the
numerator is >= 1, for x < m it is >= 1 - (m - x) b >= 1 - c > 0. (b) h is non-increasing
in m at fixed l: d h / d m has the sign of (d b / d m) (x - m) - b, and b is S^(-1/2) times
a factor free of m, with d log S / d m = 0 (sigma2) or 1/m - 1/(1 - m) (m (1 - m)), or c/m:
so -1/m <= d log b / d m <= 1/(1 - m), which gives (d b / d m) (x - m) <= b for every x in
[0, 1]. By induction on i, log K+_i(m) is non-increasing in m for every i, and so is its
running maximum (K- non-decreasing). A bet decaying faster than exp(-l) near the target
(STaR-Bets' sqrt(r) has an unbounded slope at r = 0) breaks (a), and the capital need not be
monotone in m. (a) is also what makes the worst case of a failed run the least capital of
every completion scored with the same variances: the worst factor gives the least capital
so far, and every later capital is non-decreasing in it (:func:`worst_twin_sides`,
``inference.failures``). The bets depend on the tuning level delta0 through the target only,
so, as for the plug-in bets, the p-value p = 2 / K* is valid at every level, and Holm's
decisions at levels other than delta0's use capitals aimed at 1/delta0. Measured width:
0.91-1.02x deterministic STaR-Bets in 27 cells (plug-in bets 0.94-1.26x), never wider than
0.90x Hoeffding (docs/reference/benchmarks.md).

Tuning level delta0: by default alpha0 / 2 with alpha0 = alpha / (2 H), alpha the family's
level ``testing.alpha`` and H the parameter sets of the family (a twin's hypotheses of one
bound kind): Holm's smallest level over its 2H one-sided hypotheses, where its first decision
is made (``falsify.run_tests`` calls the test once per family); any delta0 gives valid
bounds, it only moves where they are tightest.

Assumptions: each side i.i.d. and bounded in [y_lo, y_up] after clipping; data order as
above. The sides need not be independent (the union rule is a union bound over two
marginally valid bounds; the twin's X_0 come from the same D patients). References:
I. Waudby-Smith & A. Ramdas (2024), "Estimating means of bounded random variables by
betting", JRSS-B 86(1):1-27; V. Voracek & F. Orabona (2025), "STaR-Bets: Sequential
Target-Recalculating Bets for Tighter Confidence Intervals", NeurIPS 2025 (arXiv
2505.22422); Ville (1939).
"""

from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from twinfalsify.inference.capital import (  # noqa: F401 - C_TRUNC, OrderedSide re-exported
    C_TRUNC,
    OrderedSide,
    StarBets,
    capital_bound,
    chunk_ranges,
    crossing,
    flat_layout,
    log_capital,
    plugin_bets,
    running_moments,
    segment_cumsum,
    star_bets,
)
from twinfalsify.inference.samples import HypothesisSamples, Ragged

BETS = ("plugin", "mixture", "star")  # WSR plug-in | order-free mixture | STaR (default)
DEFAULT_BETS = "star"
PLACING_BETS = ("plugin", "star")  # bets that put each failed run's worst case at its place
ORDER_KINDS = ("data", "seed")  # plug-in order: fixed by the data (default) | seeded
MIX_GRID = 6  # J constant bets in the mixture (power against J: docs/explanation/statistics.md)
MIX_RATIO = 1.7  # r: spacing of the grid (J = 6: bets lambda_min .. 14 lambda_min)


_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


def _mix64(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser (Steele et al. 2014): a bijective avalanche hash of uint64."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


_DATA_ORDER = 1 << 40  # hash domain of the seedless data order (seeded bases are < 2^40)


_ORDER_CACHE: dict | None = None  # permutations kept by :func:`order_cache`, else None


@contextmanager
def order_cache(max_bytes: int = 1 << 29):
    """Within the block, every data order (:func:`_order_keys`) computed is kept and reused.

    A permutation depends on the group sizes, hypothesis keys, copies, seed and side only,
    never on the values or on [y_lo, y_up], so a sweep that tests the same samples under
    other ranges (``inference.sensitivity``) orders them once; the p-values are those of
    separate calls, bit for bit. ``max_bytes`` bounds the memory kept.
    """
    global _ORDER_CACHE
    outer, _ORDER_CACHE = _ORDER_CACHE, {"max": int(max_bytes), "bytes": 0, "perms": {}}
    try:
        yield
    finally:
        _ORDER_CACHE = outer


def _order_keys(sizes: np.ndarray, keys: np.ndarray, copy: np.ndarray, seed: int | None,
                salt: int) -> np.ndarray:
    """:func:`_hashed_order`, kept for reuse inside :func:`order_cache`."""
    cache = _ORDER_CACHE
    if cache is None:
        return _hashed_order(sizes, keys, copy, seed, salt)
    arrays = [np.ascontiguousarray(a, np.int64) for a in (sizes, keys, copy)]
    key = (hashlib.blake2b(b"".join(a.tobytes() for a in arrays), digest_size=16).digest(),
           seed, salt, len(arrays[0]))
    perm = cache["perms"].get(key)
    if perm is None:
        perm = _hashed_order(sizes, keys, copy, seed, salt)
        if len(perm) < 2**31:  # kept as int32: half the memory, the same indices
            perm = perm.astype(np.int32)
        if cache["bytes"] + perm.nbytes <= cache["max"]:
            perm.setflags(write=False)
            cache["perms"][key] = perm
            cache["bytes"] += perm.nbytes
    return perm


def _hashed_order(sizes: np.ndarray, keys: np.ndarray, copy: np.ndarray, seed: int | None,
                  salt: int) -> np.ndarray:
    """A pseudo-random permutation within every group (flat indices), seeded or seedless.

    Sort by group id + U key, U a hash of (seed, salt, hypothesis key, copy, position in
    the group): within a group the order is that of i.i.d.-like uniform keys, i.e. a
    uniformly random permutation, independent of the data. Because U depends on the
    hypothesis' own key and the position only, a hypothesis gets the same order whatever
    other hypotheses are tested with it. ``seed`` None: a fixed
    hash domain instead of a seed (the data order, module doc): the permutation is then a
    fixed function of (hypothesis key, copy, group size), so applied to a sequence that is
    already i.i.d. it leaves it i.i.d. whatever the hash. U is the top 53 bits of
    splitmix64(h_g ^ position); equal U keep their positions' order (a stable sort).
    """
    sizes = np.asarray(sizes, np.int64)
    head = _DATA_ORDER if seed is None else (int(seed) & 0xFFFFFFFF) << 8
    with np.errstate(over="ignore"):
        base = _mix64(np.array([head | salt], dtype=np.uint64))
        hk = _mix64(base ^ np.asarray(keys, np.int64).astype(np.uint64))
        hk = _mix64(hk ^ (np.asarray(copy, np.int64).astype(np.uint64) << np.uint64(40)))
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    from twinfalsify.inference import kernels  # numba: imported when first needed

    return kernels.order_within_groups(hk, offsets)


def _tile(samples: HypothesisSamples, k: int) -> tuple[HypothesisSamples, np.ndarray]:
    """K copies of the samples, copy-major, keeping every hypothesis' key; and copy index."""
    return samples.tile(k), np.repeat(np.arange(k), len(samples))


def _checked(samples: HypothesisSamples, delta0: np.ndarray | float
             ) -> tuple[int, np.ndarray, np.ndarray]:
    """(H, widths, delta0 per hypothesis); one error naming the hypotheses with y_up <= y_lo."""
    h = len(samples)
    width = samples.width
    if np.any(~(width > 0)):
        bad = np.flatnonzero(~(width > 0))[:5]
        raise ValueError(f"betting: y_up must exceed y_lo (hypotheses {bad.tolist()})")
    return h, width, np.broadcast_to(np.asarray(delta0, float), (h,))


def ordered_sides(
    samples: HypothesisSamples, delta0: np.ndarray | float, seed: int = 0, c: float = C_TRUNC,
    orders: int = 1, order: str = "seed", star: bool = False,
) -> tuple[OrderedSide, OrderedSide, OrderedSide]:
    """(Y_lo, Y_up, twin) rescaled to [0, 1], in data or seeded random order, with their bets
    (``star``: also the target-recalculating bets' inputs, from the same variances).

    The observational sample is materialised here (``order`` "data" with
    ``samples.follow_pos``: every entering trajectory at its content-keyed position, followers'
    values and n - n_follow fill values; otherwise followers, then fill values) because
    every position carries its own bet; Y_lo and Y_up share the order. That sequence is
    then permuted by a hash of (seed, side, hypothesis key, copy, position)
    (``_order_keys``; ``order`` "data": no seed, module doc "Order"), built in two threads,
    chunk by chunk of hypotheses (cache-sized). ``orders`` K > 1: K independently ordered
    copies.
    """
    from twinfalsify.inference import kernels  # numba: imported when first needed

    if order not in ORDER_KINDS:
        raise ValueError(f"betting: order must be one of {', '.join(ORDER_KINDS)}, got {order!r}")
    use_pos = order == "data" and samples.follow_pos is not None
    hseed = None if order == "data" else seed
    h, _, d0 = _checked(samples, delta0)
    copy = np.zeros(h, np.int64)
    if orders > 1:
        samples, copy = _tile(samples, int(orders))
        d0, h = np.tile(d0, int(orders)), len(samples)
    keys = samples.hyp_keys
    n = samples.n.astype(np.int64)
    nf = samples.n_follow
    offs = np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
    follow, twin = samples.follow, samples.twin
    y_lo = samples.y_lo

    def side(x: np.ndarray, offsets: np.ndarray, bet: np.ndarray) -> OrderedSide:
        """``bet``: the plug-in bets, or with ``star`` the variances STaR bets read."""
        if star:
            return OrderedSide(x, None, offsets, star=star_bets(x, offsets, d0, sig2=bet))
        return OrderedSide(x, bet, offsets)

    def bets(x: np.ndarray, o: np.ndarray, h0: int, h1: int, var: np.ndarray, lay=None) -> None:
        """``var`` (a chunk's variances) becomes the plug-in bets, unless STaR bets read it."""
        if not star:
            var[:] = plugin_bets(x, o, d0[h0:h1], c, lay, sig2=var)

    def obs() -> tuple[OrderedSide, OrderedSide]:
        x_lo, x_up = np.empty(offs[-1]), np.empty(offs[-1])
        v_lo, v_up = np.empty(offs[-1]), np.empty(offs[-1])
        for h0, h1 in chunk_ranges(n):
            o = offs[h0: h1 + 1] - offs[h0]
            fsl = slice(follow.offsets[h0], follow.offsets[h1])
            fg = np.repeat(np.arange(h1 - h0), nf[h0:h1])
            is_f = np.zeros(o[-1], dtype=bool)
            if use_pos:  # each follower at its content-keyed position among the entering ones
                at = o[:-1][fg] + samples.follow_pos.values[fsl].astype(np.int64)
                is_f[at] = True
                if is_f.sum() != len(at):
                    raise ValueError("betting: two followers share a position (follow_pos)")
            else:  # the followers first, in their listed order
                at = o[:-1][fg] + flat_layout(follow.offsets[h0: h1 + 1]
                                              - follow.offsets[h0])[1] - 1
                is_f[at] = True
            staged = np.zeros(o[-1])
            staged[at] = follow.values[fsl]
            perm = _order_keys(n[h0:h1], keys[h0:h1], copy[h0:h1], hseed, 1)
            sl = slice(offs[h0], offs[h1])
            bounds = (y_lo[h0:h1], samples.y_up[h0:h1])
            kernels.rescaled_moments(staged, is_f, perm, o, *bounds, 0.0, x_lo[sl], v_lo[sl])
            kernels.rescaled_moments(staged, is_f, perm, o, *bounds, 1.0, x_up[sl], v_up[sl])
            lay = None if star else flat_layout(o)  # shared by Y_lo and Y_up
            bets(x_lo[sl], o, h0, h1, v_lo[sl], lay)
            bets(x_up[sl], o, h0, h1, v_up[sl], lay)
        return side(x_lo, offs, v_lo), side(x_up, offs, v_up)

    def twin_side() -> OrderedSide:
        sizes = twin.sizes
        xt, vt = np.empty(twin.offsets[-1]), np.empty(twin.offsets[-1])
        for h0, h1 in chunk_ranges(sizes):
            o = twin.offsets[h0: h1 + 1] - twin.offsets[h0]
            sl = slice(twin.offsets[h0], twin.offsets[h1])
            perm = _order_keys(sizes[h0:h1], keys[h0:h1], copy[h0:h1], hseed, 2)
            kernels.rescaled_moments(twin.values[sl], np.ones(o[-1], dtype=bool), perm, o,
                                     y_lo[h0:h1], samples.y_up[h0:h1], 0.0, xt[sl], vt[sl])
            bets(xt[sl], o, h0, h1, vt[sl])
        return side(xt, twin.offsets, vt)

    with ThreadPoolExecutor(2) as pool:
        f_obs, f_tw = pool.submit(obs), pool.submit(twin_side)
        (lo, up), tw = f_obs.result(), f_tw.result()
    k = max(int(orders), 1)
    return (OrderedSide(lo.x, lo.lam, lo.offsets, k, lo.star),
            OrderedSide(up.x, up.lam, up.offsets, k, up.star),
            OrderedSide(tw.x, tw.lam, tw.offsets, k, tw.star))


def twin_candidates(samples: HypothesisSamples) -> tuple[Ragged, np.ndarray]:
    """The twin runs that entered or failed, per hypothesis, in the plan's run order.

    (values rescaled to [0, 1] with NaN at failed runs, flat bool ``failed``). Needs
    ``samples.twin_run`` / ``failed_run`` (``bounds.twin_runs``).
    """
    if samples.twin_run is None:
        raise ValueError("betting: failed runs need their places (twin_run, failed_run)")
    tw, fr, tr = samples.twin_f, samples.failed_run, samples.twin_run
    gid = np.concatenate([tw.group_ids(), fr.group_ids()])
    run = np.concatenate([tr.values, fr.values])
    failed = np.concatenate([np.zeros(len(tw.values), bool), np.ones(len(fr.values), bool)])
    g = tw.group_ids()
    x = (tw.values - samples.y_lo[g]) / samples.width[g]
    x = np.concatenate([x, np.full(len(fr.values), np.nan)])
    order = np.lexsort((run, gid))
    if np.any((np.diff(run[order]) == 0) & (np.diff(gid[order]) == 0)):
        raise ValueError("betting: a twin run is listed twice (twin_run, failed_run)")
    sizes = tw.sizes + fr.sizes
    return Ragged(x[order], np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)), \
        failed[order]


def worst_twin_sides(
    samples: HypothesisSamples, delta0: np.ndarray | float, seed: int = 0, orders: int = 1,
    order: str = "seed", star: bool = False,
) -> tuple[OrderedSide, OrderedSide]:
    """Twin sides for H_lo and H_up with each failed run's worst case at its own place.

    The sequence is every run that entered or failed, in the plan's run order, permuted by
    the same hash as :func:`ordered_sides` (over its size n_c = nhat + F). Bets are the
    plug-in bets of the successful runs only, tuned for n_c: a failed run gets the bet the
    next successful run would get (it reads only successful values before it). A failed run
    enters the H_lo side as x = 1 (the K- factor 1 - lambda (1 - m), the least any outcome
    or not entering can give) and the H_up side as x = 0. ``star``: target-recalculating
    bets from the same variances (each bet also reads the capital so far, worst cases
    included). Without failed runs this is :func:`ordered_sides`' twin side. Validity:
    ``inference.failures`` module doc.
    """
    if order not in ORDER_KINDS:
        raise ValueError(f"betting: order must be one of {', '.join(ORDER_KINDS)}, got {order!r}")
    hseed = None if order == "data" else seed
    h, _, d0 = _checked(samples, delta0)
    copy = np.zeros(h, np.int64)
    if orders > 1:
        samples, copy = _tile(samples, int(orders))
        d0 = np.tile(d0, int(orders))
    cand, failed = twin_candidates(samples)
    sizes = cand.sizes
    perm = _order_keys(sizes, samples.hyp_keys, copy, hseed, 2)
    x, failed = cand.values[perm], failed[perm]
    gid = cand.group_ids()
    # the successful subsequence with one extra slot per group (the bet after the last one)
    ok = ~failed
    n_ok = np.bincount(gid[ok], minlength=len(sizes))
    offs_ext = np.concatenate([[0], np.cumsum(n_ok + 1)]).astype(np.int64)
    x_ext = np.full(offs_ext[-1], 0.5)
    lay = flat_layout(offs_ext)
    slot = offs_ext[:-1][gid] + (segment_cumsum(ok.astype(float), cand.offsets, gid)
                                 - ok).astype(np.int64)  # successful runs before each
    x_ext[slot[ok]] = x[ok]
    _, prev = running_moments(x_ext, offs_ext, lay)
    with np.errstate(divide="ignore"):
        k = 2.0 * np.log(1.0 / d0) / sizes  # tuned for n_c
    sig2 = prev[slot]
    copies = max(int(orders), 1)
    x_lo, x_up = np.where(failed, 1.0, x), np.where(failed, 0.0, x)
    if star:
        return (OrderedSide(x_lo, None, cand.offsets, copies,
                            star_bets(x_lo, cand.offsets, d0, sig2=sig2)),
                OrderedSide(x_up, None, cand.offsets, copies,
                            star_bets(x_up, cand.offsets, d0, sig2=sig2)))
    lam = np.sqrt(k[gid] / sig2)
    return (OrderedSide(x_lo, lam, cand.offsets, copies),
            OrderedSide(x_up, lam, cand.offsets, copies))


def _check_grid(grid: int, ratio: float) -> None:
    if int(grid) < 1 or not float(ratio) > 1:
        raise ValueError(f"betting: grid must be >= 1 and grid_ratio > 1, got {grid}, {ratio}")


def _grid_side(x: np.ndarray, offsets: np.ndarray, delta0: np.ndarray, grid: int,
               ratio: float) -> OrderedSide:
    """J = ``grid`` copies of the groups' values, copy j betting lambda_min r^j throughout."""
    sizes = np.diff(offsets)
    with np.errstate(divide="ignore"):
        lam_min = np.sqrt(8.0 * np.log(1.0 / delta0) / sizes)  # inf for an empty group: unused
    gid = np.repeat(np.arange(len(sizes)), sizes)
    lam = np.concatenate([lam_min[gid] * ratio ** j for j in range(grid)])
    offs = np.concatenate([[0], np.cumsum(np.tile(sizes, grid))]).astype(np.int64)
    return OrderedSide(np.tile(x, grid), lam, offs, grid)


def mixture_sides(
    samples: HypothesisSamples, delta0: np.ndarray | float, grid: int = MIX_GRID,
    ratio: float = MIX_RATIO,
) -> tuple[OrderedSide, OrderedSide, OrderedSide]:
    """(Y_lo, Y_up, twin) rescaled to [0, 1] with the constant bets of the grid mixture.

    Order-free (module doc, "Order-free mixture"): the values stay in their listing order,
    which the terminal capital of a constant bet does not see. ``grid`` J copies per side.
    """
    _check_grid(grid, ratio)
    h, width, d0 = _checked(samples, delta0)
    n = samples.n.astype(np.int64)
    nf = samples.n_follow
    offs = np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
    gid, t = flat_layout(offs)
    is_f = t <= nf[gid]
    fg = np.repeat(np.arange(h), nf)
    xf = np.zeros(len(gid))
    xf[is_f] = (samples.follow_f.values - samples.y_lo[fg]) / width[fg]
    x_lo, x_up = np.where(is_f, xf, 0.0), np.where(is_f, xf, 1.0)
    tw = samples.twin_f
    tg = tw.group_ids()
    x_tw = (tw.values - samples.y_lo[tg]) / width[tg]
    j, r = int(grid), float(ratio)
    return (_grid_side(x_lo, offs, d0, j, r), _grid_side(x_up, offs, d0, j, r),
            _grid_side(x_tw, tw.offsets, d0, j, r))


def _ragged_subset(r: Ragged, keep: np.ndarray) -> Ragged:
    """The groups where ``keep`` is True, vectorised (no loop over groups)."""
    sizes = r.sizes[keep]
    return Ragged(r.values[np.repeat(keep, r.sizes)],
                  np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64))


def _subset(samples: HypothesisSamples, keep: np.ndarray) -> HypothesisSamples:
    return samples.per_hypothesis(lambda a: a[keep], lambda r: _ragged_subset(r, keep))


def default_tune_alpha(h: int, alpha: float = 0.05) -> float:
    """alpha / (2H): the smallest Holm level of a family of H parameter sets (2H one-sided
    hypotheses) at the family's level alpha (``testing.alpha``)."""
    return float(alpha) / (2 * max(int(h), 1))


ORDERS = 1  # default K for plugin bets (K > 1 averages K orders' terminal capitals; docs)
_CHUNK_ELEMENTS = 1 << 23  # copies (n + nhat) summed per chunk of hypotheses: bounds memory


@dataclass(frozen=True)
class Bets:
    """How the capital is built: validated options of :func:`betting_test`."""

    kind: str = DEFAULT_BETS
    orders: int = 1  # plugin: K orders averaged
    running_max: bool = False  # plugin with one order: max_t K_t (Ville) instead of K_n
    grid: int = MIX_GRID  # mixture: J constant bets
    ratio: float = MIX_RATIO
    order: str = "data"  # plugin: "data" (seedless, module doc "Order") or "seed"

    @property
    def copies(self) -> int:
        return self.grid if self.kind == "mixture" else self.orders

    def sides(self, samples: HypothesisSamples, delta0: float | np.ndarray, seed: int,
              c: float) -> tuple[OrderedSide, OrderedSide, OrderedSide]:
        if self.kind == "mixture":
            return mixture_sides(samples, delta0, self.grid, self.ratio)
        return ordered_sides(samples, delta0, seed=seed, c=c, orders=self.orders,
                             order=self.order, star=self.kind == "star")

    def twin_sides(self, samples: HypothesisSamples, delta0: float | np.ndarray, seed: int,
                   tw: OrderedSide) -> tuple[OrderedSide, OrderedSide]:
        """The twin sides H_lo and H_up are tested on: ``tw`` itself, or with failed runs
        at their places (:func:`worst_twin_sides`; plug-in and STaR bets)."""
        if self.kind not in PLACING_BETS or not samples.has_failed_places:
            return tw, tw
        return worst_twin_sides(samples, delta0, seed=seed, orders=self.orders,
                                order=self.order, star=self.kind == "star")


def make_bets(bets: str = DEFAULT_BETS, orders: int | None = None,
              running_max: bool | None = None, grid: int = MIX_GRID,
              grid_ratio: float = MIX_RATIO, default_orders: int = ORDERS,
              order: str | None = None) -> Bets:
    """Check the betting options together; one clear error for a combination that cannot be."""
    if bets not in BETS:
        raise ValueError(f"betting: bets must be one of {', '.join(BETS)}, got {bets!r}")
    if bets == "mixture":
        if orders is not None or running_max or order is not None:
            raise ValueError("betting: orders, order and running_max apply to bets: plugin "
                             "(the mixture is order-free and uses the terminal capital)")
        _check_grid(grid, grid_ratio)
        return Bets("mixture", grid=int(grid), ratio=float(grid_ratio))
    if bets == "star":
        if orders not in (None, 1):
            raise ValueError("betting: bets: star takes one order (orders 1)")
        order = "data" if order is None else order
        if order not in ORDER_KINDS:
            raise ValueError(f"betting: order must be one of {', '.join(ORDER_KINDS)}, "
                             f"got {order!r}")
        return Bets("star", orders=1, running_max=True if running_max is None
                    else bool(running_max), order=order)
    k = default_orders if orders is None else int(orders)
    if k < 1:
        raise ValueError(f"betting: orders must be >= 1, got {k}")
    if running_max and k > 1:
        raise ValueError("betting: running_max needs orders = 1 (averaging over orders uses "
                         "the terminal capital)")
    order = "data" if order is None else order
    if order not in ORDER_KINDS:
        raise ValueError(f"betting: order must be one of {', '.join(ORDER_KINDS)}, got {order!r}")
    return Bets("plugin", orders=k, running_max=(k == 1) if running_max is None
                else bool(running_max), order=order)


def check_options(opts: dict) -> None:
    """Config options of :func:`betting_test`: each value's type and range, then the bet
    options together (:func:`make_bets`)."""
    from twinfalsify.inference import options as o

    o.number(opts, "tune_alpha", lo=0, hi=1, lo_open=True, hi_open=True, allow_none=True)
    o.choice(opts, "bets", BETS)
    o.choice(opts, "order", ORDER_KINDS)
    o.integer(opts, "grid", lo=1)
    o.number(opts, "grid_ratio", lo=1, lo_open=True)
    o.integer(opts, "orders", lo=1, allow_none=True)
    o.boolean(opts, "running_max", allow_none=True)
    o.number(opts, "c", lo=0, hi=1, lo_open=True, hi_open=True, note="bet truncation")
    o.number(opts, "tol", lo=0, lo_open=True)
    o.integer(opts, "max_iter", lo=1)
    make_bets(**{k: opts[k] for k in ("bets", "orders", "running_max", "grid", "grid_ratio",
                                      "order") if k in opts})


def betting_test(
    samples: HypothesisSamples,
    *,
    tune_alpha: float | None = None,
    bets: str = DEFAULT_BETS,
    order: str | None = None,
    grid: int = MIX_GRID,
    grid_ratio: float = MIX_RATIO,
    seed: int = 0,
    orders: int | None = None,
    running_max: bool | None = None,
    c: float = C_TRUNC,
    tol: float = 1e-3,
    max_iter: int = 100,
    alpha: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Betting p-values (p_lo, p_up), shape (H,) each (see module doc); p = 1 if n or nhat is 0.

    ``tune_alpha``: the level the bets are tuned for (default alpha / (2H), ``alpha`` the
    family's level ``testing.alpha``); ``bets``: "star" (default: target-recalculating bets,
    module doc "STaR bets"; one order, running maximum by default), "plugin" (WSR's
    predictable plug-in bets; ``orders`` K > 1 averages the terminal capitals of K orders;
    K = 1 (default): one order, running maximum by default; for both, ``order`` "data"
    (default) puts each sample in its data order, keyed by content and the study seed;
    "seed": a ``seed``-ed random order) or "mixture" (order-free grid mixture of ``grid``
    constant bets spaced by ``grid_ratio``; ``seed`` is not used); ``tol``: accuracy of log K* (p's
    relative accuracy), p is never understated. Hypotheses are processed in chunks (memory);
    a hypothesis' orders depend on its key only, so chunking does not change any p-value.
    """
    how = make_bets(bets, orders, running_max, grid, grid_ratio, order=order)
    h = len(samples)
    p_lo, p_up = np.ones(h), np.ones(h)
    ok = (samples.n > 0) & (samples.nhat > 0)
    if not ok.any():
        return p_lo, p_up
    alpha0 = default_tune_alpha(h, alpha) if tune_alpha is None else float(tune_alpha)
    if not 0 < alpha0 < 1:
        raise ValueError(f"betting: tune_alpha must be in (0, 1), got {alpha0}")
    sub = samples if ok.all() else _subset(samples, ok)
    nc = sub.nhat if sub.failed_run is None else sub.nhat + sub.failed_run.sizes
    size = how.copies * (sub.n + nc)
    cum = np.cumsum(size)
    cuts = np.unique(np.searchsorted(cum, np.arange(_CHUNK_ELEMENTS, cum[-1], _CHUNK_ELEMENTS)))
    cuts = cuts[(cuts > 0) & (cuts < len(sub))]
    k_lo, k_up = np.zeros(len(sub)), np.zeros(len(sub))
    rmax = how.running_max
    for idx in np.split(np.arange(len(sub)), cuts):
        part = sub if len(idx) == len(sub) else sub.take(idx)
        lo, up, tw = how.sides(part, alpha0 / 2, seed, c)
        tw_lo, tw_up = how.twin_sides(part, alpha0 / 2, seed, tw)
        r = part.width
        q_lo = (part.q_lo_hat - part.y_lo) / r
        q_up = (part.q_up_hat - part.y_lo) / r
        q_tw = (part.q_twin_hat - part.y_lo) / r
        with ThreadPoolExecutor(2) as pool:  # the two crossings are independent
            f_lo = pool.submit(crossing, lo, tw_lo, 0.5 * (q_lo + q_tw), rmax, c, tol, max_iter)
            f_up = pool.submit(crossing, tw_up, up, 0.5 * (q_up + q_tw), rmax, c, tol, max_iter)
            k_lo[idx], k_up[idx] = f_lo.result(), f_up.result()
    p_lo[ok] = np.minimum(1.0, 2.0 * np.exp(-k_lo))
    p_up[ok] = np.minimum(1.0, 2.0 * np.exp(-k_up))
    return p_lo, p_up


def betting_bounds(
    samples: HypothesisSamples, alpha: float | np.ndarray, *, tune_alpha: float | None = None,
    bets: str = DEFAULT_BETS, grid: int = MIX_GRID, grid_ratio: float = MIX_RATIO, seed: int = 0,
    orders: int | None = None, running_max: bool | None = None, c: float = C_TRUNC,
    order: str | None = None,
) -> dict[str, np.ndarray]:
    """One-sided (1 - alpha/2) bounds in outcome units, for the union rule at level alpha.

    ``alpha``: a scalar or one level per hypothesis.
    Keys: lower_lo, upper_up (observational), lower_twin, upper_twin. Same bets as
    :func:`betting_test` with the same options (``bets: plugin``: one order with the running
    maximum by default, WSR's interval), so the rule on these bounds rejects at alpha
    exactly when that p-value is <= alpha (up to the bisection's resolution).
    Requires n > 0 and nhat > 0 for every hypothesis.
    """
    if np.any(samples.n == 0) or np.any(samples.nhat == 0):
        raise ValueError("betting_bounds: every hypothesis needs n > 0 and nhat > 0")
    h = len(samples)
    how = make_bets(bets, orders, running_max, grid, grid_ratio, default_orders=1,
                    order=order)
    rmax = how.running_max
    alpha0 = default_tune_alpha(h) if tune_alpha is None else float(tune_alpha)
    lo, up, tw = how.sides(samples, alpha0 / 2, seed, c)
    alpha = np.broadcast_to(np.asarray(alpha, float), (h,))
    if np.any(~((alpha > 0) & (alpha <= 1))):
        raise ValueError("betting_bounds: alpha must be in (0, 1]")
    lev = np.log(2.0 / alpha)
    r, y0 = samples.width, samples.y_lo
    return {
        "lower_lo": y0 + r * capital_bound(lo, lev, +1, rmax, c),
        "upper_up": y0 + r * capital_bound(up, lev, -1, rmax, c),
        "lower_twin": y0 + r * capital_bound(tw, lev, +1, rmax, c),
        "upper_twin": y0 + r * capital_bound(tw, lev, -1, rmax, c),
    }
