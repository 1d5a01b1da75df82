"""How few twin-hours could keep the fixed betting test's rejections? Floors from idealised tests.

    PYTHONPATH=src python benchmarks/bench_hours_floor.py [--replicates 8] [--bias 1 2]

On calibration-harness replicates (config/calibration.yaml), each rejected (parameter set,
side) of the fixed betting test (Holm) is stopped at the first run where an idealised test
would reject it at its Holm level a = alpha/(2H_f - R + 1) (R = the family's fixed
rejections); every other parameter set costs nothing. Twin-hours are then counted as the
adaptive scheme counts them (prefix reuse, runs with X_0 in B_0 only; ``node_needs``).

Variants (columns): ``monotone`` any valid test monotone in the data (even if every entering
run sat at the worst value, it needs log(1/a) / -log(1 - m) runs); ``oracle`` knows Q_lo (the
observational point estimate) and bets the hindsight-optimal constant bet; ``oracle_Lstar``
the same at the observational bound L* at a* (what a real union test must use);
``oracle_half`` at level a/2 (the union split); ``oracle_L`` the best a union test could
do with perfect bets: the observational bound at its own Holm level a (not a*), level a/2,
the hindsight-optimal constant bet; ``oracle_cs`` with the CS plug-in bets;
``union`` L*, a*, CS bets; ``adaptive_union`` the union rule's rejected sets as run. Not
a proof beyond ``monotone``; a map of where the hours go (docs/explanation/sequential.md).

``--keep f`` (default 1) costs only the fraction f of each replicate's rejected sides that
stop earliest under each variant (a target that keeps >= 90 % of the fixed test's
rejections): the sides dropped are the most expensive alone, a heuristic for the cheapest
subset (prefix sharing is ignored when choosing it).
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from twinfalsify.bounds import hypothesis_paths, twin_runs_indexed
from twinfalsify.calibration import replicates as R
from twinfalsify.calibration.config import load_config
from twinfalsify.inference.capital import capital_bound
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.sequential import (
    cs_bets,
    family_sizes,
    node_needs,
)

C = 0.9


def _first_crossing(log_k: np.ndarray, level: float, pos: np.ndarray, m: int) -> int:
    hit = np.flatnonzero(log_k >= level)
    return int(pos[hit[0]]) + 1 if len(hit) else m


def stops(rep, base, runs, fixed: np.ndarray, alpha: float, variant: str,
          keep: float = 1.0) -> np.ndarray:
    """(H,) runs each parameter set needs under ``variant`` (0 for sets not rejected), the
    fraction ``keep`` of rejected sides that stop earliest only."""
    hyps = rep.hyps
    y_lo, y_up = hyps["y_lo"].to_numpy(float), hyps["y_up"].to_numpy(float)
    empty = Ragged(np.zeros(0), np.zeros(len(hyps) + 1, dtype=np.int64))
    hs = HypothesisSamples(y_lo, y_up, rep.obs.n, rep.obs.follow, empty)
    q = np.stack([(hs.q_lo_hat - y_lo) / (y_up - y_lo), (hs.q_up_hat - y_lo) / (y_up - y_lo)], 1)
    nf, kinds = family_sizes(hyps), hyps["kind"].to_numpy()
    m, v = runs.in_b0.shape[1], runs.values
    sides = []  # (runs needed, h)
    for h, col in zip(*np.nonzero(fixed), strict=True):
        a = alpha / (nf[h] - fixed[kinds == kinds[h]].sum() + 1)
        x = (np.clip(v.group(h), y_lo[h], y_up[h]) - y_lo[h]) / (y_up[h] - y_lo[h])
        pos = runs.run[v.offsets[h]:v.offsets[h + 1]]
        at = (base.l_star[h], base.u_star[h])[col] if variant in ("oracle_Lstar", "union") \
            else q[h, col]
        if variant == "oracle_L":  # the observational bound at level a (union: a/2 a side)
            side = (base.lo, base.up)[col].take(np.array([h]))
            at = float(capital_bound(side, np.array([np.log(2 / a)]), (+1, -1)[col], True, C)[0])
        z = (at - x) if col == 0 else (x - at)  # > 0: evidence against the null
        worst = at if col == 0 else 1 - at  # rescaled distance the worst value can move
        level = {"oracle_half": np.log(2 / a), "oracle_L": np.log(2 / a),
                 "union": np.log(2 / base.a_star[h])}.get(variant, np.log(1 / a))
        if variant == "monotone":
            need = int(np.ceil(level / -np.log1p(-min(worst, 1 - 1e-12)))) if worst > 0 else m + 1
            s = int(pos[need - 1]) + 1 if need <= len(pos) else m
        elif variant in ("oracle_cs", "union"):
            cap = C / (1 - at) if col == 0 else C / max(at, 1e-12)
            lam = np.minimum(cs_bets(x, np.array([0, len(x)]), np.array([base.delta0[h]])), cap)
            s = _first_crossing(np.cumsum(np.log1p(lam * z)), level, pos, m)
        else:
            cap = 1 / (1 - at) if col == 0 else 1 / max(at, 1e-12)
            lam = minimize_scalar(lambda b, z=z: -np.sum(np.log1p(b * z)), bounds=(0, 0.999 * cap),
                                  method="bounded").x
            s = _first_crossing(np.cumsum(np.log1p(lam * z)), level, pos, m)
        sides.append((s, h))
    out = np.zeros(len(hyps), np.int64)
    for s, h in sorted(sides)[: int(np.ceil(keep * len(sides)))]:
        out[h] = max(out[h], s)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/calibration.yaml")
    ap.add_argument("--replicates", type=int, default=8)
    ap.add_argument("--bias", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--keep", type=float, default=1.0,
                    help="cost only this fraction of the rejected sides, the earliest to stop")
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    variants = ("monotone", "oracle", "oracle_Lstar", "oracle_half", "oracle_L", "oracle_cs",
                "union")
    rows = []
    for r in range(args.replicates):
        rep = R.build_replicate(cfg, cfg.seed + r)
        base = R.adaptive_state(cfg, rep)
        for bias in args.bias:
            nodes = R.shifted_nodes(rep, bias, tuple(cfg.bias_features))
            res, _ = R.fixed_results(cfg, rep, bias)
            fixed = R._fixed_rejections(res, "betting", rep.hyps["hyp_id"].to_numpy())
            runs = twin_runs_indexed(rep.hyps, nodes, rep.states)
            paths = hypothesis_paths(rep.hyps, nodes.index)
            total = len(nodes.index) * nodes.x0.shape[0]

            def hours(per: np.ndarray) -> float:
                return node_needs(paths, per, runs.in_b0, len(nodes.index)).sum() / total  # noqa: B023

            row = {"replicate": r, "bias": bias, "fixed_rejections": int(fixed.sum())}
            for var in variants:
                row[var] = hours(stops(rep, base, runs, fixed, cfg.alpha, var, args.keep))
            o = R.run_adaptive(cfg, rep, nodes, base)
            kept = (np.stack([o.rejected_lo, o.rejected_up], 1) & fixed).any(1)
            row["adaptive_union"] = hours(np.where(kept, o.runs_per_hypothesis, 0))
            rows.append(row)
            print(row, flush=True)
    print(pd.DataFrame(rows).groupby("bias").mean().drop(columns="replicate").to_markdown())


if __name__ == "__main__":
    main()
