"""Twin-hours and rejections: fixed scheme vs adaptive (sequential) scheme on a study config.

    PYTHONPATH=src python benchmarks/bench_adaptive.py [--config config/config.yaml]
        [--batch-sizes 50 100 250 500] [--twins oracle biased fitted] [--curtail 0.01]
        [--combine union|product]
    PYTHONPATH=src python benchmarks/bench_adaptive.py --config config/test.yaml \
        --calibrate 20 --bias-levels 0 5 10 25 --batch-sizes 25

The second form is a small calibration: R replicate worlds (seeds seed + r), the oracle
(bias 0) and twins biased by HR + level; it prints the family-wise error (fraction of
replicates with any rejection of the oracle), the power (rejections per replicate and the
fraction of the fixed scheme's rejections kept) and the twin-hours ratio.

Builds the study in-process exactly as the workflow does (source -> split -> design ->
observational side -> twin plan -> every twin run of the plan, builtin twins), then
reveals the twin runs batch by batch (``inference.sequential.adaptive_test``). Twin-hours
are counted with prefix reuse for both schemes (node a_1:s = one simulated hour per run);
the fixed scheme simulates every node for the whole budget. Rejections: the fixed scheme
with the config's methods (and betting) after Holm, the adaptive scheme after Holm on the
anytime-valid p-values at the stopping times.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from twinfalsify import bounds, design
from twinfalsify.bounds import hypothesis_paths
from twinfalsify.falsify import adaptive_test, make_methods, run_tests
from twinfalsify.inference.sequential import node_runs
from twinfalsify.runs import plan as tp
from twinfalsify.runs.adaptive import shard_hypotheses
from twinfalsify.runs.registry import make_twin
from twinfalsify.schema import FEATURES, STAY_ID, TIME, to_array
from twinfalsify.sources.synthetic import generate
from twinfalsify.split import split_stays


@dataclass
class Study:
    hyps: pd.DataFrame
    obs: bounds.ObservationalSide
    states: design.StateBins
    actions: design.ActionBins
    plan: tp.TwinPlan
    x0: pd.DataFrame
    ctx: dict


def build(cfg: dict, seed: int, order_seed: int | None = None,
          renumber: int | None = None) -> Study:
    """The workflow's stages in-process for a synthetic study config.

    ``order_seed``: the seed keying the data order and the twin's X_0 draw (default ``seed``,
    as the workflow); ``renumber``: give D's stays new ids, a random bijection seeded by it
    (the same data, another numbering: D0 and the hypotheses unchanged).
    """
    if cfg["source"]["kind"] != "synthetic":
        sys.exit("bench_adaptive: only the synthetic source is supported in-process")
    traj = generate(cfg["source"].get("synthetic"), seed=seed)
    d0, d = split_stays(traj, float(cfg["split"]["d0_fraction"]), seed)
    actions = design.fit_action_bins(d0)
    states = design.fit_state_bins(d0)
    dc = cfg["design"]
    hyps, _ = design.build_hypotheses(
        d0, actions, states, quantiles=tuple(dc.get("quantiles", (0.2, 0.8))),
        min_support=int(dc.get("min_support", 10)),
        kinds=tuple(dc.get("kinds", ("causal", "manski"))),
    )
    if renumber is not None:
        old = d[STAY_ID].unique()
        new = np.random.default_rng(renumber).choice(10**8, len(old), replace=False) + 1
        d = d.assign(**{STAY_ID: d[STAY_ID].map(dict(zip(old, new, strict=True)))})
        d = d.sort_values([STAY_ID, TIME]).reset_index(drop=True)
    oseed = seed if order_seed is None else int(order_seed)
    obs = bounds.observational_side(
        hyps, to_array(d, FEATURES), design.action_codes(d, actions), states, order_seed=oseed
    )
    runs_cfg = cfg["twin_runs"]
    ids = d[STAY_ID].unique()
    plan = tp.plan_twin_runs(hyps, ids, runs_cfg.get("runs_per_sequence", 5000),
                             int(runs_cfg.get("n_shards", 4)), oseed,
                             x0=tp.x0_frame(d, ids.tolist())[list(FEATURES)].to_numpy(float))
    tmp = Path(tempfile.mkdtemp())
    d0.to_parquet(tmp / "d0.parquet")
    return Study(hyps, obs, states, actions, plan, tp.x0_frame(d, plan.x0_stay_ids),
                 {"source": cfg["source"], "d0": str(tmp / "d0.parquet")})


def in_process(spec: dict) -> dict:
    """The twin spec without its protocol keys: builtin twins run in-process here (same
    outputs as served over the protocol, which the workflow tests check)."""
    return {k: v for k, v in spec.items()
            if k not in ("protocol", "workers", "timeout_s", "retries")}


def curtailed(hyps, st, nodes, bs, alpha, seed, shard_of, curtail, fixed_sets,
              combine: str = "union") -> dict:
    """Opt-in curtailment at each epsilon: twin-hours ratio and fixed betting rejections kept."""
    out = {}
    ids = hyps["hyp_id"].to_numpy()
    for eps in curtail:
        o = adaptive_test(hyps, st.obs, nodes, st.states, batch_size=bs, alpha=alpha,
                          seed=seed, shards=shard_of, curtail=eps, combine=combine)
        ad = {(i, "lo") for i in ids[o.rejected_lo]} | {(i, "up") for i in ids[o.rejected_up]}
        out[f"ratio_curtail_{eps:g}"] = round(o.twin_hours_adaptive / o.twin_hours_fixed, 4)
        out[f"ratio_untruncated_curtail_{eps:g}"] = round(
            o.twin_hours_untruncated / o.twin_hours_fixed, 4)
        out[f"kept_betting_curtail_{eps:g}"] = len(ad & fixed_sets.get("betting", set()))
    return out


def compare(st: Study, name: str, spec: dict, batch_sizes: list[int], methods: dict,
            alpha: float, seed: int, curtail: tuple[float, ...] = (),
            combine: str = "union") -> list[dict]:
    """Fixed vs adaptive for one twin: one row per batch size."""
    twin = make_twin(name, in_process(spec), st.ctx)
    runs = pd.concat([tp.run_shard(twin, st.plan, k, st.x0, st.actions, log=io.StringIO())
                      for k in range(len(st.plan.shards))], ignore_index=True)
    nodes = tp.load_nodes(runs, st.plan, st.x0)
    hyps, m = st.hyps, len(st.plan.x0_stay_ids)
    # Holm-aware futility counts per shard, as the workflow's parallel shards do
    shard_of = np.zeros(len(hyps), np.int64)
    for k in range(len(st.plan.shards)):
        shard_of[shard_hypotheses(hyps, st.plan, k)] = k
    side = bounds.twin_runs(hyps, nodes, st.states)
    tv, nf = side, side.n_failed
    res = run_tests(hyps, bounds.hypothesis_samples(hyps, st.obs, tv), nf,
                    make_methods(methods, seed), alpha=alpha)
    fixed = res.groupby("method")["rejected"].sum().to_dict()
    fixed_sets = {
        k: set(zip(g.loc[g.rejected, "hyp_id"], g.loc[g.rejected, "side"], strict=True))
        for k, g in res.groupby("method")
    }
    rows = []
    for bs in batch_sizes:
        t1 = time.monotonic()
        out = adaptive_test(hyps, st.obs, nodes, st.states, batch_size=bs, alpha=alpha,
                            seed=seed, shards=shard_of, combine=combine)
        plain = adaptive_test(hyps, st.obs, nodes, st.states, batch_size=bs, alpha=alpha,
                              seed=seed, holm_aware=False, combine=combine)
        ids = hyps["hyp_id"].to_numpy()
        ad = {(i, "lo") for i in ids[out.rejected_lo]}
        ad |= {(i, "up") for i in ids[out.rejected_up]}
        rows.append({
            "twin": name, "batch_size": bs, "combine": combine,
            "hours_fixed": out.twin_hours_fixed, "hours_adaptive": out.twin_hours_adaptive,
            "hours_ratio": round(out.twin_hours_adaptive / max(out.twin_hours_fixed, 1), 4),
            "hours_paper": out.twin_hours_paper,
            "hours_ratio_paper": round(out.twin_hours_adaptive / max(out.twin_hours_paper, 1), 4),
            # levers, measured one at a time off the full procedure:
            # every revealed X_0 simulated per node (no B_0 skipping)
            "ratio_all_x0": round(out.twin_hours_all_x0 / max(out.twin_hours_fixed, 1), 4),
            # whole paths simulated (no depth truncation)
            "ratio_untruncated": round(out.twin_hours_untruncated
                                       / max(out.twin_hours_fixed, 1), 4),
            "rejected_adaptive": len(ad),
            **{f"rejected_fixed_{k}": int(v) for k, v in fixed.items()},
            **{f"kept_of_{k}": len(ad & s) for k, s in fixed_sets.items()},
            "decided_rejected": int((out.decision == 1).sum()),
            "decided_futile": int((out.decision == 2).sum()),
            "undecided_at_budget": int((out.decision == 0).sum()),
            # hours left if parameter sets still undecided at the budget had cost nothing:
            # how much of the bill the undecided ones drive
            "hours_without_undecided": int(node_runs(
                hypothesis_paths(hyps, nodes.index),
                np.where((out.decision == 0).any(axis=1), 0, out.runs_per_hypothesis),
                len(nodes.index)).sum()),
            "mean_stop_fraction": round(float(out.runs_per_hypothesis.mean()) / m, 4),
            # without Holm-aware futility (B_0 skipping kept), and the rejections it keeps
            "ratio_no_holm_aware": round(plain.twin_hours_adaptive
                                         / max(plain.twin_hours_fixed, 1), 4),
            "rejected_no_holm_aware": int(plain.rejected_lo.sum() + plain.rejected_up.sum()),
            **curtailed(hyps, st, nodes, bs, alpha, seed, shard_of, curtail, fixed_sets, combine),
            "seconds": round(time.monotonic() - t1, 1),
        })  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--batch-sizes", type=int, nargs="+", default=[50, 100, 250, 500])
    ap.add_argument("--twins", nargs="+", default=None)
    ap.add_argument("--calibrate", type=int, default=0, metavar="R")
    ap.add_argument("--bias-levels", type=float, nargs="+", default=[0.0, 5.0, 10.0, 25.0])
    ap.add_argument("--curtail", type=float, nargs="*", default=[],
                    help="also run opt-in curtailment at these epsilons")
    ap.add_argument("--combine", choices=["union"], default="union",
                    help="how the adaptive test combines the two capitals")
    args = ap.parse_args(argv)
    cfg = yaml.safe_load(Path(args.config).read_text())
    seed = int(cfg["seed"])
    alpha = float(cfg["testing"].get("alpha", 0.05))
    methods = {**cfg["testing"]["methods"], "betting": {}}
    rows = []
    if args.calibrate:
        for r in range(args.calibrate):
            st = build(cfg, seed + r)
            for level in args.bias_levels:
                spec = ({"kind": "oracle"} if level == 0
                        else {"kind": "biased", "shift": {"HR": level}})
                for row in compare(st, f"HR+{level:g}", spec, args.batch_sizes, methods,
                                   alpha, seed + r):
                    rows.append({"replicate": r, "bias": level, **row})
            print(json.dumps(rows[-1]), flush=True)
        t = pd.DataFrame(rows)
        t["any_rejection"] = t["rejected_adaptive"] > 0
        fixed_cols = [c for c in t if c.startswith("rejected_fixed_")]
        agg = t.groupby(["bias", "batch_size"]).agg(
            replicates=("replicate", "nunique"),
            fwer_or_any_rejection=("any_rejection", "mean"),
            rejections_adaptive=("rejected_adaptive", "mean"),
            **{c.replace("rejected_", "rejections_"): (c, "mean") for c in fixed_cols},
            hours_ratio=("hours_ratio", "mean"),
        )
        agg["any_rejection_fixed_betting"] = t.assign(
            a=t["rejected_fixed_betting"] > 0).groupby(["bias", "batch_size"])["a"].mean()
        print(agg.to_markdown())
        return
    t0 = time.monotonic()
    st = build(cfg, seed)
    print(f"study {cfg['study']}: {len(st.hyps)} parameter sets "
          f"({st.hyps.groupby('kind').size().to_dict()}), {len(st.plan.nodes)} nodes, "
          f"m = {len(st.plan.x0_stay_ids)}; twin-hours {st.plan.hours()} "
          f"(built in {time.monotonic() - t0:.0f} s)", flush=True)
    for name in args.twins or list(cfg["twins"]):
        for row in compare(st, name, cfg["twins"][name], args.batch_sizes, methods, alpha,
                           seed, tuple(args.curtail), args.combine):
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(pd.DataFrame(rows).to_markdown(index=False))


if __name__ == "__main__":
    main()
