"""What failed twin runs cost the adaptive test: conservative vs drop, on a study config.

    PYTHONPATH=src python benchmarks/bench_failed_runs.py [--config config/config.yaml]
        [--twins oracle biased fitted] [--batch-size 25] [--curtail 0.05]

Builds the study in-process as ``bench_adaptive.py`` does, simulates every twin run of the
plan, then injects failures into the simulated nodes (a failed node fails every node below
it, as an engine that stops does):

- ``init``: 5 % of the X_0 fail before hour 1 (failures unrelated to the outcome);
- ``informative``: a run fails at the first hour whose HR exceeds the D0 90th percentile,
  with probability 0.5 (an engine that breaks on extreme physiology: the successful runs
  then understate the twin's HR).

and runs ``adaptive_test`` with ``failed_runs`` conservative and drop. Reported per twin and
failure scenario: twin-hours / fixed, Holm rejections, and (``none``) the same without
failures; with ``--fixed`` also the fixed scheme's betting test (Holm) in both modes, for
comparison (``inference.failures``: the maximum over k of the p-values). Conservative never
rejects more than drop on the same runs; what it costs in power and hours is what this
measures (docs/explanation/sequential.md, "Failed twin runs").
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_adaptive import build, in_process  # noqa: E402

from twinfalsify import bounds  # noqa: E402
from twinfalsify.bounds import TwinNodes  # noqa: E402
from twinfalsify.falsify import (  # noqa: E402
    adaptive_test,  # noqa: E402
    make_methods,
    run_tests,
)
from twinfalsify.runs import plan as tp  # noqa: E402
from twinfalsify.runs.adaptive import shard_hypotheses  # noqa: E402
from twinfalsify.runs.registry import make_twin  # noqa: E402
from twinfalsify.schema import FEATURES  # noqa: E402


def with_failures(nodes: TwinNodes, scenario: str, hr_cap: float, seed: int) -> TwinNodes:
    """``nodes`` with the scenario's failures: NaN at a failed node and every node below it."""
    if scenario == "none":
        return nodes
    rng = np.random.default_rng(seed)
    m = nodes.values.shape[1]
    hr = nodes.values[:, :, FEATURES.index("HR")]
    fails_here = {
        "init": np.broadcast_to(rng.random(m) < 0.05, hr.shape),
        "informative": (hr > hr_cap) & (rng.random(m) < 0.5)[None, :],
    }[scenario]
    failed = np.zeros(hr.shape, bool)
    for key in sorted(nodes.index, key=len):  # parents before children
        i = nodes.index[key]
        parent = failed[nodes.index[key[:-1]]] if len(key) > 1 else False
        failed[i] = parent | fails_here[i]
    values = nodes.values.copy()
    values[failed] = np.nan
    return TwinNodes(index=nodes.index, values=values, x0=nodes.x0)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--twins", nargs="+", default=None)
    ap.add_argument("--batch-size", type=int, default=25)
    ap.add_argument("--curtail", type=float, default=0.05)
    ap.add_argument("--fixed", action="store_true", help="also the fixed betting test")
    args = ap.parse_args(argv)
    cfg = yaml.safe_load(Path(args.config).read_text())
    seed = int(cfg.get("seed", 0))
    alpha = float(cfg.get("testing", {}).get("alpha", 0.05))
    st = build(cfg, seed)
    hr_cap = float(np.quantile(pd.read_parquet(st.ctx["d0"])["HR"].dropna(), 0.9))
    shard_of = np.zeros(len(st.hyps), np.int64)
    for k in range(len(st.plan.shards)):
        shard_of[shard_hypotheses(st.hyps, st.plan, k)] = k
    rows = []
    for name in args.twins or list(cfg["twins"]):
        twin = make_twin(name, in_process(cfg["twins"][name]), st.ctx)
        runs = pd.concat([tp.run_shard(twin, st.plan, k, st.x0, st.actions, log=io.StringIO())
                          for k in range(len(st.plan.shards))], ignore_index=True)
        clean = tp.load_nodes(runs, st.plan, st.x0)
        for scenario in ("none", "init", "informative"):
            nodes = with_failures(clean, scenario, hr_cap, seed)
            row = {"twin": name, "failures": scenario,
                   "failed_node_runs": round(float(np.isnan(nodes.values[:, :, 0]).mean()), 4)}
            if args.fixed:
                tv = bounds.twin_runs(st.hyps, nodes, st.states)
                nf = tv.n_failed
                samples = bounds.hypothesis_samples(st.hyps, st.obs, tv)
            for mode in ("drop", "conservative") if scenario != "none" else ("drop",):
                o = adaptive_test(st.hyps, st.obs, nodes, st.states, batch_size=args.batch_size,
                                  alpha=alpha, seed=seed, shards=shard_of, curtail=args.curtail,
                                  failed_runs=mode)
                row[f"hours_{mode}"] = round(o.twin_hours_adaptive / o.twin_hours_fixed, 4)
                row[f"rejected_{mode}"] = int(o.rejected_lo.sum() + o.rejected_up.sum())
                if args.fixed:
                    res = run_tests(st.hyps, samples, nf, make_methods({"betting": {}}, seed),
                                    alpha=alpha, failed_runs=mode)
                    row[f"fixed_rejected_{mode}"] = int(res["rejected"].sum())
            rows.append(row)
            print(row, flush=True)
    print(pd.DataFrame(rows).to_markdown(index=False))


if __name__ == "__main__":
    main()
