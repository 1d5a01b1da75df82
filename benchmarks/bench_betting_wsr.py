"""Betting intervals, every variant, against hedged WSR and Hoeffding: widths and coverage.

    PYTHONPATH=src python benchmarks/bench_betting_wsr.py [--reps 1000] [--coverage-reps 10000]
        [--ns 20 50 200 1000] [--distributions ...] [--variants ...]
    PYTHONPATH=src python benchmarks/bench_betting_wsr.py --merge out1.txt out2.txt ...
        (the tables of runs split by --ns / --distributions, e.g. parallel jobs)

One run prints, for Bernoulli(1/2), Bernoulli(0.1), Beta(2,2) and Uniform at n = 20, 50, 200,
1000 and alpha = 0.05, 1e-4 (two-sided (1 - alpha) intervals for the mean, alpha/2 per end,
bets tuned at alpha/2):

1. mean width of every variant / mean width of the hedged WSR reference (same samples);
2. the same / mean width of Hoeffding's interval, and the share of replicates in which the
   default (``plugin``) is wider than Hoeffding;
3. coverage: misses (true mean outside) of every variant over the same replicates, and of the
   default over ``coverage-reps`` further replicates, with a Clopper-Pearson 95 % upper bound.

Reference (``wsr``). Hedged capital of Waudby-Smith & Ramdas (2024, JRSS-B 86(1):1-27, Sec. 4,
Thm 3; theta = 1/2) with the fixed-n predictable plug-in bets of their Sec. 5.1 (prior mean
1/2, prior variance 1/4, one fake observation), truncated only at c/m and c/(1-m), c = the
project's 0.9, running intersection over t. Written here as a plain vectorised bisection over
the replicates; it shares no code with the library. It is fed each sample in the order the
project's ``plugin`` uses (any fixed order is as valid; the same one makes the ratio measure
the algorithms, not two orders' luck). ``hoeffding``: mean +- sqrt(log(2/alpha) / (2n)),
clipped to [0, 1].

Variants (the library's ``betting`` options, and order-free constructions built from the
library's capital ``log_capital``/``capital_bound``):

- ``plugin`` (default): WSR plug-in bets in the data order (no seed), running maximum.
- ``plugin:16``: terminal capital averaged over 16 data orders.
- ``mixture``: the grid mixture of 6 constant bets (lambda_min 1.7^j), terminal capital.
- ``const-oracle``: one constant bet sqrt(2 log(2/alpha) / (n sigma^2)) at the TRUE variance:
  not a method (sigma^2 is unknown), the ceiling of every order-free constant bet.
- ``const-D0``: the same bet at a variance estimated on an independent sample of n0 =
  max(1, round(n / 19)) values (the default study's D0 : D = 5 : 95),
  sigma2 = (1/4 + sum (x - mean)^2) / (n0 + 1) (WSR's shrunk estimator): valid (the bet is
  independent of the sample tested), order-free.
- ``const-pilot``: the twin side's honest pilot: the first ceil(sqrt(n)) values estimate
  sigma2 as above and are left out; the interval uses the other n - ceil(sqrt(n)).
- ``mix-D0``: uniform mixture of the three constant bets lambda_D0 * {1/1.5, 1, 1.5}.
- ``wsr-c0.5``, ``wsr-c0.75``: the reference itself at WSR's suggested truncations c = 1/2
  and 3/4 (its ratio to the reference at c = 0.9 is WSR(c)/WSR(0.9); the default's ratio to
  WSR at c is then plugin / wsr-c).
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
    OrderedSide,
    betting_bounds,
    capital_bound,
    ordered_sides,
)
from twinfalsify.inference.samples import HypothesisSamples, Ragged

DISTRIBUTIONS = {  # name: (draw(rng, shape), mean, variance)
    "Bernoulli(1/2)": (lambda r, s: (r.random(s) < 0.5).astype(float), 0.5, 0.25),
    "Bernoulli(0.1)": (lambda r, s: (r.random(s) < 0.1).astype(float), 0.1, 0.09),
    "Beta(2,2)": (lambda r, s: r.beta(2, 2, s), 0.5, 0.05),
    "Uniform": (lambda r, s: r.random(s), 0.5, 1 / 12),
}
VARIANTS = ("plugin", "plugin:16", "mixture", "const-oracle", "const-D0", "const-pilot",
            "mix-D0", "wsr-c0.5", "wsr-c0.75")


def wsr_reference(x: np.ndarray, alpha: float, c: float = C_TRUNC, n_iter: int = 50
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the hedged WSR (1 - alpha) interval for every row of x (R, n)."""
    r, n = x.shape
    t = np.arange(1, n + 1)
    mu = (0.5 + np.cumsum(x, axis=1)) / (t + 1)
    sig2 = (0.25 + np.cumsum((x - mu) ** 2, axis=1)) / (t + 1)
    prev = np.concatenate([np.full((r, 1), 0.25), sig2[:, :-1]], axis=1)
    lam = np.sqrt(2 * np.log(2 / alpha) / (n * prev))  # log(1/(alpha theta)), theta = 1/2
    level = np.log(2 / alpha)  # theta K >= 1/alpha

    def hit(m: np.ndarray, sign: int) -> np.ndarray:
        with np.errstate(divide="ignore"):
            cap = c / m if sign > 0 else c / (1 - m)
        lm = np.minimum(lam, cap[:, None])
        logk = np.cumsum(np.log1p(sign * lm * (x - m[:, None])), axis=1)
        return logk.max(axis=1) >= level

    mean = x.mean(axis=1)
    a, b = np.zeros(r), mean.copy()  # lower end: rejected at a (or a = 0), not at b
    for _ in range(n_iter):
        mid = 0.5 * (a + b)
        h = hit(mid, +1)
        a, b = np.where(h, mid, a), np.where(h, b, mid)
    lower = b
    a, b = mean.copy(), np.ones(r)
    for _ in range(n_iter):
        mid = 0.5 * (a + b)
        h = hit(mid, -1)
        a, b = np.where(h, a, mid), np.where(h, mid, b)
    return lower, a


def hoeffding(x: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    h = math.sqrt(math.log(2 / alpha) / (2 * x.shape[1]))
    m = x.mean(axis=1)
    return np.maximum(0.0, m - h), np.minimum(1.0, m + h)


def _samples(x: np.ndarray) -> HypothesisSamples:
    r, n = x.shape
    g = Ragged(x.ravel().copy(), np.arange(0, r * n + 1, n, dtype=np.int64))
    return HypothesisSamples(np.zeros(r), np.ones(r), np.full(r, n), g, g)


def _shrunk_var(x0: np.ndarray) -> np.ndarray:
    """WSR's shrunk variance estimate (1/4 + sum (x - mean)^2) / (n0 + 1), per row."""
    return (0.25 + ((x0 - x0.mean(axis=1, keepdims=True)) ** 2).sum(axis=1)) / (x0.shape[1] + 1)


def constant_ci(x: np.ndarray, alpha: float, lams: list[np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Interval of the uniform mixture of constant bets ``lams`` (each (R,)), terminal
    capital, truncated at c/m, c/(1-m): a symmetric function of each row of x."""
    r, n = x.shape
    j = len(lams)
    side = OrderedSide(np.tile(x.ravel(), j), np.concatenate([np.repeat(lam, n) for lam in lams]),
                       np.arange(0, j * r * n + 1, n, dtype=np.int64), j)
    lev = np.full(r, np.log(2 / alpha))
    return (capital_bound(side, lev, +1, False, C_TRUNC),
            capital_bound(side, lev, -1, False, C_TRUNC))


def bet_at(var: np.ndarray, n: int, alpha: float) -> np.ndarray:
    return np.sqrt(2 * np.log(2 / alpha) / (n * np.asarray(var, float)))


def variant_ci(name: str, x: np.ndarray, alpha: float, var: float, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:
    r, n = x.shape
    if name.startswith("wsr-c"):
        return wsr_reference(x, alpha, float(name[len("wsr-c"):]))
    if name in ("plugin", "plugin:16", "mixture"):
        kind, _, k = name.partition(":")
        opts = {"orders": int(k)} if k else {}
        b = betting_bounds(_samples(x), alpha, tune_alpha=alpha, bets=kind, **opts)
        return b["lower_twin"], b["upper_twin"]
    if name == "const-oracle":
        return constant_ci(x, alpha, [bet_at(np.full(r, var), n, alpha)])
    if name == "const-pilot":
        k = math.ceil(math.sqrt(n))
        return constant_ci(x[:, k:], alpha, [bet_at(_shrunk_var(x[:, :k]), n - k, alpha)])
    n0 = max(1, round(n / 19))
    draw = DISTRIBUTIONS[_current[0]][0]
    lam = bet_at(_shrunk_var(draw(rng, (r, n0))), n, alpha)
    if name == "const-D0":
        return constant_ci(x, alpha, [lam])
    if name == "mix-D0":
        return constant_ci(x, alpha, [lam / 1.5, lam, lam * 1.5])
    raise ValueError(name)


_current = [""]  # distribution being run (the D0 sample is drawn from it)


def cp_upper(k: int, n: int) -> float:
    """Clopper-Pearson 95 % upper bound of a binomial rate."""
    return 1.0 if k >= n else float(stats.beta.ppf(0.975, k + 1, n - k))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=1000, help="replicates per cell (widths)")
    ap.add_argument("--coverage-reps", type=int, default=10000,
                    help="further replicates per cell for the default's coverage")
    ap.add_argument("--ns", type=int, nargs="+", default=[20, 50, 200, 1000])
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.05, 1e-4])
    ap.add_argument("--distributions", nargs="+", default=list(DISTRIBUTIONS),
                    choices=list(DISTRIBUTIONS))
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--merge", nargs="+", help="print the tables from these runs' outputs")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge)
        return
    print("#args " + json.dumps({"reps": args.reps, "coverage_reps": args.coverage_reps}))
    rng = np.random.default_rng(args.seed)
    rows = []
    t0 = time.monotonic()
    for dist in args.distributions:
        _current[0] = dist
        draw, mu, var = DISTRIBUTIONS[dist]
        for n in args.ns:
            for alpha in args.alphas:
                x = draw(rng, (args.reps, n))
                # the order the default uses (data order); WSR sees the same sequences
                xo = ordered_sides(_samples(x), alpha / 2, order="data")[2].x.reshape(x.shape)
                w_lo, w_up = wsr_reference(xo, alpha)
                h_lo, h_up = hoeffding(x, alpha)
                w, hw = np.mean(w_up - w_lo), np.mean(h_up - h_lo)
                row = {"dist": dist, "n": n, "alpha": alpha, "wsr": w, "hoef": hw,
                       "miss": {"wsr": int(np.sum((w_lo > mu) | (w_up < mu))),
                                "hoeffding": int(np.sum((h_lo > mu) | (h_up < mu)))},
                       "ratio": {}, "wider_hoef": {}}
                for v in args.variants:
                    lo, up = variant_ci(v, x, alpha, var, rng)
                    row["ratio"][v] = np.mean(up - lo) / w
                    row["wider_hoef"][v] = float(np.mean((up - lo) > (h_up - h_lo) + 1e-12))
                    row["miss"][v] = int(np.sum((lo > mu) | (up < mu)))
                if args.coverage_reps and "plugin" in args.variants:
                    miss = 0
                    for k in range(0, args.coverage_reps, 2000):
                        xc = draw(rng, (min(2000, args.coverage_reps - k), n))
                        lo, up = variant_ci("plugin", xc, alpha, var, rng)
                        miss += int(np.sum((lo > mu) | (up < mu)))
                    row["cov_miss"] = miss
                rows.append(row)
                print(f"# {dist} n={n} alpha={alpha:g} done ({time.monotonic() - t0:.0f} s)",
                      flush=True)
                print("#row " + json.dumps(row), flush=True)
    report(rows, args.variants, args.reps, args.coverage_reps)
    print(f"total {time.monotonic() - t0:.0f} s")


def report(rows: list[dict], vs: list[str], reps: int, coverage_reps: int) -> None:
    """The three tables and the worst ratios, from the per-cell rows (each row may carry its
    own replicate counts ``reps``, ``cov_reps``; else the run's)."""
    for r in rows:
        r.setdefault("reps", reps)
        r.setdefault("cov_reps", coverage_reps)
    print(f"\nwidth / hedged WSR width (mean over the replicates; c = {C_TRUNC})\n")
    print("| distribution | n | alpha | replicates | WSR width | Hoeffding | " + " | ".join(vs)
          + " |")
    print("|---|---|---|---|---|---|" + "---|" * len(vs))
    for r in rows:
        print(f"| {r['dist']} | {r['n']} | {r['alpha']:g} | {r['reps']} | {r['wsr']:.4f} | "
              f"{r['hoef'] / r['wsr']:.3f} | "
              + " | ".join(f"{r['ratio'][v]:.3f}" for v in vs) + " |")
    print("\nwidth / Hoeffding width (mean); in brackets: share of replicates where the "
          "variant is wider than Hoeffding\n")
    print("| distribution | n | alpha | WSR | " + " | ".join(vs) + " |")
    print("|---|---|---|---|" + "---|" * len(vs))
    for r in rows:
        q = r["wsr"] / r["hoef"]
        print(f"| {r['dist']} | {r['n']} | {r['alpha']:g} | {q:.3f} | "
              + " | ".join(f"{r['ratio'][v] * q:.3f} ({r['wider_hoef'][v]:.0%})" for v in vs)
              + " |")
    print("\ncoverage: misses (true mean outside the interval) over the width replicates; "
          "nominal alpha; last column: the default over further replicates "
          "(95 % Clopper-Pearson upper bound)\n")
    names = ["wsr", "hoeffding", *vs]
    print("| distribution | n | alpha | replicates | " + " | ".join(names)
          + " | plugin, more reps |")
    print("|---|---|---|---|" + "---|" * (len(names) + 1))
    for r in rows:
        cm, cr = r.get("cov_miss"), r["cov_reps"]
        more = f"{cm} / {cr} (<= {cp_upper(cm, cr):.2g})" if cm is not None and cr else "-"
        print(f"| {r['dist']} | {r['n']} | {r['alpha']:g} | {r['reps']} | "
              + " | ".join(str(r["miss"][v]) for v in names) + f" | {more} |")
    worst = {v: max(r["ratio"][v] for r in rows) for v in vs}
    over_h = {v: max(r["ratio"][v] * r["wsr"] / r["hoef"] for r in rows) for v in vs}
    print("\nworst ratio to WSR: " + ", ".join(f"{v} {worst[v]:.3f}" for v in vs))
    print("worst ratio to Hoeffding: " + ", ".join(f"{v} {over_h[v]:.3f}" for v in vs))


def merge(paths: list[str]) -> None:
    """Tables from the ``#row`` lines of runs split by ``--distributions`` / ``--ns``
    (parallel jobs); each row keeps its own run's replicate counts."""
    rows = []
    for p in paths:
        lines = open(p).read().splitlines()
        a = json.loads(next(ln for ln in lines if ln.startswith("#args "))[6:])
        rows += [{**json.loads(ln[5:]), "reps": a["reps"], "cov_reps": a["coverage_reps"]}
                 for ln in lines if ln.startswith("#row ")]
    rows.sort(key=lambda r: (list(DISTRIBUTIONS).index(r["dist"]), r["n"], -r["alpha"]))
    vs = [v for v in VARIANTS if v in rows[0]["ratio"]]
    report(rows, vs, 0, 0)


if __name__ == "__main__":
    main()
