"""Betting p-values and the sample order: decisions across seeds, one order vs K orders.

    PYTHONPATH=src python benchmarks/bench_betting_order.py [--config config/config.yaml]
        [--seeds 5] [--bets star plugin mixture plugin:16 plugin:1:seed plugin:16:seed]

Builds the study in-process as ``bench_adaptive.build`` does, simulates every twin run of
the plan (builtin twins), then runs the betting test (``testing.failed_runs`` of the config,
Holm per kind) with each bets variant (``star``: target-recalculating bets in the data
order, the default; ``plugin``: plug-in bets in the same order; ``mixture``: the order-free
grid mixture; ``plugin:K``: terminal capitals averaged
over K data orders; a ``:seed`` suffix: seeded orders instead) for seeds 0..S-1 of the test
(the study itself, hence the data, is fixed). Prints per twin and variant: Holm rejections
per seed (min-max), causal / Manski under seed 0 (and, for comparison, Holm over both kinds
pooled in one family), decisions that flip across the seeds (a
(hypothesis, side) rejected under some seeds but not others), the seed-to-seed p ratio
max/min (median and 90th percentile over hypotheses with p < 1 under every seed) and the
wall time of one test run.

``--layouts R S``: instead, the default test (``betting: {}``) on the same data under R
renumberings of D's stays (a random bijection of the ids: D0, hypotheses and values
unchanged) and under S - 1 other order seeds (the seed keying the data order and the twin's
X_0 draw); prints per twin the Holm rejections and the decisions that differ from the
study as configured (a (hypothesis, side) rejected in one and not the other). A run's noise
stream is keyed by its position in the content-keyed X_0 list, so under a renumbering a
stochastic twin sees the same runs too.
"""

from __future__ import annotations

import argparse
import io
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from bench_adaptive import build, in_process  # noqa: E402

from twinfalsify import bounds  # noqa: E402
from twinfalsify.falsify import make_methods, run_tests  # noqa: E402
from twinfalsify.inference.multiple_testing import correct  # noqa: E402
from twinfalsify.runs import plan as tp  # noqa: E402
from twinfalsify.runs.registry import make_twin  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--bets", nargs="+",
                    default=["star", "plugin", "mixture", "plugin:16", "plugin:1:seed",
                             "plugin:16:seed"])
    ap.add_argument("--twins", nargs="+", default=None)
    ap.add_argument("--layouts", type=int, nargs=2, default=None, metavar=("R", "S"))
    args = ap.parse_args()
    cfg = yaml.safe_load(Path(args.config).read_text())
    seed = int(cfg["seed"])
    testing = cfg["testing"]
    if args.layouts:
        layouts(cfg, seed, testing, *args.layouts, args.twins)
        return
    st = build(cfg, seed)
    print("| twin | bets | rejections per seed | causal / Manski | pooled kinds | "
          "flipped decisions | p ratio median | p ratio 90th | s per run |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.twins or list(cfg["twins"]):
        samples, nf = _twin_samples(cfg, st, name)
        for k in args.bets:
            kind, orders, order = (k.split(":") + ["", ""])[:3]
            opts = {"bets": kind, **({"orders": int(orders)} if orders else {}),
                    **({"order": order} if order else {})}
            rej, ps, secs, by_kind, pooled = [], [], [], "", 0
            for s in range(args.seeds):
                t0 = time.monotonic()
                res = run_tests(st.hyps, samples, nf,
                                make_methods({"betting": opts}, s),
                                alpha=float(testing.get("alpha", 0.05)),
                                correction=testing.get("correction", "holm"),
                                failed_runs=testing.get("failed_runs", "conservative"))
                secs.append(time.monotonic() - t0)
                rej.append(res["rejected"].to_numpy())
                if s == 0:
                    cnt = res.groupby("kind")["rejected"].sum()
                    by_kind = f"{cnt.get('causal', 0)} / {cnt.get('manski', 0)}"
                    pooled = int(correct(res["p_value"].to_numpy(),
                                         float(testing.get("alpha", 0.05)),
                                         testing.get("correction", "holm")).sum())
                ps.append(res["p_value"].to_numpy())
            rej, ps = np.array(rej), np.array(ps)
            flips = int((rej.any(axis=0) & ~rej.all(axis=0)).sum())
            ok = ps.max(axis=0) < 1
            ratio = ps[:, ok].max(axis=0) / ps[:, ok].min(axis=0)
            med, q90 = ((f"{np.median(ratio):.3f}", f"{np.quantile(ratio, 0.9):.3f}")
                        if ok.any() else ("-", "-"))  # no p < 1 under every seed
            counts = rej.sum(axis=1)
            print(f"| {name} | {k} | {counts.min()}-{counts.max()} | {by_kind} | {pooled} | "
                  f"{flips} of {rej.shape[1]} | "
                  f"{med} | {q90} | {np.mean(secs):.1f} |", flush=True)


def _twin_samples(cfg: dict, st, name: str):
    """(hypothesis samples, failed runs) of twin ``name`` run in-process over the plan."""
    twin = make_twin(name, in_process(cfg["twins"][name]), st.ctx)
    runs = pd.concat([tp.run_shard(twin, st.plan, k, st.x0, st.actions, log=io.StringIO())
                      for k in range(len(st.plan.shards))], ignore_index=True)
    nodes = tp.load_nodes(runs, st.plan, st.x0)
    side = bounds.twin_runs(st.hyps, nodes, st.states)  # failed runs keep their places
    return bounds.hypothesis_samples(st.hyps, st.obs, side), side.n_failed


def _decisions(cfg: dict, st, name: str, testing: dict) -> tuple[pd.Series, float]:
    """Holm decisions of the default betting test (by (hyp_id, side)) and the test's seconds."""
    samples, nf = _twin_samples(cfg, st, name)
    t0 = time.monotonic()
    res = run_tests(st.hyps, samples, nf, make_methods({"betting": {}}, 0),
                    alpha=float(testing.get("alpha", 0.05)),
                    correction=testing.get("correction", "holm"),
                    failed_runs=testing.get("failed_runs", "conservative"))
    secs = time.monotonic() - t0
    key = res["hyp_id"].astype(str) + ":" + res["side"].astype(str)
    return pd.Series(res["rejected"].to_numpy(), index=key.to_numpy()), secs


def layouts(cfg: dict, seed: int, testing: dict, renumberings: int, seeds: int,
            twins: list[str] | None) -> None:
    """Decisions under renumberings of D and under other order seeds (module doc)."""
    names = twins or list(cfg["twins"])
    variants = [("as configured", {})]
    variants += [(f"renumbered {r}", {"renumber": 1000 + r}) for r in range(1, renumberings + 1)]
    variants += [(f"order seed {seed + s}", {"order_seed": seed + s}) for s in range(1, seeds)]
    print("| twin | layout | Holm rejections | decisions differing from as configured | "
          "s per test |")
    print("|---|---|---|---|---|")
    base: dict[str, pd.Series] = {}
    for label, kw in variants:
        st = build(cfg, seed, **kw)
        for name in names:
            dec, secs = _decisions(cfg, st, name, testing)
            ref = base.setdefault(name, dec)
            diff = int((dec.reindex(ref.index) != ref).sum())
            print(f"| {name} | {label} | {int(dec.sum())} | {diff} of {len(ref)} | {secs:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
