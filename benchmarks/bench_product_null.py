"""The product rule at the null boundary when the twin shares the observational sample's X_0.

    PYTHONPATH=src nice python benchmarks/bench_product_null.py [--reps 20000] [--n 100]

``combine: product`` (``inference.product``) multiplies the observational capital G_lo(m) and
the twin's K-_twin(m); its proof needs the two samples independent. In the workflow they are
not: the twin's runs start from the X_0 of the same D patients whose outcomes form the
observational sample. This harness measures the rule's null rejection rate with and without
that sharing, R replicates per scenario, vectorised over replicates (one replicate = one
hypothesis of the library's functions: ``product.obs_cell_capital`` on the observational
sample, ``sequential.cs_bets`` + ``product.twin_grid`` on the twin sample, ``product_stat``:
the construction the adaptive mode runs, at its full budget).

World (boundary of H_lo: Q_twin = Q_lo = 1/2 exactly, by symmetry): X_0 ~ N(0, 1) per
patient; the observational value of patient i is x_i = clip(1/2 + 0.4 tanh(1.5 X_0i) +
0.05 e_i, 0, 1); a twin run from X_0 gives z = clip(1/2 + s 0.4 tanh(1.5 X_0) + 0.05 e', 0, 1)
with s = -1 (a twin whose response to X_0 is the mirror image of the world's: the dependence
that favours rejecting H_lo) or s = +1. Scenarios:

- ``shared``: the twin's m = n runs start from the X_0 of the same n patients, drawn without
  replacement (the workflow's construction, at its most overlapping);
- ``disjoint``: the twin's X_0 come from n other patients (what the proof assumes).

Printed: rejections of H_lo (p <= a) at a = 0.05, 0.01, 0.001, with a Clopper-Pearson 95 %
interval, bets tuned at ``--tune`` (default 0.001, delta0 = tune / 2).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from twinfalsify.inference.betting import C_TRUNC, OrderedSide
from twinfalsify.inference.product import (
    GRID_CELLS,
    SUB_STEPS,
    grid,
    obs_cell_capital,
    product_stat,
    twin_grid,
)
from twinfalsify.inference.sequential import cs_bets

LEVELS = (0.05, 0.01, 0.001)


def world(rng: np.random.Generator, x0: np.ndarray, sign: float) -> np.ndarray:
    return np.clip(0.5 + sign * 0.4 * np.tanh(1.5 * x0) + 0.05 * rng.standard_normal(x0.shape),
                   0.0, 1.0)


def log_stat(x: np.ndarray, z: np.ndarray, delta0: float) -> np.ndarray:
    """log inf_m G_lo(m) K-_twin(m) (lower bound, ``product_stat``) per row."""
    r, n = x.shape
    m = z.shape[1]
    offs_x = np.arange(0, r * n + 1, n, dtype=np.int64)
    offs_z = np.arange(0, r * m + 1, m, dtype=np.int64)
    g_left, g_right = obs_cell_capital(x.ravel(), offs_x, grid(GRID_CELLS), C_TRUNC)
    zf = z.ravel()
    side = OrderedSide(zf, cs_bets(zf, offs_z, np.full(r, delta0), C_TRUNC), offs_z)
    k_max, _ = twin_grid(side, grid(GRID_CELLS, SUB_STEPS), C_TRUNC)
    return product_stat(g_left, g_right, k_max)


def cp(k: int, n: int) -> tuple[float, float]:
    lo = 0.0 if k == 0 else float(stats.beta.ppf(0.025, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(0.975, k + 1, n - k))
    return lo, hi


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=20000)
    ap.add_argument("--n", type=int, default=100, help="observational sample = twin runs")
    ap.add_argument("--tune", type=float, default=0.001)
    ap.add_argument("--chunk", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--responses", nargs="+", default=["mirror", "same"],
                    choices=["mirror", "same"])
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    n = args.n
    t0 = time.monotonic()
    print(f"n = m = {n}, R = {args.reps} replicates per scenario, bets tuned at "
          f"{args.tune:g}; rejections of H_lo at the boundary Q_twin = Q_lo\n")
    print("| twin response | X_0 | " + " | ".join(f"a = {a:g}: rate (95 % CI)" for a in LEVELS)
          + " |")
    print("|---|---|" + "---|" * len(LEVELS))
    for sign in [{"mirror": -1.0, "same": 1.0}[r] for r in args.responses]:
        for scen in ("shared", "disjoint"):
            hits = np.zeros(len(LEVELS), np.int64)
            for k in range(0, args.reps, args.chunk):
                r = min(args.chunk, args.reps - k)
                x0 = rng.standard_normal((r, n))
                x = world(rng, x0, 1.0)
                if scen == "shared":  # the same patients' X_0, in a random draw order
                    perm = np.argsort(rng.random((r, n)), axis=1)
                    tx0 = np.take_along_axis(x0, perm, axis=1)
                else:
                    tx0 = rng.standard_normal((r, n))
                z = world(rng, tx0, sign)
                s = log_stat(x, z, args.tune / 2)
                p = np.minimum(1.0, np.exp(-s))
                hits += (p[:, None] <= np.array(LEVELS)[None, :]).sum(axis=0)
            cells = []
            for h in hits:
                lo, hi = cp(int(h), args.reps)
                cells.append(f"{h / args.reps:.4f} ({lo:.4f}-{hi:.4f})")
            print(f"| {'mirror' if sign < 0 else 'same'} | {scen} | " + " | ".join(cells) + " |",
                  flush=True)
    print(f"\n{time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main()
