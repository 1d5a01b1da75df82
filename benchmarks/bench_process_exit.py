"""What a job's process pays at exit for the heap it leaves, with and without
``io.freeze_heap`` (``gc.freeze``), in the same run.

    PYTHONPATH=src python benchmarks/bench_process_exit.py [--runs 10]

Each run is a fresh interpreter that imports what a figure job imports (the library's figures
and summary: pandas, matplotlib, numba, pyarrow) and exits, either as it is or after
``freeze_heap()``, the two kinds alternating. Reported: the mean CPU time (user + system) of
a process of each kind and their ratio.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
IMPORTS = "import twinfalsify.figures, twinfalsify.summary, twinfalsify.io as io"
KINDS = {"plain exit": IMPORTS, "freeze_heap, then exit": f"{IMPORTS}; io.freeze_heap()"}


def cpu_of(code: str) -> float:
    """CPU seconds of one fresh interpreter running ``code``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    env = {**os.environ, "PYTHONPATH": str(SRC), "MPLBACKEND": "Agg"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="processes of each kind")
    args = parser.parse_args()
    cpu_of(IMPORTS)  # warm the file cache and numba's cache index
    times: dict[str, list[float]] = {k: [] for k in KINDS}
    for _ in range(args.runs):
        for kind, code in KINDS.items():
            times[kind].append(cpu_of(code))
    mean = {k: sum(v) / len(v) for k, v in times.items()}
    base = mean["plain exit"]
    print(f"| process | CPU s (mean of {args.runs}) | ratio to a plain exit |")
    print("|---|---|---|")
    for kind, m in mean.items():
        print(f"| {kind} | {m:.3f} | {m / base:.2f} |")


if __name__ == "__main__":
    main()
