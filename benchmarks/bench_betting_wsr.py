"""Betting intervals: the project's against Waudby-Smith & Ramdas's hedged capital process.

    PYTHONPATH=src python benchmarks/bench_betting_wsr.py [--reps 200] [--coverage-reps 2000]

Reference. ``confseq`` (the authors' package) does not build here (its C++ part needs
Boost headers); when it imports, its ``betting.betting_mart`` is used as a cross-check of
the reference below, otherwise that check is skipped. ``hedged_ci_reference`` implements
the published process directly (WSR 2024, JRSS-B 86(1):1-27, Sec. 4, Thm 3, with the
predictable plug-in bets of Sec. 5.1 tuned for a fixed n, as confseq's ``betting_ci`` does):

    K^pm_t(m) = max(theta K+_t(m), (1 - theta) K-_t(m)),  theta = 1/2,
    K+_t(m) = prod_{i<=t} (1 + min(lambda_i, c/m) (x_i - m)),
    K-_t(m) = prod_{i<=t} (1 - min(lambda_i, c/(1-m)) (x_i - m)),
    lambda_i = sqrt(2 log(1/(alpha theta)) / (n sigma2_{i-1})),  (sigma2 as in the paper,
               prior mean 1/2, prior variance 1/4, one fake observation),

and the (1 - alpha) interval {m : K^pm_t(m) < 1/alpha for every t <= n} (the running
intersection). It is a plain per-sample loop over t, per m, sharing no code with the
library; each end is found by bisection on m (K+ is non-increasing, K- non-decreasing in m,
so each end is a monotone threshold), 50 halvings (resolution 1e-15).

Project. ``betting.betting_bounds`` (lower_twin, upper_twin; bets tuned at alpha/2, the
same level), and the order-free variant used by ``betting_test`` by default (terminal
capital averaged over K seeded orders, ``orders``): its interval is computed by bisection
on the same averaged capital.

The reference is fed each sample in the project's seeded order (any fixed order is as valid;
using the same one makes the ratio measure the algorithms, not two orders' luck).
Printed per (distribution, n, alpha): mean width of the project's interval / mean width of
the reference's on the same samples (target <= 1.00), the same for the order-free variant,
and the project's one-sided miss rates over ``coverage-reps`` replicates (nominal alpha/2
each side; Monte-Carlo 2-SE given).
"""

from __future__ import annotations

import argparse

import numpy as np

from twinfalsify.inference.betting import (
    C_TRUNC,
    _bound,
    betting_bounds,
    ordered_sides,
)
from twinfalsify.inference.samples import HypothesisSamples, Ragged

DISTRIBUTIONS = {
    "Beta(2,5)": (lambda r, k: r.beta(2, 5, k), 2 / 7),
    "30%-at-0 + Beta(2,2)": (lambda r, k: np.where(r.random(k) < 0.3, 0.0, r.beta(2, 2, k)),
                             0.7 * 0.5),
    "Bernoulli(0.1)": (lambda r, k: (r.random(k) < 0.1).astype(float), 0.1),
    "Beta(2,2)": (lambda r, k: r.beta(2, 2, k), 0.5),
    "Uniform": (lambda r, k: r.random(k), 0.5),
}


def _plugin_bets_ref(x: np.ndarray, alpha_side: float) -> np.ndarray:
    """WSR's fixed-n predictable plug-in bets, written out as a loop over t."""
    n = len(x)
    lam = np.empty(n)
    s, ss, sig2_prev = 0.0, 0.0, 0.25
    for t in range(1, n + 1):
        lam[t - 1] = np.sqrt(2 * np.log(1 / alpha_side) / (n * sig2_prev))
        s += x[t - 1]
        mu = min((0.5 + s) / (t + 1), 1.0)
        ss += (x[t - 1] - mu) ** 2
        sig2_prev = (0.25 + ss) / (t + 1)
    return lam


def hedged_ci_reference(x: np.ndarray, alpha: float, c: float = C_TRUNC,
                        theta: float = 0.5) -> tuple[float, float]:
    """(lower, upper) of WSR's hedged-capital (1 - alpha) CI (module doc)."""
    lam_p = _plugin_bets_ref(x, alpha * theta)
    lam_m = _plugin_bets_ref(x, alpha * (1 - theta))

    def rejected(m: float) -> tuple[bool, bool]:
        m = np.float64(m)  # m = 0 or 1 (all-0 / all-1 samples): the cap is +inf, not an error
        with np.errstate(divide="ignore", invalid="ignore"):
            kp = np.cumprod(1 + np.minimum(lam_p, c / m) * (x - m))
            km = np.cumprod(1 - np.minimum(lam_m, c / (1 - m)) * (x - m))
        return bool(np.any(theta * kp >= 1 / alpha)), bool(np.any((1 - theta) * km >= 1 / alpha))

    mean = float(np.mean(x))
    a, b = 0.0, mean  # lower end: K+ rejects at a (or a = 0), not at b
    for _ in range(50):
        mid = 0.5 * (a + b)
        a, b = (mid, b) if rejected(mid)[0] else (a, mid)
    lower = b
    a, b = mean, 1.0
    for _ in range(50):
        mid = 0.5 * (a + b)
        a, b = (a, mid) if rejected(mid)[1] else (mid, b)
    return lower, a


def _confseq_check(x: np.ndarray, alpha: float, lower: float, upper: float) -> str:
    """Cross-check against confseq's own capital process when it is installed."""
    try:
        from confseq.betting import betting_mart
        from confseq.betting_strategies import lambda_predmix_eb
    except ImportError:
        return "confseq not installed: cross-check skipped"
    n = len(x)
    fn = lambda z, m: lambda_predmix_eb(z, alpha=alpha / 2, fixed_n=n)  # noqa: E731
    bad = 0
    for m, inside in ((lower + 1e-6, True), (upper - 1e-6, True),
                      (lower - 1e-3, False), (upper + 1e-3, False)):
        if not 0 < m < 1:
            continue
        k = betting_mart(x, m, alpha=alpha, lambdas_fn_positive=fn, lambdas_fn_negative=fn,
                         trunc_scale=C_TRUNC, m_trunc=True)
        bad += (np.max(k) < 1 / alpha) != inside
    return f"confseq cross-check: {bad} disagreement(s)"


def _samples(xs: list[np.ndarray]) -> HypothesisSamples:
    g = len(xs)
    r = Ragged.from_groups(xs)
    return HypothesisSamples(np.zeros(g), np.ones(g), np.array([len(x) for x in xs]), r, r)


def project_ci(xs: list[np.ndarray], alpha: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    b = betting_bounds(_samples(xs), alpha, tune_alpha=alpha, bets="plugin", seed=seed)
    return b["lower_twin"], b["upper_twin"]


def order_free_ci(xs: list[np.ndarray], alpha: float, seed: int, orders: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The order-free interval: terminal capital averaged over ``orders`` seeded orders."""
    s = _samples(xs)
    tw = ordered_sides(s, alpha / 2, seed=seed, orders=orders)[2]
    lev = np.full(len(xs), np.log(2 / alpha))
    return (_bound(tw, lev, +1, False, C_TRUNC), _bound(tw, lev, -1, False, C_TRUNC))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=200, help="replicates for the width ratio")
    ap.add_argument("--coverage-reps", type=int, default=2000)
    ap.add_argument("--orders", type=int, default=16)
    ap.add_argument("--ns", type=int, nargs="+", default=[20, 100, 1000])
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.05, 1e-4])
    ap.add_argument("--distributions", nargs="+", default=list(DISTRIBUTIONS),
                    choices=list(DISTRIBUTIONS))
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"c = {C_TRUNC}; width ratio = mean width project / mean width reference "
          f"({args.reps} reps); order-free: K = {args.orders} orders, terminal capital")
    print("| distribution | n | alpha | project / WSR | order-free / WSR | miss below | "
          "miss above | nominal per side |")
    print("|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for name in args.distributions:
        draw, mu = DISTRIBUTIONS[name]
        for n in args.ns:
            for alpha in args.alphas:
                xs = [draw(rng, n) for _ in range(args.reps)]
                lo, up = project_ci(xs, alpha, seed=1)
                # the reference sees each sample in the project's (seeded) order, so the
                # ratio measures the algorithms, not the luck of two different orders
                tw = ordered_sides(_samples(xs), alpha / 2, seed=1)[2]
                ref = np.array([hedged_ci_reference(tw.x[tw.offsets[i]: tw.offsets[i + 1]], alpha)
                                for i in range(len(xs))])
                flo, fup = order_free_ci(xs, alpha, seed=1, orders=args.orders)
                ratio = np.mean(up - lo) / np.mean(ref[:, 1] - ref[:, 0])
                ratio_f = np.mean(fup - flo) / np.mean(ref[:, 1] - ref[:, 0])
                worst = max(worst, ratio)
                cov = [draw(rng, n) for _ in range(args.coverage_reps)]
                clo, cup = project_ci(cov, alpha, seed=2)
                below, above = np.mean(clo > mu), np.mean(cup < mu)
                se = 2 * np.sqrt(alpha / 2 * (1 - alpha / 2) / args.coverage_reps)
                print(f"| {name} | {n} | {alpha:g} | {ratio:.3f} | {ratio_f:.3f} | "
                      f"{below:.4f} | {above:.4f} | {alpha / 2:g} (2 SE {se:.4f}) |",
                      flush=True)
    print(f"\nworst width ratio project / WSR: {worst:.3f} (target <= 1.00)")
    x = DISTRIBUTIONS["Beta(2,5)"][0](rng, 100)
    lo, up = hedged_ci_reference(x, 0.05)
    print(_confseq_check(x, 0.05, lo, up))


if __name__ == "__main__":
    main()
