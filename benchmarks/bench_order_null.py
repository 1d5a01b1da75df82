"""Type-I error of the default betting test at the null boundary, per order key: a scan of
many keys, then a confirmatory run on the worst keys (a pooled rate cannot show one key's
violation, and the worst of many small-sample rates is large by chance).

    PYTHONPATH=src nice -n 10 python benchmarks/bench_order_null.py [--keys 200] [--reps 8]
        [--confirm 1000] [--top 3] [--n 1000] [--alpha 0.05] [--data continuous|binary]

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

``--data binary``: tied data. Every stay has the same X_0 (so the twin's X_0 all tie) and
a binary outcome Y ~ Bernoulli(0.5) (y_lo, y_up = 0, 1), A_1 ~ Bernoulli(0.5); the twin's run
j returns y_lo with probability 1/2, else a Bernoulli(0.5) draw: Q_twin = Q_lo. Identical
contents must not sit together (``inference.order.break_ties``).

Prints per (order, numbering): type-I rate pooled over all K x reps studies and the worst
scanned key's rate, then for each of the ``--top`` worst keys a confirmatory run of
``--confirm`` fresh studies with its exact (Clopper-Pearson, 95 %) interval, and the largest
ratio between the content order's p-values under the numberings (the order is the same;
only floating-point sums over followers listed in another row order differ).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from scipy.stats import beta as beta_dist

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


def simulate(rng: np.random.Generator, reps: int, n: int, data: str = "continuous"
             ) -> dict[str, np.ndarray]:
    """``reps`` studies of n stays (rows in an arbitrary storage order)."""
    global Y_LO, Y_UP
    if data == "binary":  # tied: one X_0 for everyone, binary outcome (module doc)
        Y_LO, Y_UP = 0.0, 1.0
        x0 = np.zeros((reps, n, 2))
        prop = np.full((reps, n), 0.5)
        a = (rng.random((reps, n)) < prop).astype(np.int64)
        x1 = x0.copy()
        x1[..., 0] = rng.random((reps, n)) < 0.5
        y = x1[..., 0]
        tw = np.where(rng.random((reps, n)) < prop, (rng.random((reps, n)) < 0.5) * 1.0, Y_LO)
    else:
        x0 = rng.normal(size=(reps, n, 2))
        prop = 1.0 / (1.0 + np.exp(-x0[..., 0]))
        a = (rng.random((reps, n)) < prop).astype(np.int64)
        x1 = x0 + rng.normal(0, 0.6, (reps, n, 2))
        y = np.clip(x1[..., 0], Y_LO, Y_UP)
        # the twin's run from X_0 j: the action with probability prop, else y_lo (module doc)
        tw = np.where(rng.random((reps, n)) < prop,
                      np.clip(x0[..., 0] + rng.normal(0, 0.6, (reps, n)), Y_LO, Y_UP), Y_LO)
    z = (y - y.mean(axis=1, keepdims=True)) / np.maximum(y.std(axis=1, keepdims=True), 1e-12)
    noisy = R_ID * z + np.sqrt(1 - R_ID**2) * rng.normal(size=(reps, n))
    ids = {
        NUMBERINGS[0]: np.argsort(rng.random((reps, n)), axis=1),
        NUMBERINGS[1]: np.argsort(np.argsort(noisy, axis=1), axis=1),
        NUMBERINGS[2]: np.argsort(np.argsort(y, axis=1, kind="stable"), axis=1),
    }
    return {"x0": x0, "a": a, "x1": x1, "y": y, "tw": tw, "tied_x0": data == "binary", **ids}


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
        if d["tied_x0"]:  # one X_0 for all: run j's output is the j-th draw, whoever's X_0
            twin.append(d["tw"][r])
        else:
            plan = np.lexsort((d[numbering][r, rows], x0_keys(x[:, 0], seed)))  # the plan
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
        twin.append(d["tw"][r] if d["tied_x0"] else
                    d["tw"][r, rows][np.random.default_rng([key, r]).permutation(n)])
    s = _samples(n, follow, pos, twin, np.full(reps, key, np.int64))
    return betting_test(s, tune_alpha=default_tune_alpha(1))[0]


def _hits(d: dict, order: str, nb: str, key: int, alpha: float) -> tuple[int, np.ndarray]:
    p = content_pvalues(d, nb, key) if order == "content" else id_pvalues(d, nb, key)
    return int((p <= alpha).sum()), p


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--keys", type=int, default=200)
    ap.add_argument("--reps", type=int, default=8, help="studies per order key in the scan")
    ap.add_argument("--confirm", type=int, default=1000, help="studies per confirmed key")
    ap.add_argument("--top", type=int, default=3, help="worst keys confirmed per cell")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--data", choices=("continuous", "binary"), default="continuous")
    ap.add_argument("--tied-keys", action="store_true",
                    help="for contrast: identical contents keep identical keys (no copy index)")
    args = ap.parse_args()
    if args.tied_keys:
        from twinfalsify.inference import order

        order.break_ties = lambda keys, seed: np.asarray(keys, dtype=np.uint64)
    t0 = time.monotonic()
    hits = {(o, nb): np.zeros(args.keys, np.int64) for o in ("content", "stay id")
            for nb in NUMBERINGS}
    spread = 0.0  # largest |log p ratio| between numberings, content order
    for key in range(args.keys):
        d = simulate(np.random.default_rng([args.seed, key]), args.reps, args.n, args.data)
        ref = None
        for nb in NUMBERINGS:
            k, p = _hits(d, "content", nb, key, args.alpha)
            ref = p if ref is None else ref
            spread = max(spread, float(np.max(np.abs(np.log(p) - np.log(ref)))))
            hits["content", nb][key] = k
            hits["stay id", nb][key] = _hits(d, "stay id", nb, key, args.alpha)[0]
        if (key + 1) % 20 == 0:
            print(f"  {key + 1} keys, {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)
    total = args.keys * args.reps
    print(f"data {args.data}, n = {args.n}, alpha = {args.alpha}: scan {args.keys} order keys "
          f"x {args.reps} studies, then the {args.top} worst keys of each cell x "
          f"{args.confirm} fresh studies")
    print("| order | stay numbering | type-I pooled (scan) [95 % CI] | worst scanned key | "
          "confirmed worst keys: rate [95 % CI] |")
    print("|---|---|---|---|---|")
    for (order, nb), h in hits.items():
        k = int(h.sum())
        lo, hi = clopper_pearson(k, total)
        confirmed = []
        for key in np.argsort(-h, kind="stable")[: args.top]:
            fresh = simulate(np.random.default_rng([args.seed, int(key), 1]), args.confirm,
                             args.n, args.data)
            c = _hits(fresh, order, nb, int(key), args.alpha)[0]
            clo, chi = clopper_pearson(c, args.confirm)
            confirmed.append(f"key {int(key)}: {c / args.confirm:.4f} [{clo:.4f}, {chi:.4f}]")
        print(f"| {order} | {nb} | {k / total:.4f} [{lo:.4f}, {hi:.4f}] | "
              f"{h.max() / args.reps:.3f} | {'; '.join(confirmed)} |", flush=True)
    print(f"content order: largest |log p ratio| between the numberings: {spread:.1e} "
          f"({time.monotonic() - t0:.0f} s)")


if __name__ == "__main__":
    main()
