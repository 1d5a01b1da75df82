"""Width of the betting test's lower bound against deterministic STaR-Bets, WSR and Hoeffding.

    PYTHONPATH=src python benchmarks/bench_star_bets.py [--reps 2000] [--ns 50 200 1000]
        [--alphas 0.05 0.001 2.248e-05] [--distributions ...]

Per cell (distribution, n, alpha): ``reps`` samples; for each method the one-sided lower
bound at level 1 - alpha/2 (the union rule's per-side level; bets tuned there), the mean
distance from the true mean to it, its ratio to deterministic STaR-Bets' on the same
samples, and coverage (misses: bound above the true mean) with a 95 % Clopper-Pearson
interval. alpha = 2.248e-05 is 0.05 / 2224, about the smallest Holm level of the default
study.

Methods. Every method sees each sample in the order the library's default uses (the data
order), so the ratios measure the bets, not the orders.

- ``star-det``: deterministic STaR-Bets (Voracek & Orabona, NeurIPS 2025), an independent
  implementation of the method of the paper's reference code, written here: for every m of
  a grid, log-capital l(m) with bets
  b_t(m) = sqrt(2 max(log(1/delta) - l_{t-1}(m), 0) / ((n - t') S_t(m))),
  S_t(m) = min(V_{t-1}(m) / t' + (m + 1e-4) n / t'^2, 1e-3 + m (1 - m)),
  t' = t - 1 + 1e-4, V the sum of squared deviations from m of the past values, bets clipped
  at 1 / (m + 1e-3); deterministic: m is rejected when l_n(m) >= log(1/delta) (no
  randomised last bet). The bound is the grid point before the first m not rejected; grid:
  201 points on [0, 1], then 100 points inside the cell before the first point not rejected
  (resolution 5e-5; a point not rejected in an earlier cell between coarse points would be
  missed: the capital need not be monotone in m).
- ``plugin``: the library's ``bets: plugin``, WSR plug-in bets, c = 0.9, running maximum.
- ``wsr-c0.5``: the same bets truncated at c = 1/2 (WSR's suggestion).
- ``star``: the library's default, ``bets: star`` (``inference.betting`` module doc, "STaR
  bets").
- ``hoeffding``: mean - sqrt(log(2/alpha) / (2 n)).
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
from scipy import stats

from twinfalsify.inference.betting import (
    C_TRUNC,
    capital_bound,
    ordered_sides,
)
from twinfalsify.inference.samples import HypothesisSamples, Ragged

DISTRIBUTIONS = {  # name: (draw(rng, shape), mean)
    "Bernoulli(0.1)": (lambda r, s: (r.random(s) < 0.1).astype(float), 0.1),
    "Bernoulli(0.5)": (lambda r, s: (r.random(s) < 0.5).astype(float), 0.5),
    "Beta(2,5)": (lambda r, s: r.beta(2, 5, s), 2 / 7),
}
METHODS = ("star-det", "plugin", "wsr-c0.5", "star", "hoeffding")


def star_deterministic(x: np.ndarray, delta: float, coarse: int = 200, fine: int = 100
                       ) -> np.ndarray:
    """Deterministic STaR-Bets lower bound at level 1 - delta for every row of x (R, n)."""
    r, n = x.shape
    level = math.log(1 / delta)

    def log_capital(ms: np.ndarray) -> np.ndarray:  # ms (R, G)
        lg, v = np.zeros_like(ms), np.zeros_like(ms)
        var_m = 1e-3 + ms * (1 - ms)
        cap = 1 / (ms + 1e-3)
        for t in range(n):
            tt = t + 1e-4
            s = np.minimum(v / tt + (ms + 1e-4) * n / tt ** 2, var_m)
            b = np.minimum(np.sqrt(2 * np.maximum(level - lg, 0) / ((n - tt) * s)), cap)
            xt = x[:, t: t + 1]
            lg += np.log1p(b * (xt - ms))
            v += (xt - ms) ** 2
        return lg

    grid = np.linspace(0, 1, coarse + 1)
    keep = log_capital(np.tile(grid, (r, 1))) < level
    k = np.where(keep.any(axis=1), np.argmax(keep, axis=1), coarse + 1)
    lo = grid[np.maximum(k - 1, 0)]
    step = 1 / coarse
    pts = np.minimum(lo[:, None] + step * np.arange(1, fine + 1)[None, :] / fine, 1.0)
    keep_f = log_capital(pts) < level
    kf = np.where(keep_f.any(axis=1), np.argmax(keep_f, axis=1), fine)
    return np.where(k == 0, 0.0, lo + step * kf / fine)


def _samples(x: np.ndarray) -> HypothesisSamples:
    r, n = x.shape
    g = Ragged(x.ravel().copy(), np.arange(0, r * n + 1, n, dtype=np.int64))
    return HypothesisSamples(np.zeros(r), np.ones(r), np.full(r, n), g, g)


def lower_bounds(x: np.ndarray, alpha: float) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(x in the data order, {method: lower bound}) for every row of x."""
    r, n = x.shape
    delta = alpha / 2
    tw = ordered_sides(_samples(x), delta, order="data")[2]
    st = ordered_sides(_samples(x), delta, order="data", star=True)[2]  # the same order
    xo = tw.x.reshape(x.shape)
    lev = np.full(r, math.log(1 / delta))
    out = {
        "star-det": star_deterministic(xo, delta),
        "plugin": capital_bound(tw, lev, +1, True, C_TRUNC),
        "wsr-c0.5": capital_bound(tw, lev, +1, True, 0.5),
        "star": capital_bound(st, lev, +1, True, C_TRUNC),
        "hoeffding": x.mean(axis=1) - math.sqrt(math.log(1 / delta) / (2 * n)),
    }
    return xo, out


def cp(k: int, n: int) -> tuple[float, float]:
    lo = 0.0 if k == 0 else float(stats.beta.ppf(0.025, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(0.975, k + 1, n - k))
    return lo, hi


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=2000)
    ap.add_argument("--ns", type=int, nargs="+", default=[50, 200, 1000])
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.05, 1e-3, 0.05 / 2224])
    ap.add_argument("--distributions", nargs="+", default=list(DISTRIBUTIONS),
                    choices=list(DISTRIBUTIONS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    rows, t0 = [], time.monotonic()
    for dist in args.distributions:
        draw, mu = DISTRIBUTIONS[dist]
        for n in args.ns:
            for alpha in args.alphas:
                x = draw(rng, (args.reps, n))
                _, lbs = lower_bounds(x, alpha)
                dist_ = {k: float(np.mean(mu - v)) for k, v in lbs.items()}
                miss = {k: int(np.sum(v > mu)) for k, v in lbs.items()}
                row = {"dist": dist, "n": n, "alpha": alpha, "reps": args.reps,
                       "dist_mean": dist_, "miss": miss}
                rows.append(row)
                print("#row " + json.dumps(row), flush=True)
                print(f"# {dist} n={n} alpha={alpha:.4g} ({time.monotonic() - t0:.0f} s)",
                      flush=True)
    report(rows)
    print(f"total {time.monotonic() - t0:.0f} s")


def report(rows: list[dict]) -> None:
    print("\nmean distance from the true mean to the lower bound (deterministic STaR-Bets), and "
          "every method's / STaR's\n")
    ms = [m for m in METHODS if m != "star-det"]
    print("| distribution | n | alpha | replicates | STaR-Bets (det.) | "
          + " | ".join(ms) + " |")
    print("|---|---|---|---|---|" + "---|" * len(ms))
    for r in rows:
        d = r["dist_mean"]
        print(f"| {r['dist']} | {r['n']} | {r['alpha']:.3g} | {r['reps']} | {d['star-det']:.4f} | "
              + " | ".join(f"{d[m] / d['star-det']:.3f}" for m in ms) + " |")
    print("\ncoverage: misses of the lower bound (nominal alpha/2) and 95 % Clopper-Pearson "
          "interval of the miss rate\n")
    print("| distribution | n | alpha | " + " | ".join(METHODS) + " |")
    print("|---|---|---|" + "---|" * len(METHODS))
    for r in rows:
        cells = []
        for m in METHODS:
            k = r["miss"][m]
            lo, hi = cp(k, r["reps"])
            cells.append(f"{k} [{lo:.4f}, {hi:.4f}]")
        print(f"| {r['dist']} | {r['n']} | {r['alpha']:.3g} | " + " | ".join(cells) + " |")
    for m in ms:
        q = [r["dist_mean"][m] / r["dist_mean"]["star-det"] for r in rows]
        print(f"{m}: ratio to STaR-Bets {min(q):.3f} - {max(q):.3f}")
    q = [r["dist_mean"]["star"] / r["dist_mean"]["hoeffding"] for r in rows]
    print(f"star / hoeffding (mean distance): max {max(q):.3f}")


if __name__ == "__main__":
    main()
