"""Benchmark of the tests stage: vectorised methods vs a straightforward per-hypothesis pandas
implementation of the same methods on the same data, in one run; prints the ratio.

    PYTHONPATH=src python benchmarks/bench_tests_stage.py [--hypotheses 3000] [--baseline-subset K]

Data: H synthetic hypotheses of realistic size (n log-uniform in [50, 11000], nhat
log-uniform in [20, 4000], follower fraction uniform in [0.05, 0.9], outcomes
normal with some twins shifted), raw outcomes clipped to [y_lo, y_up] by the methods.
Methods: Hoeffding, reverse-percentile bootstrap (100 resamples, exact p), betting
(WSR 2024), empirical Bernstein, each followed by Holm over all 2H p-values.
The baseline loops over hypotheses with pandas Series (materialised samples,
Series.sample for the bootstrap, pandas cumulative ops and a bisection on m for
betting). ``--baseline-subset K`` times the baseline on K random hypotheses and
scales linearly (stated in the output) when the full loop would take too long.

``--power`` instead prints the small power/width comparison of the exact methods
quoted in docs/explanation/statistics.md.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import pandas as pd

from twinfalsify.inference.bernstein import bernstein_test
from twinfalsify.inference.betting import C_TRUNC, betting_test, default_tune_alpha
from twinfalsify.inference.bootstrap import bootstrap_test
from twinfalsify.inference.hoeffding import hoeffding_test
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged


def make_samples(h: int, seed: int = 0) -> HypothesisSamples:
    rng = np.random.default_rng(seed)
    n = np.exp(rng.uniform(np.log(50), np.log(11000), h)).astype(np.int64)
    nf = (n * rng.uniform(0.05, 0.9, h)).astype(np.int64)
    nhat = np.exp(rng.uniform(np.log(20), np.log(4000), h)).astype(np.int64)
    mu = rng.uniform(60, 100, h)
    shift = np.where(rng.random(h) < 0.3, rng.normal(0, 6, h), 0.0)
    follow = Ragged.from_groups([rng.normal(mu[i], 12, k) for i, k in enumerate(nf)])
    twin = Ragged.from_groups([rng.normal(mu[i] + shift[i], 12, k) for i, k in enumerate(nhat)])
    y_lo, y_up = mu - 10, mu + 10  # ~20 % clipped on each side
    return HypothesisSamples(y_lo, y_up, n, follow, twin)


METHODS = {
    "hoeffding": hoeffding_test,
    "bootstrap": lambda s: bootstrap_test(s, n_resamples=100, seed=0),
    # one order of the plug-in bets, as the baseline
    "betting": lambda s: betting_test(s, bets="plugin", seed=0, orders=1),
    "bernstein": bernstein_test,
}


def run_vectorised(s: HypothesisSamples) -> dict[str, tuple[float, int]]:
    out = {}
    for name, fn in METHODS.items():
        t0 = time.perf_counter()
        p_lo, p_up = fn(s)
        rej = correct(np.concatenate([p_lo, p_up]), 0.05, "holm")
        out[name] = (time.perf_counter() - t0, int(rej.sum()))
    return out


# ---------------------------------------------------------------- per-hypothesis baseline
def _baseline_one(y_lo, y_up, n, follow, twin, rng, alpha0, b=100):
    """All four methods for one hypothesis, written the straightforward way with pandas."""
    r = y_up - y_lo
    f = pd.Series(follow).clip(y_lo, y_up)
    obs = pd.DataFrame({
        "lo": pd.concat([f, pd.Series(np.full(n - len(f), y_lo))], ignore_index=True),
        "up": pd.concat([f, pd.Series(np.full(n - len(f), y_up))], ignore_index=True),
    })
    tw = pd.Series(twin).clip(y_lo, y_up)
    q_lo, q_up, q_tw = obs["lo"].mean(), obs["up"].mean(), tw.mean()
    nhat = len(tw)
    out = {}
    # Hoeffding
    s = 1 / np.sqrt(n) + 1 / np.sqrt(nhat)
    out["hoeffding"] = tuple(
        min(1.0, 2 * np.exp(-2 * d**2 / (r * s) ** 2)) if d > 0 else 1.0
        for d in (q_lo - q_tw, q_tw - q_up)
    )
    # bootstrap (reverse percentile, exact smallest alpha on the sorted resamples)
    if n >= 100 and nhat >= 100:
        bo = [obs.sample(n, replace=True, random_state=rng).mean() for _ in range(b)]
        bl = np.sort([x["lo"] for x in bo])
        bu = np.sort([x["up"] for x in bo])
        bt = np.sort([tw.sample(nhat, replace=True, random_state=rng).mean() for _ in range(b)])

        def p_rp(sh, small, lh, large):
            for j in range((b + 1) // 2):
                if 2 * sh - small[j] < 2 * lh - large[b - 1 - j]:
                    return min(1.0, 2 * j / b)
            return 1.0

        out["bootstrap"] = (p_rp(q_tw, bt, q_lo, bl), p_rp(q_up, bu, q_tw, bt))
    else:
        out["bootstrap"] = (1.0, 1.0)
    # empirical Bernstein
    ps = []
    for d, v in ((q_lo - q_tw, obs["lo"].var()), (q_tw - q_up, obs["up"].var())):
        a = np.sqrt(2 * v / n) + np.sqrt(2 * tw.var() / nhat)
        bb = 7 * r / (3 * (n - 1)) + 7 * r / (3 * (nhat - 1))
        ss = (-a + np.sqrt(a * a + 4 * bb * d)) / (2 * bb) if d > 0 else 0.0
        ps.append(min(1.0, 4 * np.exp(-ss * ss)) if d > 0 else 1.0)
    out["bernstein"] = tuple(ps)
    # betting: permute, plug-in bets with pandas expanding ops, bisection on m
    xo = obs.sample(frac=1, random_state=rng).reset_index(drop=True)
    xt = ((tw - y_lo) / r).sample(frac=1, random_state=rng).reset_index(drop=True)

    def bets(x):
        k = pd.Series(np.arange(1, len(x) + 1))
        mu = (0.5 + x.cumsum()) / (k + 1)
        sig = (0.25 + ((x - mu) ** 2).cumsum()) / (k + 1)
        prev = sig.shift(1, fill_value=0.25)
        return np.sqrt(2 * np.log(2 / alpha0) / (len(x) * prev))  # truncated per m below

    def logk(x, lam, m, sign):
        cap = C_TRUNC / m if sign > 0 else C_TRUNC / (1 - m)
        return max(0.0, np.log1p(sign * lam.clip(upper=cap) * (x - m)).cumsum().max())

    ps = []
    for large, small in (((xo["lo"] - y_lo) / r, xt), (xt, (xo["up"] - y_lo) / r)):
        la, ls = bets(large), bets(small)
        a_, b_ = 0.0, 1.0
        for _ in range(40):
            m = 0.5 * (a_ + b_)
            if logk(large, la, m, 1) >= logk(small, ls, m, -1):
                a_ = m
            else:
                b_ = m
        k = max(logk(large, la, b_, 1), logk(small, ls, a_, -1))
        ps.append(min(1.0, 2 * np.exp(-k)))
    out["betting"] = tuple(ps)
    return out


def run_baseline(s: HypothesisSamples, index: np.ndarray) -> float:
    rng = np.random.default_rng(0)
    alpha0 = default_tune_alpha(len(s))
    t0 = time.perf_counter()
    results = []
    for h in index:
        results.append(_baseline_one(s.y_lo[h], s.y_up[h], int(s.n[h]), s.follow.group(h),
                                     s.twin.group(h), rng, alpha0))
    for name in METHODS:  # the correction, as in the vectorised run
        p = np.array([r[name] for r in results]).T.ravel()
        correct(p, 0.05, "holm")
    return time.perf_counter() - t0


def power_comparison() -> None:
    """Width and power of the exact methods on simple simulated cases.

    Quoted in docs/explanation/statistics.md.
    """
    from twinfalsify.inference.bernstein import bernstein_radius, sample_variances
    from twinfalsify.inference.betting import ordered_sides
    from twinfalsify.inference.capital import capital_bound
    from twinfalsify.inference.hoeffding import hoeffding_radius

    rng = np.random.default_rng(0)
    print("mean one-sided (1 - alpha/2) radius / Hoeffding radius (200 reps, values in [0, 1])")
    for name, draw in (("Bernoulli(1/2)", lambda k: rng.binomial(1, 0.5, k) * 1.0),
                       ("Bernoulli(0.1)", lambda k: rng.binomial(1, 0.1, k) * 1.0),
                       ("Beta(2,2)", lambda k: rng.beta(2, 2, k)),
                       ("Uniform", lambda k: rng.random(k))):
        for n in (50, 200, 1000, 4000):
            reps = 200
            grp = Ragged.from_groups([draw(n) for _ in range(reps)])
            s = HypothesisSamples(np.zeros(reps), np.ones(reps), np.full(reps, n), grp, grp)
            v = sample_variances(s)[2]
            for alpha in (0.05, 1e-5):
                hr = hoeffding_radius(1.0, n, alpha)
                tw = ordered_sides(s, alpha / 2)[2]  # bets tuned at the level evaluated
                up = capital_bound(tw, np.full(reps, np.log(2 / alpha)), -1, True, C_TRUNC)
                rb = np.mean(up - s.q_twin_hat) / hr
                re = np.mean(bernstein_radius(v, np.full(reps, n), np.ones(reps), alpha)) / hr
                print(f"  {name:15s} n={n:5d} alpha={alpha:g}: betting {rb:.2f}  "
                      f"Bernstein {re:.2f}")
    print("\npower: Holm over 200 hypotheses, twin shifted down by d (Beta(2,2) outcomes,")
    print("obs propensity 0.7 => Y_lo has mass 0.3 at y_lo; n = nhat)")
    for n in (200, 1000, 4000):
        for d in (0.02, 0.05, 0.1, 0.2):
            h = 200
            nf = rng.binomial(n, 0.7, h)
            follow = Ragged.from_groups([rng.beta(2, 2, k) for k in nf])
            # Q_lo = 0.7 * 0.5 = 0.35; twin mean 0.35 - d
            twin = Ragged.from_groups([np.clip(rng.beta(2, 2, n) * 0.7 - d, 0, 1)
                                       for _ in range(h)])
            s = HypothesisSamples(np.zeros(h), np.ones(h), np.full(h, n), follow, twin)
            row = []
            for name, fn in (("hoeffding", hoeffding_test), ("betting", betting_test),
                             ("bernstein", bernstein_test),
                             ("bootstrap", lambda x: bootstrap_test(x, seed=1))):
                p_lo, p_up = fn(s)
                rej = correct(np.concatenate([p_lo, p_up]), 0.05, "holm")[:h]
                row.append(f"{name} {rej.mean():.2f}")
            print(f"  n={n:5d} d={d:.2f}: " + "  ".join(row))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hypotheses", type=int, default=3000)
    ap.add_argument("--baseline-subset", type=int, default=0,
                    help="time the baseline on this many hypotheses and scale (0: all)")
    ap.add_argument("--power", action="store_true")
    args = ap.parse_args()
    if args.power:
        power_comparison()
        return
    s = make_samples(args.hypotheses)
    print(f"H = {len(s)}, total n = {int(s.n.sum()):,}, total followers = "
          f"{int(s.n_follow.sum()):,}, total nhat = {int(s.nhat.sum()):,}")
    print(f"load average at start: {os.getloadavg()[0]:.1f} (machine has {os.cpu_count()} cores)")
    vec = run_vectorised(s)
    total_vec = sum(t for t, _ in vec.values())
    for name, (t, k) in vec.items():
        print(f"  vectorised {name:10s} {t:7.2f} s   Holm rejections {k}")
    print(f"  vectorised total      {total_vec:7.2f} s")
    h = len(s)
    if args.baseline_subset and args.baseline_subset < h:
        idx = np.sort(np.random.default_rng(1).choice(h, args.baseline_subset, replace=False))
        t_sub = run_baseline(s, idx)
        t_base = t_sub * h / len(idx)
        print(f"  baseline (pandas, per hypothesis) {t_sub:.1f} s on {len(idx)} hypotheses "
              f"-> {t_base:.1f} s scaled to {h}")
    else:
        t_base = run_baseline(s, np.arange(h))
        print(f"  baseline (pandas, per hypothesis) {t_base:.1f} s")
    # time the vectorised run again after the baseline and keep the slower of the two, so
    # a change of machine load during the run cannot flatter the ratio
    again = sum(t for t, _ in run_vectorised(s).values())
    print(f"  vectorised total, rerun after the baseline {again:7.2f} s")
    print(f"load average at end: {os.getloadavg()[0]:.1f}")
    print(f"ratio baseline / vectorised = {t_base / max(total_vec, again):.1f}x")


if __name__ == "__main__":
    main()
