"""Level of the betting test under outcome-dependent twin failures, failed runs in place.

    PYTHONPATH=src nice -n 10 python benchmarks/bench_failed_places.py [--reps 20000]
        [--n 200 1000] [--alpha 0.05]

One hypothesis per replicate at the null boundary: every trajectory of D follows, D's and
the twin's outcomes come from one law on [0, 1] (so Q_twin = Q_lo = Q_up), and twin run i
fails with a probability that depends on its own outcome x_i. ``testing.failed_runs:
conservative`` (each failed run's worst case at its place, ``inference.failures``) against
``drop``. Prints the rejection rate of H_lo (the side failures of high outcomes push towards
rejection) and of H_up at alpha, with exact (Clopper-Pearson, 95 %) intervals. The fast
version is ``tests/inference/test_failed_places.py::test_level_under_outcome_dependent_failures``.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_order_null import clopper_pearson  # noqa: E402

from twinfalsify.inference.betting import betting_test, default_tune_alpha  # noqa: E402
from twinfalsify.inference.failures import failure_pvalues  # noqa: E402
from twinfalsify.inference.samples import HypothesisSamples, Ragged  # noqa: E402

LAWS = {
    "Bernoulli(0.3)": lambda rng, size: (rng.random(size) < 0.3).astype(float),
    "Beta(2, 2)": lambda rng, size: rng.beta(2, 2, size),
}
FAILURES = {
    "fails iff x > Q (Q = 0.5; Beta: 0.6)": lambda x, law: (
        x > (0.5 if law.startswith("Bern") else 0.6)).astype(float),
    "P(fail given x) = x / 2": lambda x, law: 0.5 * x,
}


def replicates(rng: np.random.Generator, reps: int, n: int, law: str, fail
               ) -> tuple[HypothesisSamples, np.ndarray]:
    draw = LAWS[law]
    obs, runs = draw(rng, (reps, n)), draw(rng, (reps, n))
    failed = rng.random((reps, n)) < fail(runs, law)
    ok = [np.flatnonzero(~f) for f in failed]
    s = HypothesisSamples(
        y_lo=np.zeros(reps), y_up=np.ones(reps), n=np.full(reps, n),
        follow=Ragged.from_groups(list(obs)),
        twin=Ragged.from_groups([x[o] for x, o in zip(runs, ok, strict=True)]),
        twin_run=Ragged.from_groups(ok),
        failed_run=Ragged.from_groups([np.flatnonzero(f) for f in failed]),
    )  # fmt: skip
    return s, failed.sum(axis=1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=20000)
    ap.add_argument("--n", type=int, nargs="+", default=[200, 1000])
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--chunk", type=int, default=2000)
    args = ap.parse_args()
    method = partial(betting_test, tune_alpha=default_tune_alpha(1))  # one hypothesis each
    print("| n | outcomes | failures | failed share | mode | H_lo rejected [95 % CI] | "
          "H_up rejected [95 % CI] | s |")
    print("|---|---|---|---|---|---|---|---|")
    for n in args.n:
        for law in LAWS:
            for fname, fail in FAILURES.items():
                t0 = time.monotonic()
                hits = {m: np.zeros(2, np.int64) for m in ("conservative", "drop")}
                share = 0.0
                rng = np.random.default_rng([n, len(law), len(fname)])
                for start in range(0, args.reps, args.chunk):
                    k = min(args.chunk, args.reps - start)
                    s, f = replicates(rng, k, n, law, fail)
                    share += f.sum() / (k * n) * k / args.reps
                    for mode in hits:
                        p = failure_pvalues(method, s, f, mode)
                        hits[mode] += [int((p[0] <= args.alpha).sum()),
                                       int((p[1] <= args.alpha).sum())]
                secs = time.monotonic() - t0
                for mode, (lo_k, up_k) in hits.items():
                    cells = []
                    for kk in (lo_k, up_k):
                        a, b = clopper_pearson(int(kk), args.reps)
                        cells.append(f"{kk / args.reps:.4f} [{a:.4f}, {b:.4f}]")
                    print(f"| {n} | {law} | {fname} | {share:.2f} | {mode} | {cells[0]} | "
                          f"{cells[1]} | {secs:.0f} |", flush=True)


if __name__ == "__main__":
    main()
