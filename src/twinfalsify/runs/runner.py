"""Protocol client: run a twin subprocess pool over the JSON Lines protocol (v1).

``simulate_via_protocol`` starts ``workers`` copies of a twin command, streams
one ``simulate`` request at a time to each, enforces a per-run timeout,
restarts a worker that dies or hangs, retries the run a bounded number of
times, validates every answer, and returns one status per requested run:
``ok``, ``init_failed``, ``irreversible`` (reported by the twin), ``timeout``
(no answer in time after every attempt) or ``error`` (the twin said so, the
worker kept dying, or the answer broke the protocol). No run is ever dropped.

Concurrency: one thread per worker, each owning one subprocess and blocking on
its pipes (a reader thread per pipe turns stdout into a queue so that waits can
time out), so N workers keep N cores busy with the GIL idle. Runs are grouped
by seed (one seed = one X_0 draw) and each group goes to one worker, ordered
lexicographically by dose sequence, so a twin with state save/restore sees
shared dose prefixes consecutively and can branch them.

Batching: a twin whose hello advertises ``capabilities.batch`` > 1 gets
``simulate_batch`` messages of up to min(batch, ``batch_size``) runs, taken
in the same order (whole seed groups, dose order inside each), so a fast
vectorised twin is not throttled by one round trip per run. The time limit
of a batch is ``timeout_s`` x its length; if the worker dies, hangs or
answers garbage during a batch, it is restarted and the batch's runs are
retried one by one with plain ``simulate`` requests, so every run still gets
its own status and message exactly as without batching. Once a run was ok, the
next batch is sent before the previous answer is read (two in flight at most,
``runs.worker.BATCHES_IN_FLIGHT``): the twin computes while this process encodes,
checks and records, instead of each waiting for the other.

The worker processes and the pool they share are ``runs.worker``'s. The protocol is
described in docs/reference/twin-protocol.md.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from twinfalsify import schema
from twinfalsify.runs.worker import (
    DEFAULT_BATCH_SIZE,
    DEFAULT_FAIL_FAST_RUNS,
    DEFAULT_MAX_RESTARTS,
    SHUTDOWN_GRACE_S,
    WorkerPool,
    resolve_command,
)
from twinfalsify.schema import FEATURES, ContractError
from twinfalsify.twins.base import SimResult, empty_features

PROGRESS_INTERVAL_S = 5.0  # at most one progress line per interval


def format_duration(seconds: float) -> str:
    """``1h02m03s`` / ``2m03s`` for a number of seconds; ``?`` when it is not finite."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s"


def _validate_inputs(
    x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray, features: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Check shapes and values; return (x0 values, doses, seeds, hours per run)."""
    unknown = [f for f in features if f not in schema.FEATURE_BY_NAME]
    if unknown:
        raise ContractError(f"features: unknown feature name(s) {', '.join(unknown)}")
    if not isinstance(x0, pd.DataFrame):
        raise ContractError(f"x0 must be a pandas DataFrame, got {type(x0).__name__}")
    schema.require_columns(x0, FEATURES, "x0")
    doses = np.asarray(doses, dtype=float)
    n = len(x0)
    if doses.ndim != 3 or doses.shape[0] != n or doses.shape[2] != 2 or doses.shape[1] < 1:
        raise ContractError(
            f"doses must have shape (n={n}, t>=1, 2) (iv_fluid mL/h, vasopressor ug/kg/min); "
            f"got {doses.shape}"
        )
    seeds = np.asarray(seeds)
    if seeds.shape != (n,) or (n and not np.issubdtype(seeds.dtype, np.integer)):
        raise ContractError(f"seeds must be an integer array of shape ({n},); got {seeds.shape} "
                            f"{seeds.dtype}")
    if n and np.issubdtype(seeds.dtype, np.signedinteger) and (seeds < 0).any():
        raise ContractError("seeds must be >= 0 (uint64)")
    values = np.empty((n, len(FEATURES)))
    for j, col in enumerate(FEATURES):
        if not pd.api.types.is_numeric_dtype(x0[col]):
            raise ContractError(f"x0: column {col} is not numeric (dtype {x0[col].dtype})")
        v = x0[col].to_numpy(dtype=float)
        bad = ~np.isfinite(v)
        if bad.any():
            raise ContractError(
                f"x0: column {col} has {int(bad.sum())} non-finite value(s), "
                f"e.g. at row {int(np.flatnonzero(bad)[0])}"
            )
        values[:, j] = v
    # A run may be shorter than t: trailing all-NaN hours are not simulated
    # (lets one pool serve action sequences of different lengths).
    t = doses.shape[1]
    finite = np.isfinite(doses).all(axis=2)
    all_nan = np.isnan(doses).all(axis=2)
    hours = np.cumprod(finite, axis=1).sum(axis=1)
    in_run = np.arange(t)[None, :] < hours[:, None]
    bad = np.flatnonzero(~(in_run | all_nan).all(axis=1))
    if bad.size:
        raise ContractError(
            f"doses: run {int(bad[0])} has non-finite doses before its last hour "
            "(only trailing all-NaN hours are allowed, meaning a shorter run)"
        )
    if (hours < 1).any():
        raise ContractError(f"doses: run {int(np.flatnonzero(hours < 1)[0])} has no hours")
    neg = np.argwhere(np.nan_to_num(doses) < 0)
    if neg.size:
        i, h, k = neg[0]
        raise ContractError(
            f"doses: run {i} hour {h + 1} has a negative {schema.DOSES[k]} dose {doses[i, h, k]:g}"
        )
    return values, doses, seeds, hours


def plan_groups(seeds: np.ndarray, doses: np.ndarray) -> list[np.ndarray]:
    """Group run indices by seed; order each group by dose sequence.

    Lexicographic order of the flattened dose sequences puts runs sharing a
    dose prefix next to each other (a depth-first walk of the prefix tree).
    Larger groups come first so that the pool's tail is short.
    """
    n = len(seeds)
    if n == 0:
        return []
    flat = np.nan_to_num(doses.reshape(n, -1), nan=-1.0)  # shorter runs first
    keys = tuple(flat[:, j] for j in reversed(range(flat.shape[1]))) + (seeds,)
    order = np.lexsort(keys)  # np.lexsort: the LAST key is the primary one
    s = seeds[order]
    cuts = np.flatnonzero(s[1:] != s[:-1]) + 1
    groups = np.split(order, cuts)
    groups.sort(key=len, reverse=True)  # stable: ties stay in seed order
    return groups


def simulate_via_protocol(
    command: Sequence[str],
    x0: pd.DataFrame,
    doses: np.ndarray,
    seeds: np.ndarray,
    *,
    workers: int = 1,
    timeout_s: float = 600.0,
    retries: int = 2,
    progress: bool = True,
    env: Mapping[str, str] | None = None,
    features: Sequence[str] = FEATURES,
    batch_size: int = DEFAULT_BATCH_SIZE,
    fail_fast_runs: int = DEFAULT_FAIL_FAST_RUNS,
    max_restarts: int = DEFAULT_MAX_RESTARTS,
    continue_while: Sequence[list] | None = None,
    check_range: bool = False,
    hello_out: dict | None = None,
    stats_out: dict | None = None,
) -> SimResult:
    """Simulate n runs with a protocol twin; return a SimResult in input order.

    x0: n rows with every schema.FEATURES column (all are sent). doses:
    (n, t, 2), IV fluid mL/h and vasopressor ug/kg/min during hours 1..t; a
    run may end early with trailing all-NaN hours. seeds: (n,) non-negative
    integers (uint64). env: variables added to (overriding) the current
    environment of the worker processes.

    Every run gets a status: the twin's (ok / init_failed / irreversible /
    error), "timeout" when every attempt exceeded ``timeout_s`` (the worker
    is killed and restarted between attempts), "error" when the worker died on
    every attempt (message: exit code and stderr tail) or the answer broke the
    protocol (message names the problem; not retried). Hours completed before
    a failure are kept; NaN after. Raises FileNotFoundError for a command that
    does not exist and ContractError for a twin whose hello is unusable.

    batch_size: most runs per simulate_batch message, used only when the
    twin's hello advertises ``capabilities.batch`` > 1 (then a message holds
    min(batch, batch_size) runs; 1 = never batch). Results do not depend on it.

    Circuit breaker (ContractError naming the command, the reason and the first failed
    run's status and message): the first ``fail_fast_runs`` recorded runs all failed, or
    workers had to be restarted more than ``max_restarts`` times before any run was ok;
    0 turns a check off. After the first ok run neither check acts. Until then each X_0
    (seed) gets one run before any gets a second, so the first ``fail_fast_runs`` runs
    come from as many distinct X_0 as there are (up to that number): one patient the twin
    cannot simulate never stops the shard; its runs are recorded as failed.

    check_range: count a run answered ``ok`` with a value outside the trajectory contract's
    range (``schema.mark_implausible``) as ``implausible``, a failure, in the progress line
    and for the breaker, as it is when a study stores the runs (``runs.plan.plausible``,
    which marks the stored status; the SimResult returned here is the twin's answer).
    ``ProtocolTwin``, what a study uses, turns it on. hello_out: a dict this call fills
    with the ``name`` and ``version`` of the first worker's hello (recorded with the runs).
    stats_out: a dict this call fills with its worker trouble (``WorkerPool.worker_stats``:
    restarts, crashes, hangs, protocol_breaks), also when it raises.

    Each worker gets TMPDIR = a folder of this call, removed when it returns, so
    temporary files of workers that had to be killed do not outlive it.

    continue_while: per run, the box paths of ``runs.truncation`` (send only to a twin
    whose hello advertises ``capabilities.truncate``): a run may come back truncated,
    status ok with NaN after its last needed hour.
    """
    for key, value in (("fail_fast_runs", fail_fast_runs), ("max_restarts", max_restarts)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
            raise ContractError(f"{key} must be an integer >= 0, got {value!r}")
    if workers < 1:
        raise ContractError(f"workers must be >= 1, got {workers}")
    if retries < 0:
        raise ContractError(f"retries must be >= 0, got {retries}")
    if not timeout_s > 0:
        raise ContractError(f"timeout_s must be > 0, got {timeout_s}")
    if isinstance(batch_size, bool) or not isinstance(batch_size, int | np.integer) \
            or batch_size < 1:
        raise ContractError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    full_env = {**os.environ, **{str(k): str(v) for k, v in env.items()}} if env else None
    cmd = resolve_command(command, full_env)
    x0_values, doses, seeds, hours = _validate_inputs(x0, doses, seeds, features)
    n, t = doses.shape[:2]
    if n == 0:
        return SimResult(empty_features(0, t), np.full(0, "", dtype=object))

    if continue_while is not None and len(continue_while) != n:
        raise ContractError(f"continue_while holds {len(continue_while)} runs, expected {n}")
    # Workers killed on a timeout or a refused hello cannot clean up after themselves (the
    # Pulse worker keeps its prefix states in a temporary folder): their TMPDIR is ours.
    base_env = full_env if full_env is not None else os.environ
    scratch = tempfile.mkdtemp(prefix="twinfalsify-workers-", dir=base_env.get("TMPDIR"))
    full_env = {**base_env, "TMPDIR": scratch}
    pool = WorkerPool(cmd, full_env, x0_values, doses, seeds, hours, timeout_s, retries, features,
                 int(batch_size), int(fail_fast_runs), int(max_restarts), continue_while,
                 bool(check_range), hello_out)
    groups = plan_groups(seeds, doses)
    pool.tasks.extend(groups)
    n_threads = min(workers, len(groups))
    threads = [
        threading.Thread(target=pool.thread_main, args=(slot,), name=f"twin-worker-{slot}")
        for slot in range(n_threads)
    ]
    start = time.monotonic()
    last_report = start
    finished = False
    restore_sigterm = _sigterm_as_exit()
    try:
        for th in threads:
            th.start()
        for th in threads:
            while th.is_alive():
                th.join(timeout=0.25)
                now = time.monotonic()
                if progress and now - last_report >= PROGRESS_INTERVAL_S:
                    _report(pool, n, now - start)
                    last_report = now
        finished = True
    finally:
        if not finished:  # interrupted: unblock the threads by killing workers
            pool.stop.set()
            pool.kill_all()
            for th in threads:
                th.join(timeout=SHUTDOWN_GRACE_S + 1)
            pool.kill_all()  # a worker a thread started while we were stopping
        restore_sigterm()
        shutil.rmtree(scratch, ignore_errors=True)
        if stats_out is not None:
            stats_out.update(pool.worker_stats())
    if pool.error is not None:
        raise pool.error
    missing = np.flatnonzero(pool.status == "")
    if missing.size:  # would be a bug in this module, never a silent drop
        raise RuntimeError(f"twin runner lost {missing.size} run(s), e.g. run {missing[0]}")
    if progress:
        _report(pool, n, time.monotonic() - start, final=True)
    return SimResult(pool.features, pool.status, pool.message, pool.clamped)


def _sigterm_as_exit() -> Callable[[], None]:
    """While the pool runs, turn SIGTERM (Snakemake cancelling a job) into SystemExit.

    Workers live in their own process groups (so a timeout can kill a twin's
    children), hence a SIGTERM to the job's group does not reach them; with
    the default handler Python would die without killing them. Only replaces
    the default handler, only in the main thread; returns the restorer.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return lambda: None

    def handler(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _report(pool: WorkerPool, total: int, elapsed: float, final: bool = False) -> None:
    with pool.lock:
        counts = dict(pool.counts)
    done = sum(counts.values())
    failures = ", ".join(
        f"{s} {counts[s]}" for s in schema.TWIN_STATUSES if s != "ok" and counts.get(s)
    ) or "none"
    stats = pool.worker_stats()
    if stats["restarts"]:
        failures += (f" | worker restarts: {stats['restarts']} (crashes {stats['crashes']}, "
                     f"hangs {stats['hangs']}, malformed answers {stats['protocol_breaks']})")
    rate = done / elapsed if elapsed > 0 else float("nan")
    eta = (total - done) / rate if rate and rate > 0 else float("inf")
    line = (
        f"[twin] {done}/{total} runs ({100 * done / total:.1f}%) | failures: {failures} | "
        f"{rate:.2f} runs/s | "
        + (f"took {format_duration(elapsed)}" if final else f"ETA {format_duration(eta)}")
    )
    print(line, file=sys.stderr, flush=True)

