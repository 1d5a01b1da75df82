"""ProtocolTwin: the Twin interface (twins.base.Twin) backed by a subprocess command.

The command speaks the twin protocol v1 (docs/reference/twin-protocol.md); runs go
through ``runs.runner.simulate_via_protocol`` (worker pool, timeouts,
restarts, retries, one status per run). ``batch_size`` caps the runs per
``simulate_batch`` message for a twin that advertises batches.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.runs.protocol import ProtocolError, check_result
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.runs.worker import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_FAIL_FAST_RUNS,
    DEFAULT_MAX_RESTARTS,
    WorkerDied,
    WorkerTimeout,
    resolve_command,
    start_worker,
)
from twinfalsify.schema import FEATURES, ContractError
from twinfalsify.twins.base import SimResult


def probe_record(hours: int, seconds_each: list[float], status: str,
                 message: str) -> dict[str, Any]:
    """A hello's ``probe``: the timed runs (the last one ended ``status``) and the median
    of their wall times as ``seconds``."""
    return {"hours": int(hours), "runs": len(seconds_each),
            "seconds": float(np.median(seconds_each)),
            "seconds_each": [float(v) for v in seconds_each], "status": status,
            "message": message}


class ProtocolTwin:
    """A Twin (twins.base.Twin) backed by a subprocess speaking the protocol."""

    def __init__(
        self,
        name: str,
        command: Sequence[str],
        *,
        workers: int = 1,
        timeout_s: float = 600.0,
        retries: int = 2,
        env: Mapping[str, str] | None = None,
        progress: bool = True,
        batch_size: int = DEFAULT_BATCH_SIZE,
        fail_fast_runs: int = DEFAULT_FAIL_FAST_RUNS,
        max_restarts: int = DEFAULT_MAX_RESTARTS,
    ) -> None:
        self.name = name
        self.command = list(command)
        self.workers, self.timeout_s, self.retries = workers, timeout_s, retries
        self.env = dict(env) if env else None
        self.progress = progress
        self.batch_size = batch_size
        self.fail_fast_runs, self.max_restarts = fail_fast_runs, max_restarts
        self._truncates: bool | None = None
        self.last_hello: dict[str, Any] = {}  # name and version the twin last said hello with
        # worker trouble of the last simulate call (runs.worker.WorkerPool.worker_stats)
        self.last_workers: dict[str, int] = {}

    def hello(self, probe: dict[str, float] | None = None, hours: int = 1,
              runs: int = 1) -> dict[str, Any]:
        """Start one worker, return its (validated) hello answer, shut it down.

        probe: an X_0; the worker then also simulates it ``runs`` times (seeds 0, 1, ...)
        for ``hours`` hours without doses and the answer gets ``"probe": {"hours", "runs",
        "seconds", "seconds_each", "status", "message"}``: the wall time of each run
        (start-up excluded) and their median, a first estimate of the twin's seconds per
        simulated hour. A failed probe run ends the probe and is reported there, never
        raised.
        """
        full_env = {**os.environ, **self.env} if self.env else None
        cmd = resolve_command(self.command, full_env)
        try:
            worker = start_worker(cmd, full_env, self.timeout_s)
        except ContractError as exc:  # name the twin as the config does
            raise ContractError(f"twins.{self.name}: {exc}") from None
        try:
            hello = {k: v for k, v in worker.hello.items() if k != "declared_units"}
            if probe is not None:
                hello["probe"] = self._probe(worker, probe, hours, runs)
        finally:
            worker.close()
        return json.loads(json.dumps(hello))

    def _probe(self, worker: Any, x0: dict[str, float], hours: int,
               runs: int) -> dict[str, Any]:
        each: list[float] = []
        status, message = "ok", ""
        for k in range(max(int(runs), 1)):
            rid = f"probe.{k}"
            request = {"op": "simulate", "id": rid, "x0": {f: float(x0[f]) for f in FEATURES},
                       "doses": [[0.0, 0.0]] * hours, "hours": hours, "seed": k}
            start = time.monotonic()
            try:
                answer = worker.ask(request, self.timeout_s)
                status = check_result(answer, rid, hours, FEATURES,
                                      worker.hello["declared_units"], FEATURES).status
            except (WorkerDied, WorkerTimeout, ProtocolError) as exc:
                status = "timeout" if isinstance(exc, WorkerTimeout) else "error"
                message = str(exc) or f"no answer within {self.timeout_s:g} s"
            else:
                message = str(answer.get("message", "")) if status != "ok" else ""
            each.append(time.monotonic() - start)
            if status != "ok":
                break
        return probe_record(hours, each, status, message)

    @property
    def truncates(self) -> bool:
        """Whether the twin advertises ``capabilities.truncate`` (asked once)."""
        if self._truncates is None:
            self._truncates = bool(self.hello().get("capabilities", {}).get("truncate", False))
        return self._truncates

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray,
                 continue_while: list | None = None) -> SimResult:
        """``continue_while`` (per run, ``runs.truncation`` box paths) is sent only to a twin
        that advertises ``capabilities.truncate``; other twins simulate whole paths."""
        if continue_while is not None and not self.truncates:
            continue_while = None
        hello: dict[str, Any] = {}
        self.last_workers = {}
        try:
            res = simulate_via_protocol(
                self.command, x0, doses, seeds, workers=self.workers, timeout_s=self.timeout_s,
                retries=self.retries, progress=self.progress, env=self.env,
                batch_size=self.batch_size, fail_fast_runs=self.fail_fast_runs,
                max_restarts=self.max_restarts, continue_while=continue_while,
                check_range=True, hello_out=hello, stats_out=self.last_workers,
            )
        except ContractError as exc:  # name the twin as the config does
            raise ContractError(f"twins.{self.name}: {exc}") from None
        if hello:
            self.last_hello = hello
        return res
