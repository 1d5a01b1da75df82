"""Type-I error of the default betting test at the null boundary under three stay numberings.

    PYTHONPATH=src nice -n 10 python benchmarks/bench_order_null.py [--keys 200] [--reps 50]
        [--n 1000] [--alpha 0.05]

One hypothesis (t = 1, action a_1 = 1, B = whole space) per simulated study of n stays:
X_0 ~ N(0, I_2), A_1 ~ Bernoulli(logistic(X_0[0])), X_1 = X_0 + N(0, 0.6^2 I), outcome
Y = X_1[0] clipped to [y_lo, y_up] = [-2, 2]. The twin runs on the n stays of D itself
(m = n: every X_0 of D, in the plan's keyed X_0 order, ``runs.plan.plan_twin_runs``); run j
returns y_lo with probability 1 - P(A_1 = 1 | X_0 j) and otherwise a fresh draw of X_1[0]
given X_0 j, so Q_twin = Q_lo exactly: H_lo at its boundary. A rejection of H_lo at alpha is
a type-I error.

The stays are listed by id, and the ids are assigned three ways: at random; correlated with
the outcome (id rank = rank of r z(Y) + sqrt(1 - r^2) noise, r = 0.75, z the standardised
outcome); sorted by the outcome. Two data orders are measured on the same data:

- ``content``: the default, as the workflow computes it: ``inference.order.content_keys``
  of (X_0:1, A_1) keyed by the study seed gives each follower's position
  (``bounds.observational_side``'s rule), ``x0_keys`` orders the twin's X_0, then
  ``betting_test`` (default options, tuned for a family of one hypothesis). The order key
  is the study seed: keys 0..K-1, ``--reps`` studies each.
- ``stay id``: followers at their rank in stay-id order, then the seedless hash of
  (hypothesis key, position), the twin's X_0 in a seeded random order: the construction the
  content order replaced, for contrast. The order key is the hypothesis key: 0..K-1.

Prints per (order, numbering): type-I rate pooled over all K x reps studies and the worst
key's rate, each with an exact (Clopper-Pearson, 95 %) interval; the probability that the
worst of K keys reaches that count if every key had the pooled rate (a selection check:
the worst of many binomials is large by chance); and the largest ratio between the content
order's p-values under the numberings (the order is the same; only floating-point sums over
followers listed in another row order differ).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from scipy.stats import beta as beta_dist
from scipy.stats import binom

from twinfalsify.inference.betting import betting_test, default_tune_alpha
from twinfalsify.inference.order import content_keys, x0_keys
from twinfalsify.inference.samples import HypothesisSamples, Ragged

Y_LO, Y_UP, R_ID = -2.0, 2.0, 0.75
NUMBERINGS = ("random", "correlated r = 0.75", "sorted by outcome")


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1 - level
    lo = 0.0 if k == 0 else float(beta_dist.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta_dist.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def simulate(rng: np.random.Generator, reps: int, n: int) -> dict[str, np.ndarray]:
    """``reps`` studies of n stays (rows in an arbitrary storage order)."""
    x0 = rng.normal(size=(reps, n, 2))
    prop = 1.0 / (1.0 + np.exp(-x0[..., 0]))
    a = (rng.random((reps, n)) < prop).astype(np.int64)
    x1 = x0 + rng.normal(0, 0.6, (reps, n, 2))
    y = np.clip(x1[..., 0], Y_LO, Y_UP)
    # the twin's run from X_0 j: the action with probability prop, else y_lo (module doc)
    tw = np.where(rng.random((reps, n)) < prop,
                  np.clip(x0[..., 0] + rng.normal(0, 0.6, (reps, n)), Y_LO, Y_UP), Y_LO)
    z = (y - y.mean(axis=1, keepdims=True)) / y.std(axis=1, keepdims=True)
    noisy = R_ID * z + np.sqrt(1 - R_ID**2) * rng.normal(size=(reps, n))
    ids = {
        NUMBERINGS[0]: np.argsort(rng.random((reps, n)), axis=1),
        NUMBERINGS[1]: np.argsort(np.argsort(noisy, axis=1), axis=1),
        NUMBERINGS[2]: np.argsort(np.argsort(y, axis=1, kind="stable"), axis=1),
    }
    return {"x0": x0, "a": a, "x1": x1, "y": y, "tw": tw, **ids}


def _samples(n: int, follow: list[np.ndarray], pos: list[np.ndarray], twin: list[np.ndarray],
             keys: np.ndarray) -> HypothesisSamples:
    h = len(follow)
    return HypothesisSamples(
        y_lo=np.full(h, Y_LO), y_up=np.full(h, Y_UP), n=np.full(h, n),
        follow=Ragged.from_groups(follow), twin=Ragged.from_groups(twin), keys=keys,
        follow_pos=Ragged.from_groups(pos),
    )  # fmt: skip


def content_pvalues(d: dict, numbering: str, seed: int) -> np.ndarray:
    """p_lo of every study with the stays listed by ``numbering``'s ids, content order."""
    reps, n = d["a"].shape
    follow, pos, twin = [], [], []
    for r in range(reps):
        rows = np.argsort(d[numbering][r])  # the table as stored: listed by stay id
        x = np.stack([d["x0"][r, rows], d["x1"][r, rows]], axis=1)  # (n, 2, F)
        act = d["a"][r, rows][:, None]
        k1 = content_keys(x, act, seed)[:, 1]
        rank = np.argsort(np.argsort(k1, kind="stable"), kind="stable")  # everyone enters
        f = act[:, 0] == 1
        follow.append(d["y"][r, rows][f])
        pos.append(rank[f])
        plan = np.lexsort((d[numbering][r, rows], x0_keys(x[:, 0], seed)))  # plan_twin_runs
        twin.append(d["tw"][r, rows][plan])
    s = _samples(n, follow, pos, twin, np.zeros(reps, np.int64))  # each study: hypothesis 0
    return betting_test(s, tune_alpha=default_tune_alpha(1))[0]


def id_pvalues(d: dict, numbering: str, key: int) -> np.ndarray:
    """p_lo with followers at their stay-id rank and the twin in stay-id order, hash of
    (hypothesis key, position) on top (the replaced construction)."""
    reps, n = d["a"].shape
    follow, pos, twin = [], [], []
    for r in range(reps):
        rows = np.argsort(d[numbering][r])
        f = d["a"][r, rows] == 1
        follow.append(d["y"][r, rows][f])
        pos.append(np.flatnonzero(f))
        # the twin's X_0: a seeded permutation of the stays sorted by id (as that plan drew)
        twin.append(d["tw"][r, rows][np.random.default_rng([key, r]).permutation(n)])
    s = _samples(n, follow, pos, twin, np.full(reps, key, np.int64))
    return betting_test(s, tune_alpha=default_tune_alpha(1))[0]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--keys", type=int, default=200)
    ap.add_argument("--reps", type=int, default=50, help="studies per order key")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=2026)
    args = ap.parse_args()
    t0 = time.monotonic()
    hits = {(o, nb): np.zeros(args.keys, np.int64) for o in ("content", "stay id")
            for nb in NUMBERINGS}
    spread = 0.0  # largest |log p ratio| between numberings, content order
    for key in range(args.keys):
        d = simulate(np.random.default_rng([args.seed, key]), args.reps, args.n)
        ref = None
        for nb in NUMBERINGS:
            p = content_pvalues(d, nb, key)
            ref = p if ref is None else ref
            spread = max(spread, float(np.max(np.abs(np.log(p) - np.log(ref)))))
            hits["content", nb][key] = int((p <= args.alpha).sum())
            hits["stay id", nb][key] = int((id_pvalues(d, nb, key) <= args.alpha).sum())
        if (key + 1) % 20 == 0:
            print(f"  {key + 1} keys, {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
    total = args.keys * args.reps
    print(f"n = {args.n}, alpha = {args.alpha}, {args.keys} order keys x {args.reps} studies "
          f"= {total} studies per cell, {time.monotonic() - t0:.0f} s")
    print("| order | stay numbering | type-I, pooled [95 % CI] | worst key [95 % CI] | "
          "P(worst >= this by chance) |")
    print("|---|---|---|---|---|")
    for (order, nb), h in hits.items():
        k = int(h.sum())
        lo, hi = clopper_pearson(k, total)
        w = int(h.max())
        wlo, whi = clopper_pearson(w, args.reps)
        rate = k / total
        p_sel = 1.0 - (binom.cdf(w - 1, args.reps, rate)) ** args.keys if w else 1.0
        print(f"| {order} | {nb} | {rate:.4f} [{lo:.4f}, {hi:.4f}] | {w / args.reps:.3f} "
              f"[{wlo:.3f}, {whi:.3f}] | {p_sel:.2f} |", flush=True)
    print(f"content order: largest |log p ratio| between the numberings: {spread:.1e} "
          "(same order; sums over followers listed in another row order round differently)")


if __name__ == "__main__":
    main()
