"""ProtocolTwin: the Twin interface (twins.base.Twin) backed by a subprocess command.

The command speaks the twin protocol v1 (docs/reference/twin-protocol.md); runs go
through ``runs.runner.simulate_via_protocol`` (worker pool, timeouts,
restarts, retries, one status per run). ``batch_size`` caps the runs per
``simulate_batch`` message for a twin that advertises batches.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.runs.runner import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_FAIL_FAST_RUNS,
    DEFAULT_MAX_RESTARTS,
    _Pool,
    resolve_command,
    simulate_via_protocol,
)
from twinfalsify.schema import FEATURES, ContractError
from twinfalsify.twins.base import SimResult


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

    def hello(self) -> dict[str, Any]:
        """Start one worker, return its (validated) hello answer, shut it down."""
        full_env = {**os.environ, **self.env} if self.env else None
        cmd = resolve_command(self.command, full_env)
        pool = _Pool(cmd, full_env, np.empty((0, len(FEATURES))), np.empty((0, 1, 2)),
                     np.empty(0, dtype=np.uint64), np.ones(1, dtype=int), self.timeout_s,
                     self.retries, FEATURES)
        worker = pool._start_worker(0)
        try:
            hello = {k: v for k, v in worker.hello.items() if k != "declared_units"}
        finally:
            pool.workers.pop(0, None)
            worker.close()
        return json.loads(json.dumps(hello))

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
        try:
            res = simulate_via_protocol(
                self.command, x0, doses, seeds, workers=self.workers, timeout_s=self.timeout_s,
                retries=self.retries, progress=self.progress, env=self.env,
                batch_size=self.batch_size, fail_fast_runs=self.fail_fast_runs,
                max_restarts=self.max_restarts, continue_while=continue_while,
                check_range=True, hello_out=hello,
            )
        except ContractError as exc:  # name the twin as the config does
            raise ContractError(f"twins.{self.name}: {exc}") from None
        if hello:
            self.last_hello = hello
        return res
