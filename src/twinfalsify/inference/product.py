"""The product combination of the observational and twin capitals (adaptive mode, opt-in).

The union rule (``betting``, ``sequential``) rejects H_lo: Q_twin >= Q_lo at level a when
some m has G_lo(m) >= 2/a and K-_twin(m) >= 2/a: each side must clear the whole 2/a on
its part of the gap. The product rule multiplies the two capitals:

    reject at level a  iff  inf_{m in [0, 1]} G_lo(m) K-_twin(m) >= 1/a,
    p = min(1, 1 / inf_m G_lo(m) K-_twin(m)).

*What its validity needs: the two samples independent.* Suppose the twin sample is
independent of the observational one. Under H_lo (Q_twin >= Q_lo), at m = Q_lo both factors
are nulls: G_lo(Q_lo) is the terminal capital of a test martingale for "mean <= Q_lo" on the
observational sample, an e-value (E <= 1), and K-_twin,t(Q_lo) is a test supermartingale for
"mean >= Q_lo" on the twin runs. Conditionally on the observational sample (which, by
independence, leaves the twin's law unchanged) Ville's inequality gives P(exists t:
K_t(Q_lo) >= 1/(a G)) <= min(1, a G), so P(exists t: G(Q_lo) K_t(Q_lo) >= 1/a) <=
a E[G(Q_lo)] <= a, and the inf over m is at most the value at Q_lo: the p-value is valid at
any stopping time ("e-values multiply for independent data": Vovk & Wang 2021, Ann. Stat.
49(3):1736-1754; Ramdas, Grünwald, Vovk & Shafer 2023, Stat. Sci. 38(4):576-601).

*As run, that premise is false, and the proof does not hold.* The workflow initialises the
twin's runs with the X_0 of D patients, drawn without replacement: the same patients whose
outcomes form the observational sample. Given the observational sample the twin's runs are no
longer i.i.d. draws with mean Q_twin (their X_0 are D's, a finite population correlated with
the observational outcomes), so the conditional Ville step fails. Conditioning on the X_0 of
D does not repair it either: given them, the observational values are independent but not
identically distributed (each has its own conditional mean given its X_0), so G_lo(Q_lo) is
no longer a test martingale, and the twin's draws without replacement have a drifting
conditional mean. The argument holds exactly when the twin's X_0 come from patients disjoint
from the observational sample (e.g. a part of D set aside, at random, before any test; its
patients then leave the observational sample, which costs that part of n). The union rule
needs no independence (a union bound over two marginally valid bounds) and stays valid.

Measured, null boundary (``benchmarks/bench_product_null.py``; X_0 shared vs disjoint, a twin
whose response to X_0 mirrors the world's, the dependence that favours rejecting H_lo): see
docs/explanation/sequential.md. Sharing X_0 raises the rejection rate several-fold; no rate
above its level was seen, but none is excluded by a proof: ``combine: product`` is offered
as an unproven, opt-in rule, not as a valid test.

*Why it is tighter when it holds.* No union bound: each side sees the whole gap, and the
required gap behaves like a two-sample test's, sqrt(2 log(1/a) (s_obs^2/n + s_twin^2/t)),
instead of the sum of two one-sample widths at 2/a (docs/explanation/sequential.md, measured).

*Bets.* The observational capital must not decay where its null holds, or the inf would
sit there: its bets are m-dependent, aGRAPA (Waudby-Smith & Ramdas 2024, JRSS-B
86(1):1-27, Sec. 5.1) on a grid of M cells, lambda_i(m) = clip((mu_{i-1} - m) /
(sigma2_{i-1} + (mu_{i-1} - m)^2), 0, c/m) for K+ (mu, sigma2 the running mean and
variance with mu_0 = 1/2, sigma2_0 = 1/4, predictable), terminal capital (an e-value;
one seeded order, as the union rule's observational side in adaptive mode). The twin side
is the union rule's confidence sequence unchanged (m-independent CS bets, truncated at
c/(1-m)), so its log-capital is non-decreasing in m.

*An exact inf on a grid.* Bet cells [m_k, m_{k+1}], m_k = k/M, each using the bets of
m_{k+1} throughout. With fixed bets log G_lo(m) is concave and decreasing in m, so on its
cell it lies above the chord through its two end values; log K-_twin(m) is non-decreasing
in m. Each bet cell is split into S sub-steps u_0 < ... < u_S, and on [u_i, u_{i+1}]

    log G_lo(m) + log K-_twin(m) >= chord(u_{i+1}) + log K-_twin(u_i),

so the min over all sub-steps is a lower bound of the inf over [0, 1]: the reported p is
never smaller than the exact one (checked against a brute force on a fine grid). The grid
is fixed before any data (a data-dependent partition would make the bets of an m depend
on the data). H_up mirrors everything through x -> 1 - x (the observational y_up sample
with K-, the twin with K+).
"""

from __future__ import annotations

import numpy as np

from twinfalsify.inference.betting import C_TRUNC, OrderedSide, _chunks, running_moments

GRID_CELLS = 64  # M bet cells: two observational capitals per cell
SUB_STEPS = 4  # S: twin capital at M S + 1 points (the twin sample is the small one)
_CHUNK = 1 << 21  # elements of a (values x grid) working array


def grid(cells: int = GRID_CELLS, sub: int = 1) -> np.ndarray:
    """m = i / (M S), i = 0..M S (bet cells of :func:`obs_cell_capital` when S = 1)."""
    if cells < 1 or sub < 1:
        raise ValueError(f"product: grid cells and sub-steps must be >= 1, got {cells}, {sub}")
    return np.linspace(0.0, 1.0, cells * sub + 1)


def _row_chunks(offsets: np.ndarray, width: int) -> list[tuple[int, int]]:
    """Consecutive group ranges whose (values x width) arrays hold about _CHUNK elements."""
    return _chunks(np.diff(offsets), max(_CHUNK // max(width, 1), 1))


def obs_cell_capital(x: np.ndarray, offsets: np.ndarray, m_grid: np.ndarray,
                     c: float = C_TRUNC) -> tuple[np.ndarray, np.ndarray]:
    """(G, M) each: log G^(k)(m_k) and log G^(k)(m_{k+1}), the terminal K+ capital of each
    group's sample (in its order) with the aGRAPA bets of m_{k+1} (truncated at c/m_{k+1})
    at the two ends of bet cell k. Empty groups give 0 (capital 1)."""
    m_grid = np.asarray(m_grid, float)
    left, right = m_grid[:-1], m_grid[1:]
    n_groups = len(offsets) - 1
    g_left, g_right = np.zeros((n_groups, len(right))), np.zeros((n_groups, len(right)))
    mu_prev, s2_prev = running_moments(x, offsets)
    cap = c / right
    for g0, g1 in _row_chunks(offsets, 2 * len(right)):
        sl = slice(offsets[g0], offsets[g1])
        o = offsets[g0: g1 + 1] - offsets[g0]
        d = mu_prev[sl, None] - right[None, :]
        lam = np.minimum(np.clip(d / (s2_prev[sl, None] + d * d), 0.0, None), cap[None, :])
        for out, at in ((g_left, left), (g_right, right)):
            term = np.log1p(lam * (x[sl, None] - at[None, :]))
            # segment sums: cumulative sums read at the group ends
            cs = np.vstack([np.zeros((1, len(right))), np.cumsum(term, axis=0)])
            out[g0:g1] = cs[o[1:]] - cs[o[:-1]]
    return g_left, g_right


def twin_grid(side: OrderedSide, m_grid: np.ndarray, c: float = C_TRUNC
              ) -> tuple[np.ndarray, np.ndarray]:
    """(G, M+1) each: log max_{t<=n} K-_t(m_k) and log K-_n(m_k) of each group at every
    grid point (CS bets of ``side``, truncated at c/(1-m)); empty groups give 0."""
    m = np.asarray(m_grid, float)
    n_groups = len(side.offsets) - 1
    run_max, end = np.zeros((n_groups, len(m))), np.zeros((n_groups, len(m)))
    with np.errstate(divide="ignore"):
        cap = c / (1.0 - m)
    for g0, g1 in _row_chunks(side.offsets, len(m)):
        sl = slice(side.offsets[g0], side.offsets[g1])
        lam = np.minimum(side.lam[sl, None], cap[None, :])
        term = np.log1p(-lam * (side.x[sl, None] - m[None, :]))
        cs = np.cumsum(term, axis=0)
        o = side.offsets[g0: g1 + 1] - side.offsets[g0]
        base = np.vstack([np.zeros((1, len(m))), cs])[o[:-1]]
        sizes = np.diff(o)
        gid = np.repeat(np.arange(g1 - g0), sizes)
        local = cs - base[gid]  # log K_t per group
        has = sizes > 0
        end[g0:g1][has] = local[o[1:][has] - 1]
        # running max within groups, K_0 = 1 included (so values below 0 never matter):
        # lift each group above every earlier one, accumulate, drop the lift
        pos = np.maximum(local, 0.0)
        lift = np.arange(g1 - g0, dtype=float)[gid, None] * (pos.max(initial=0.0) + 1.0)
        acc = np.maximum.accumulate(pos + lift, axis=0) - lift
        run_max[g0:g1][has] = acc[o[1:][has] - 1]
    return run_max, end


def mirrored(side: OrderedSide) -> OrderedSide:
    """The side seen through x -> 1 - x (same bets): K+(m) of x is K-(1 - m) of 1 - x."""
    return OrderedSide(1.0 - side.x, side.lam, side.offsets, side.copies)


def product_stat(g_left: np.ndarray, g_right: np.ndarray, k_max: np.ndarray) -> np.ndarray:
    """Lower bound of log inf_m G(m) K-(m) per group (module doc): bet cells of
    ``g_left``/``g_right`` (G, M), twin running-max capital ``k_max`` at the M S + 1 points
    of ``grid(M, S)``."""
    n_groups, cells = g_left.shape
    sub = (k_max.shape[1] - 1) // cells
    frac = np.arange(1, sub + 1) / sub  # right ends of the sub-steps within a cell
    chord = g_left[:, :, None] + (g_right - g_left)[:, :, None] * frac[None, None, :]
    k_left = k_max[:, :-1].reshape(n_groups, cells, sub)
    return (chord + k_left).min(axis=(1, 2))
