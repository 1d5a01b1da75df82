"""Per-rule cost of a finished study, from the benchmark files Snakemake wrote for each job
(``results/<study>/benchmarks/**/*.tsv``: wall time ``s``, ``cpu_time`` of the job's process
tree, ``max_rss`` in MB).

Prints a markdown table: per rule, the jobs, summed and longest wall time, summed CPU time and
the largest peak memory of one job; then the totals. On a machine shared with other work,
wall time grows with the load while CPU time changes little: read the CPU column for the cost.
Snakemake samples a job's processes every few seconds, so CPU time of short-lived child
processes can be undercounted; ``/usr/bin/time -v snakemake ...`` gives the exact total.

Run:  python benchmarks/workflow_benchmarks.py results/<study>
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd

# benchmark file names (without shard / chunk numbers) that are not their rule's name
RULES = {"shard": "twin_shard", "adaptive_shard": "twin_shard_adaptive", "runs": "twin_runs",
         "chunk": "calibration_chunk", "report": "calibration_report"}


def rule_of(path: Path, root: Path) -> str:
    """Rule name from a benchmark path: its file name without shard / chunk numbers."""
    stem = re.sub(r"_\d+$", "", path.relative_to(root).with_suffix("").name)
    return RULES.get(stem, stem)


def collect(results: Path) -> pd.DataFrame:
    """One row per job: rule, path, s, cpu_time, max_rss."""
    root = results / "benchmarks"
    rows = []
    for p in sorted(root.rglob("*.tsv")):
        df = pd.read_csv(p, sep="\t")
        last = df.iloc[-1]
        rows.append({"rule": rule_of(p, root), "job": str(p.relative_to(root)),
                     "s": float(last["s"]), "cpu_time": float(last["cpu_time"]),
                     "max_rss": pd.to_numeric(last["max_rss"], errors="coerce")})
    return pd.DataFrame(rows)


def table(jobs: pd.DataFrame) -> str:
    g = jobs.groupby("rule").agg(jobs=("job", "size"), wall_sum=("s", "sum"),
                                 wall_max=("s", "max"), cpu_sum=("cpu_time", "sum"),
                                 rss_max=("max_rss", "max"))
    g = g.sort_values("cpu_sum", ascending=False)
    lines = ["| rule | jobs | wall, s (sum / longest job) | CPU, s | peak memory of a job, MB |",
             "|---|---:|---:|---:|---:|"]
    for rule, r in g.iterrows():
        lines.append(f"| `{rule}` | {int(r.jobs)} | {r.wall_sum:.0f} / {r.wall_max:.0f} | "
                     f"{r.cpu_sum:.1f} | {r.rss_max:.0f} |")
    lines.append(f"| **all** | {int(g.jobs.sum())} | {g.wall_sum.sum():.0f} | "
                 f"**{g.cpu_sum.sum():.0f}** | **{g.rss_max.max():.0f}** |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", type=Path, help="results/<study>")
    a = p.parse_args()
    jobs = collect(a.results)
    print(table(jobs))


if __name__ == "__main__":
    main()
