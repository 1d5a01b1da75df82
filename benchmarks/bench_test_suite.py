"""Time the test suite: wall time, CPU time (the runner and every process it waited for:
Snakemake runs, twins, workers), the machine's load average while it ran, and the test counts
pytest reports.

    python benchmarks/bench_test_suite.py OUT.json [-- PYTEST ARGS...]
    python benchmarks/bench_test_suite.py --table A.json B.json ...

The first form runs ``python -m pytest -q`` (plus any arguments after ``--``) from the
repository root and writes one JSON record (pytest's output beside it, ``OUT.log``); the
second prints a Markdown table of records (a "before" and an "after" run of the same machine,
side by side).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_COUNT = re.compile(r"(\d+) (passed|failed|skipped|errors?|deselected|xfailed|xpassed)")


def _load_sampler(samples: list[float], stop: threading.Event, every: float = 5.0) -> None:
    while not stop.is_set():
        samples.append(os.getloadavg()[0])
        stop.wait(every)


def run_suite(pytest_args: list[str], log: Path | None = None) -> dict:
    """Run pytest once and measure it (children's CPU from ``getrusage``, so every descendant
    the runner waited for counts); pytest's output goes to ``log``."""
    samples: list[float] = []
    stop = threading.Event()
    sampler = threading.Thread(target=_load_sampler, args=(samples, stop), daemon=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_start = os.getloadavg()[0]
    t0 = time.monotonic()
    sampler.start()
    cmd = [sys.executable, "-m", "pytest", "-q", *pytest_args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.monotonic() - t0
    stop.set()
    if log is not None:
        log.write_text(proc.stdout + proc.stderr)
    sampler.join()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    counts = {k.rstrip("s") if k.startswith("error") else k: int(n)
              for n, k in _COUNT.findall(tail)}  # fmt: skip
    return {
        "command": " ".join(["python -m pytest -q", *pytest_args]),
        "returncode": proc.returncode,
        "wall_s": round(wall, 1),
        "cpu_user_s": round(after.ru_utime - before.ru_utime, 1),
        "cpu_system_s": round(after.ru_stime - before.ru_stime, 1),
        "cpu_s": round(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, 1),
        "load_start": round(load_start, 2),
        "load_mean": round(sum(samples) / len(samples), 2) if samples else None,
        "load_max": round(max(samples), 2) if samples else None,
        "counts": counts,
        "summary": tail,
        "cores": os.cpu_count(),
        "machine": f"{platform.machine()} {platform.system()}, Python {platform.python_version()}",
    }


def _mmss(seconds: float) -> str:
    m, s = divmod(round(seconds), 60)
    return f"{m} min {s:02d} s"


def table(records: list[tuple[str, dict]]) -> str:
    rows = ["| run | tests passed / skipped | wall | CPU | load average (start, mean, max) |",
            "|---|---|---|---|---|"]  # fmt: skip
    for name, r in records:
        c = r["counts"]
        rows.append(
            f"| {name} | {c.get('passed', 0)} / {c.get('skipped', 0)} | {_mmss(r['wall_s'])} | "
            f"{_mmss(r['cpu_s'])} | {r['load_start']}, {r['load_mean']}, {r['load_max']} |"
        )
    base = records[0][1]
    for name, r in records[1:]:
        rows.append(f"\n{name} / {records[0][0]}: wall {r['wall_s'] / base['wall_s']:.2f}x, "
                    f"CPU {r['cpu_s'] / base['cpu_s']:.2f}x")  # fmt: skip
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1 :]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="*", type=Path, help="JSON record to write (or, with "
                    "--table, records to tabulate)")  # fmt: skip
    ap.add_argument("--table", action="store_true", help="print the records as a table")
    args = ap.parse_args(argv)
    if args.table:
        print(table([(p.stem, json.loads(p.read_text())) for p in args.out]))
        return 0
    if len(args.out) != 1:
        ap.error("give one OUT.json to write")
    record = run_suite(extra, log=args.out[0].with_suffix(".log"))
    args.out[0].write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))
    return 0 if record["returncode"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
