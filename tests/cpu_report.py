"""pytest plugin: the CPU time of every test, its own and its subprocesses' (Snakemake runs,
twins, rule jobs), written as a table sorted by CPU with ``--cpu-report FILE``.

Measured with ``getrusage``: the test process's own CPU plus that of every child it waited for
during the test (``RUSAGE_CHILDREN``), per phase (setup, call, teardown), so a shared fixture's
cost lands on the first test that asks for it. Under pytest-xdist every worker writes its own
part (``FILE.gw0``, ...) and the controller merges them into ``FILE``.
"""

from __future__ import annotations

import os
import resource
import time
from pathlib import Path

import pytest


def _cpu() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-report", metavar="FILE", default=None,
                     help="write every test's CPU seconds (its own and its subprocesses') "
                          "and wall seconds to FILE, most CPU first")  # fmt: skip


class CpuReport:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.rows: list[tuple[str, str, float, float]] = []

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_setup(self, item):
        yield from self._measure(item, "setup")

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_call(self, item):
        yield from self._measure(item, "call")

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_teardown(self, item):
        yield from self._measure(item, "teardown")

    def _measure(self, item, phase: str):
        c0, t0 = _cpu(), time.monotonic()
        yield
        self.rows.append((item.nodeid, phase, _cpu() - c0, time.monotonic() - t0))

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        worker = os.environ.get("PYTEST_XDIST_WORKER")
        part = self.path.with_name(f"{self.path.name}.{worker}") if worker else None
        lines = [f"{cpu:.2f}\t{wall:.2f}\t{phase}\t{nodeid}" for nodeid, phase, cpu, wall
                 in self.rows]  # fmt: skip
        if part is not None:
            part.write_text("\n".join(lines) + "\n")
            return
        # the controller (or a run without workers): merge the parts, sort, write the table
        for p in sorted(self.path.parent.glob(f"{self.path.name}.gw*")):
            lines += [ln for ln in p.read_text().splitlines() if ln]
            p.unlink()
        rows = sorted((ln.split("\t") for ln in lines), key=lambda r: -float(r[0]))
        total_cpu = sum(float(r[0]) for r in rows)
        header = f"# cpu_s\twall_s\tphase\ttest   (sum of CPU: {total_cpu:.0f} s)\n"
        self.path.write_text(header + "\n".join("\t".join(r) for r in rows) + "\n")


def pytest_configure(config: pytest.Config) -> None:
    path = config.getoption("--cpu-report")
    if path:
        config.pluginmanager.register(CpuReport(Path(path).resolve()), "cpu_report_plugin")
