"""Benchmark: simulated twin-hours saved by prefix-tree reuse.

    PYTHONPATH=src python benchmarks/bench_prefix_reuse.py [--config config/config.yaml]
        [--results results/<study>] [--skip-pulse]

Part 1 (counting, exact): for the study's hypothesis set (read from
results/<study>/design/hypotheses.parquet + twin_plan.json when present, else
built in-process from the config), every sequence gets m runs (m = the plan's
X_0 per sequence); twin-hours are counted for

- per_hypothesis: the paper's scheme as it reads (Cornish et al. 2026, Sec. 6):
  every hypothesis's action sequence a_1:t simulated from scratch for its own
  m runs: m * sum_h t_h;
- per_sequence: each distinct sequence once, from scratch: m * sum_seq len(seq);
- leaves: only the leaves of the prefix tree, from scratch (what a twin without
  state save/restore needs here: every node is a prefix of a leaf and a twin is
  non-anticipating): m * sum_leaf len(leaf);
- prefix_tree: each (prefix, X_0) node simulated once (a save/restore twin
  branching shared prefixes): m * n_nodes.

Part 2 (measured): the Pulse worker (which advertises save_restore) on the fake
engine of tests/fakes/pulse, through the real protocol runner, on the plan of
the recorded reference runs (3 patients x 5 sequences, S5 sharing hour 1 with
S1): engine-hours the worker actually advanced vs hours requested, read from
the worker's own shutdown report.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from twinfalsify import design  # noqa: E402
from twinfalsify.runs import plan as tp  # noqa: E402
from twinfalsify.schema import FEATURES, STAY_ID  # noqa: E402


def study_inputs(config: Path, results: Path | None) -> tuple[pd.DataFrame, tp.TwinPlan, str]:
    """(hypotheses, plan, where they came from)."""
    cfg = yaml.safe_load(config.read_text())
    results = results or ROOT / "results" / cfg["study"]
    hyp_path, plan_path = results / "design" / "hypotheses.parquet", results / "twin_plan.json"
    if hyp_path.exists() and plan_path.exists():
        plan = tp.TwinPlan.from_json(json.loads(plan_path.read_text()))
        return pd.read_parquet(hyp_path), plan, f"{results}"
    from twinfalsify.sources.synthetic import SyntheticWorld
    from twinfalsify.split import split_stays

    if cfg["source"]["kind"] != "synthetic":
        raise SystemExit(f"{config}: no results at {results} and source is not synthetic")
    world = SyntheticWorld.from_config(cfg["source"].get("synthetic"))
    traj = world.sample_observational(int(cfg["seed"]))
    d0, d = split_stays(traj, float(cfg["split"]["d0_fraction"]), int(cfg["seed"]))
    dcfg = cfg.get("design", {})
    outcomes = tuple(dcfg.get("outcomes", design.OUTCOMES))
    actions = design.fit_action_bins(d0)
    states = design.fit_state_bins(d0, outcomes)
    hyps, _ = design.build_hypotheses(
        d0, actions, states, outcomes=outcomes,
        quantiles=tuple(dcfg.get("quantiles", (0.2, 0.8))),
        min_support=int(dcfg.get("min_support", 10)),
        kinds=tuple(dcfg.get("kinds", ("causal", "manski"))),
    )  # fmt: skip
    runs = cfg["twin_runs"]
    plan = tp.plan_twin_runs(hyps, d[STAY_ID].unique(), runs.get("runs_per_sequence", 5000),
                             int(runs.get("n_shards", 4)), int(cfg["seed"]))
    return hyps, plan, f"built in-process from {config}"


def count_hours(hyps: pd.DataFrame, plan: tp.TwinPlan) -> dict[str, int]:
    m = len(plan.x0_stay_ids)
    seqs = {tuple(int(a) for a in s) for s in hyps["actions"].tolist()}
    leaves = [leaf for shard in plan.shards for leaf in shard]
    return {
        "per_hypothesis": m * int(sum(len(s) for s in hyps["actions"].tolist())),
        "per_sequence": m * sum(len(s) for s in seqs),
        "leaves": m * sum(len(tp.parse_node(n)) for n in leaves),
        "prefix_tree": m * len(plan.nodes),
    }


def pulse_fake_engine() -> dict[str, int]:
    """The recorded plan through the Pulse worker on the fake engine; engine-hours.

    The worker runs in-process (the fake engine matches recorded patients on
    their height, which is not a study feature the runner sends), fed in the
    runner's order (runs.runner.plan_groups: runs grouped by X_0, dose
    sequences depth-first), which is what lets it branch shared prefixes.
    """
    sys.path.insert(0, str(ROOT / "tests" / "fakes"))
    from twinfalsify.pulse.worker import PulseWorker
    from twinfalsify.runs.runner import plan_groups

    fixture = ROOT / "tests" / "fixtures" / "pulse-reference"
    patients = pd.read_csv(fixture / "patients.csv").set_index("patient_id")
    sequences = json.loads((fixture / "meta.json").read_text())["design"]["sequences"]
    x0s = []
    for pid in ("P1", "P2", "P3"):
        p = patients.loc[pid]
        row = dict.fromkeys(FEATURES, 0.0)
        row.update(age=float(p.age_yr), sex=1.0 if p.sex == "Female" else 0.0,
                   weight=float(p.weight_kg), HR=float(p.HR_baseline_per_min),
                   SysBP=float(p.SBP_baseline_mmHg), DiaBP=float(p.DBP_baseline_mmHg),
                   RR=float(p.RR_baseline_per_min), height_cm=float(p.height_cm))
        x0s.append(row)
    runs = [(i, np.asarray(seq, float)) for i in range(3) for seq in sequences.values()]
    doses = np.stack([d for _, d in runs])
    seeds = np.array([i for i, _ in runs], dtype=np.uint64)
    # every node of the prefix tree (per patient), counted from scratch
    nodes = {tuple(map(tuple, np.asarray(seq, float)[:s].tolist()))
             for seq in sequences.values() for s in range(1, len(seq) + 1)}
    with tempfile.TemporaryDirectory() as tmp:
        worker = PulseWorker(state_cache=Path(tmp) / "cache")
        statuses = []
        for group in plan_groups(seeds, doses):
            for j in group:
                i, seq = runs[int(j)]
                res = worker.simulate({"op": "simulate", "id": str(j), "x0": x0s[i],
                                       "doses": seq.tolist(), "hours": len(seq), "seed": i})
                statuses.append(res["status"])
        stats = worker.stats
        worker.close()
    return {
        "runs": len(runs),
        "runs_ok": statuses.count("ok"),
        "requested_hours": int(stats.requested_hours),
        "engine_hours": int(stats.simulated_hours),
        "from_scratch_every_node": 3 * sum(len(n) for n in nodes),
        "prefix_tree_minimum": 3 * len(nodes),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config" / "config.yaml")
    ap.add_argument("--results", type=Path, default=None)
    ap.add_argument("--skip-pulse", action="store_true")
    args = ap.parse_args()
    hyps, plan, origin = study_inputs(args.config, args.results)
    h = count_hours(hyps, plan)
    seqs = {tuple(s) for s in hyps["actions"].tolist()}
    leaves = sum(map(len, plan.shards))
    print(f"study: {origin}")
    print(f"  {len(hyps)} hypotheses ({hyps['kind'].value_counts().to_dict()}), "
          f"{len(seqs)} distinct action sequences, {len(plan.nodes)} prefix-tree nodes, "
          f"{leaves} leaves, m = {len(plan.x0_stay_ids)} X_0 per sequence")
    print("  simulated twin-hours:")
    for key, label in (("per_hypothesis", "paper: each hypothesis from scratch"),
                       ("per_sequence", "each distinct sequence from scratch"),
                       ("leaves", "leaves only (twin without save/restore)"),
                       ("prefix_tree", "prefix tree, each node once (save/restore)")):
        print(f"    {label:46s} {h[key]:>12,d}   x{h['per_hypothesis'] / h[key]:6.2f} "
              f"vs paper, x{h['per_sequence'] / h[key]:5.2f} vs per sequence")
    if not args.skip_pulse:
        p = pulse_fake_engine()
        print("Pulse worker (save_restore) on the fake engine, recorded plan "
              "(3 patients x 5 sequences):")
        print(f"  {p['runs']} leaf runs ({p['runs_ok']} ok); requested "
              f"{p['requested_hours']} hours (leaves), engine advanced {p['engine_hours']} "
              f"hours; every node from scratch would be {p['from_scratch_every_node']}, "
              f"prefix-tree minimum {p['prefix_tree_minimum']}")
        print(f"  engine-hours: x{p['from_scratch_every_node'] / p['engine_hours']:.2f} fewer "
              f"than every sequence from scratch, x{p['requested_hours'] / p['engine_hours']:.2f}"
              " fewer than the requested leaves")


if __name__ == "__main__":
    np.set_printoptions(linewidth=120)
    main()
