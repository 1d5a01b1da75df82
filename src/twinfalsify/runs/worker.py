"""The twin's worker processes: one subprocess speaking the protocol, and the pool of them.

``Worker`` is one twin subprocess (its own process group) with timed line reads and
writes; ``WorkerPool`` is the state the worker threads of one
``runs.runner.simulate_via_protocol`` call share: the queue of seed groups, a worker per
slot (started, checked by its hello, restarted after a crash or hang), the runs' retries,
batches and statuses, and the circuit breaker. ``start_worker`` starts one worker and
checks its hello outside any call (``ProtocolTwin.hello``); ``runs.check`` drives
``Worker`` directly.

The protocol is described in docs/reference/twin-protocol.md.
"""

from __future__ import annotations

import os
import queue
import select
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from twinfalsify import schema
from twinfalsify.runs.protocol import (
    ARRAYS,
    CheckedResult,
    ProtocolError,
    check_array_results,
    check_hello,
    check_result,
    check_results,
    decode,
    encode,
)
from twinfalsify.schema import FEATURES, ContractError, mark_implausible
from twinfalsify.twins.base import empty_features

STARTUP_TIMEOUT_S = 60.0  # a worker's hello may take max(timeout_s, this): start-up
# (interpreter, engine libraries) is not simulation and must not eat the run's limit
SHUTDOWN_GRACE_S = 5.0  # time a worker gets to answer "shutdown" and exit
STDERR_TAIL_LINES = 20  # stderr lines kept per worker for error messages
STDERR_LINE_CHARS = 4000  # and at most this much of each
PIPE_POLL_S = 0.2  # the pipe threads and waits wake this often (stop flags, twin exit)
EXIT_DRAIN_S = 1.0  # after the twin exits, time for what it wrote to arrive; then it died
MAX_LINE_BYTES = 16 << 20  # an answer line may hold at most 16 MiB (a batch answer
# gets MAX_LINE_BYTES_PER_RUN_HOUR per run-hour asked when that is more): a twin writing
# without newlines is a protocol error, not an unbounded read into memory
MAX_LINE_BYTES_PER_RUN_HOUR = 8 << 10
DEFAULT_FAIL_FAST_RUNS = 20  # circuit breaker: stop when the first K runs all failed ...
DEFAULT_MAX_RESTARTS = 10  # ... or workers were restarted R times before any run was ok:
# a twin broken for every run (e.g. a log line on stdout) would otherwise fail all of a
# shard's runs, restarting a worker for each, at Pulse prices days of wall time. Both
# checks end with the first ok run: after it, failures are the twin's answers about hard
# X_0 and are recorded run by run. The breaker must judge the twin, not one patient: until
# a run is ok, each X_0 (seed group) gets one run and its other runs wait, so the first K
# runs come from K distinct X_0 (or from every X_0, when there are fewer than K).
DEFAULT_BATCH_SIZE = 500  # runs per simulate_batch message (when the twin allows batches):
# large enough that the per-message round trip (~ms) is negligible per run, small enough
# that a batch's JSON (~1 kB per run) and a retry after a failed batch stay cheap
BATCHES_IN_FLIGHT = 2  # simulate_batch messages a worker may have at once: the next one
# is sent before the previous answer is read, so the twin computes while the client encodes,
# checks and records (taking turns, each side idled half the time); 1 = take turns
_UNITS = {f.name: f.unit for f in schema.FEATURE_TABLE}
# the contract's range per feature (schema.mark_implausible's), to test a run's values at
# once: mark_implausible is called only for a run with a value outside it
_LO = np.array([f.lo for f in schema.FEATURE_TABLE])
_HI = np.array([f.hi for f in schema.FEATURE_TABLE])


class WorkerDied(Exception):
    """The worker process closed its stdout (exited or crashed)."""


class WorkerTimeout(Exception):
    """No answer within the time limit."""


def resolve_command(command: Sequence[str], env: Mapping[str, str] | None = None) -> list[str]:
    """Check that the twin command can be started; return it as a list of strings.

    Raises FileNotFoundError naming the command if its executable does not
    exist (so a typo fails at once instead of after ``retries`` restarts).
    """
    if isinstance(command, str | bytes):
        raise TypeError(
            f"twin command must be a sequence of arguments, not a string: {command!r} "
            "(use shlex.split)"
        )
    cmd = [os.fspath(c) if not isinstance(c, str) else c for c in command]
    if not cmd or not cmd[0]:
        raise ContractError("twin command is empty")
    exe = cmd[0]
    path = (env or os.environ).get("PATH", os.defpath)
    if os.sep in exe or (os.altsep and os.altsep in exe):
        if not os.path.isfile(exe):
            raise FileNotFoundError(f"twin command not found: {exe!r} (command: {shlex.join(cmd)})")
        if not os.access(exe, os.X_OK):
            raise PermissionError(
                f"twin command is not executable: {exe!r} (command: {shlex.join(cmd)})"
            )
    elif shutil.which(exe, path=path) is None:
        raise FileNotFoundError(
            f"twin command not found on PATH: {exe!r} (command: {shlex.join(cmd)})"
        )
    return cmd


class _TooLong(str):
    """Stands in the line queue for an answer line longer than the worker's cap."""


def _leader_exited(pid: int) -> bool:
    """Whether the process ``pid`` (our child) has exited, without reaping it.

    Not reaping keeps its pid, which is also its process group's id (start_new_session),
    reserved, so a later kill of the group cannot reach an unrelated process.
    """
    if not hasattr(os, "waitid"):  # (macOS): then only end of stdout or a timeout tells
        return False
    try:
        return os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
    except ChildProcessError:  # already reaped
        return True


class Worker:
    """One twin subprocess with timed line reads and writes.

    The twin runs in its own session (process group), and the whole group is killed when
    the twin ends, times out or is dropped: a child the twin started (an engine, a shell
    wrapper's process, a daemon) never outlives it. The pipes are read by threads that
    wake every PIPE_POLL_S and stop when told, and written with a deadline, so a child
    that escaped the group and keeps the twin's stdout open cannot stall the shard.
    """

    def __init__(self, command: list[str], env: Mapping[str, str] | None) -> None:
        self.command = command
        try:
            self.proc = subprocess.Popen(
                command,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                bufsize=0,
                env=dict(env) if env is not None else None,
                # Own process group: a kill also reaches the twin's children
                # (e.g. a shell wrapper's engine process).
                start_new_session=True,
            )
        except OSError as exc:
            raise FileNotFoundError(
                f"cannot start twin command {shlex.join(command)}: {exc}"
            ) from exc
        assert self.proc.stdin is not None
        os.set_blocking(self.proc.stdin.fileno(), False)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stderr_tail: deque[str] = deque(maxlen=STDERR_TAIL_LINES)
        self.hello: dict[str, Any] = {}
        self.max_line = MAX_LINE_BYTES  # set per request by ask()
        self._unsent = memoryview(b"")  # the end of a message post() could not yet write
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._read_stdout, daemon=True),
            threading.Thread(target=self._read_stderr, daemon=True),
        ]
        for th in self._threads:
            th.start()

    def _chunks(self, pipe: Any) -> Iterator[bytes]:
        """The bytes of ``pipe`` as they come, until end of stream or until told to stop."""
        fd = pipe.fileno()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], PIPE_POLL_S)
                if not ready:
                    continue
                chunk = os.read(fd, 1 << 16)
            except (OSError, ValueError):
                return
            if not chunk:
                return
            yield chunk

    def _read_stdout(self) -> None:
        buf = bytearray()
        skipping = False  # inside a line already reported as too long
        try:
            for chunk in self._chunks(self.proc.stdout):
                start = 0
                while (end := chunk.find(b"\n", start)) >= 0:
                    if skipping:
                        skipping = False
                    else:
                        buf += chunk[start : end + 1]
                        self.lines.put(buf.decode("utf-8", errors="replace"))
                    buf.clear()
                    start = end + 1
                if not skipping:
                    buf += chunk[start:]
                    if len(buf) > self.max_line:
                        # a broken twin writing without newlines must not fill the memory
                        self.lines.put(_TooLong(bytes(buf[:80]).decode("utf-8", "replace")))
                        buf.clear()
                        skipping = True
            if buf and not skipping:  # a last line without its newline
                self.lines.put(buf.decode("utf-8", errors="replace"))
        finally:
            self.lines.put(None)  # end of stream

    def _read_stderr(self) -> None:
        buf = b""
        for chunk in self._chunks(self.proc.stderr):
            *done, buf = (buf + chunk).split(b"\n")
            buf = buf[-STDERR_LINE_CHARS:]
            self.stderr_tail.extend(
                ln[:STDERR_LINE_CHARS].decode("utf-8", "replace").rstrip("\r") for ln in done)
        if buf:
            self.stderr_tail.append(buf.decode("utf-8", "replace"))

    def tail(self) -> str:
        """The last stderr lines, for error messages ('' if none)."""
        self._threads[1].join(timeout=1.0)
        lines = [ln for ln in self.stderr_tail if ln.strip()]
        return " | ".join(lines[-5:])

    def _died(self) -> WorkerDied:
        # End of stdout: the worker is finished either way. A twin that exits closes its
        # stdout a moment before it is gone: it gets EXIT_DRAIN_S to do so and keeps its own
        # exit code. One still running then closed its stdout and lives on: the runner kills
        # it (its -9 is the runner's, not the twin's) and says so. What is left of its group
        # is killed, it is reaped, the tail kept.
        deadline = time.monotonic() + EXIT_DRAIN_S
        while (self.proc.returncode is None and not _leader_exited(self.proc.pid)
               and time.monotonic() < deadline):
            time.sleep(0.02)
        # (without waitid, macOS, the runner cannot tell without reaping: the exit code)
        alive = (hasattr(os, "waitid") and self.proc.returncode is None
                 and not _leader_exited(self.proc.pid))
        self._terminate_group()
        code = self.proc.returncode
        tail = self.tail()
        self._close()
        what = ("worker closed its stdout but kept running (killed by the runner)" if alive
                else f"worker exited with code {code}")
        return WorkerDied(what + (f"; stderr tail: {tail}" if tail else ""))

    def _send(self, data: bytes | memoryview, deadline: float) -> memoryview:
        """Write ``data`` to the twin's stdin until ``deadline`` (a twin that stopped
        reading must not block the caller); return what is left unwritten (empty: all)."""
        assert self.proc.stdin is not None
        fd = self.proc.stdin.fileno()
        view = memoryview(data)
        while view:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            _, ready, _ = select.select([], [fd], [], min(remaining, PIPE_POLL_S))
            if not ready:
                continue
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                continue
        return view

    def ask(self, msg: dict[str, Any], timeout_s: float,
            max_line: int = MAX_LINE_BYTES) -> dict[str, Any]:
        """Send one message and wait for the next non-blank line (decoded).

        An answer line longer than ``max_line`` bytes is a ProtocolError (it is not read
        into memory); a twin that exited while a child of it holds its stdout counts as
        died once the lines it wrote are read.
        """
        self.max_line = max_line
        deadline = time.monotonic() + timeout_s
        try:
            if self._send(encode(msg).encode("utf-8"), deadline):
                raise WorkerTimeout("the twin stopped reading its input")
        except (OSError, ValueError):  # broken pipe: the worker is gone
            raise self._died() from None
        return self.answer(deadline - time.monotonic())

    def post(self, msg: dict[str, Any], deadline: float) -> bool:
        """Send one message without waiting for its answer (read later with ``answer``);
        whether it was written whole by ``deadline`` (else ``flush`` writes the rest).

        Lets the next request go out while the twin still works on the previous one (the
        twin reads it when it is done with that one). A closed pipe is not raised here: the
        worker's death shows when its answer is awaited, with its exit code and stderr
        tail, after any answers it wrote before dying are read.
        """
        self._unsent = memoryview(encode(msg).encode("utf-8"))
        return self.flush(deadline)

    def flush(self, deadline: float) -> bool:
        """Write what ``post`` left unwritten until ``deadline``; whether all is written."""
        try:
            self._unsent = self._send(self._unsent, deadline)
        except (OSError, ValueError):  # broken pipe: answer() reports the death
            self._unsent = memoryview(b"")
        return not self._unsent

    def answer(self, timeout_s: float, until: Callable[[], bool] | None = None,
               max_line: int | None = None) -> dict[str, Any]:
        """Wait for the next non-blank line (decoded), e.g. the answer to a request
        ``ask`` timed out on; ``until()`` true ends the wait early (WorkerTimeout).
        ``max_line``: the cap of the request answered (default: the last ``ask``'s)."""
        if max_line is not None:
            self.max_line = max_line
        max_line = self.max_line
        deadline = time.monotonic() + timeout_s
        exited_at: float | None = None
        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self.lines.get(timeout=max(min(remaining, PIPE_POLL_S), 0.0))
            except queue.Empty:
                if remaining <= 0 or (until is not None and until()):
                    raise WorkerTimeout() from None
                if exited_at is None:
                    if self.proc.returncode is not None or _leader_exited(self.proc.pid):
                        exited_at = time.monotonic()
                elif time.monotonic() - exited_at > EXIT_DRAIN_S:
                    raise self._died() from None
                continue
            if line is None:
                raise self._died()
            if isinstance(line, _TooLong):
                raise ProtocolError(
                    f"answer line longer than {max_line:,} bytes, the cap for this request "
                    f"(starts {str(line)!r})")
            if not line.endswith("\n"):
                # A last line without its newline: the worker died while
                # writing (or closed stdout); that is a crash, not an answer.
                died = self._died()
                raise WorkerDied(f"{died} (after a partial line {line[:80]!r})")
            if line.strip():
                return decode(line)

    def _terminate_group(self) -> None:
        # The group is killed even when the twin itself has exited (a child of it may
        # live on, holding its pipes), but only while the twin is not yet reaped: until
        # then its pid, the group id, cannot be reused by an unrelated process.
        if self.proc.returncode is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        self.proc.wait()

    def kill(self) -> None:
        """Kill the whole process group, reap it, and release the pipes."""
        self._terminate_group()
        self._close()

    def close(self) -> None:
        """Ask the worker to shut down; kill its group once it exits or its time is up."""
        if self.proc.returncode is None:
            try:
                self.ask({"op": "shutdown"}, SHUTDOWN_GRACE_S)
            except (WorkerDied, WorkerTimeout, ProtocolError):
                pass
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()
            except (OSError, ValueError):
                pass
            deadline = time.monotonic() + SHUTDOWN_GRACE_S
            while (self.proc.returncode is None and not _leader_exited(self.proc.pid)
                   and time.monotonic() < deadline):
                time.sleep(0.02)
        self.kill()

    def _close(self) -> None:
        # The reader threads wake every PIPE_POLL_S and stop when told: the pipes can then
        # be closed without waiting for a writer that never closes its end.
        self._stop.set()
        for th in self._threads:
            th.join(timeout=2.0)
        for pipe in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            try:
                if pipe is not None:
                    pipe.close()
            except (OSError, ValueError):
                pass


@dataclass
class _Batch:
    """A simulate_batch message sent to a worker, its answer not yet read."""

    idx: np.ndarray  # its runs, in request order
    ids: list[str]  # their request ids
    worker: Worker
    limit: float  # its time limit: timeout_s x its runs
    deadline: float  # for its answer; moved to when the twin gets to it (WorkerPool._land)
    max_line: int  # cap of its answer line
    unsent: bool = False  # its message is not yet written whole (Worker.flush)
    error: BaseException | None = None  # the send failed (the twin stopped reading)


class WorkerPool:
    """State shared by the worker threads of one simulate_via_protocol call."""

    def __init__(
        self,
        command: list[str],
        env: Mapping[str, str] | None,
        x0: np.ndarray,
        doses: np.ndarray,
        seeds: np.ndarray,
        hours: np.ndarray,
        timeout_s: float,
        retries: int,
        features: Sequence[str],
        batch_size: int = DEFAULT_BATCH_SIZE,
        fail_fast_runs: int = DEFAULT_FAIL_FAST_RUNS,
        max_restarts: int = DEFAULT_MAX_RESTARTS,
        continue_while: Sequence[list] | None = None,
        check_range: bool = False,
        hello_out: dict | None = None,
    ) -> None:
        self.command, self.env = command, env
        # worker restarts over the whole call (not only before the first ok run), and why:
        # a twin crashing on every third request still ends with every run ok, so the
        # restarts are the only trace of it (``worker_stats``)
        self.crashes = 0  # a worker died (exited, crashed) during a request
        self.hangs = 0  # a worker was killed for giving no answer in time
        self.protocol_breaks = 0  # a worker was dropped for a malformed answer
        self.restarts_total = 0  # worker starts beyond each slot's first
        self.check_range = check_range
        self.hello_out = hello_out  # filled with the first hello's name and version
        # per run: box paths a truncating twin may stop by (runs.truncation), or None
        self.continue_while = continue_while
        self.fail_fast_runs, self.max_restarts = fail_fast_runs, max_restarts
        self.settled = 0  # runs recorded so far, any status
        self.any_ok = False
        self.restarts = 0  # worker restarts before the first ok run
        self.first_failure = ""  # "status: message" of the first failed run
        self.failed_x0: set[int] = set()  # seeds (X_0 draws) with a failed run
        self.batch_size = batch_size
        # Runs a thread takes from the queue at a time: 1 until a hello says
        # how large a batch the twin accepts (every worker runs the same command).
        self.take = 1
        self.in_flight = BATCHES_IN_FLIGHT
        self.x0, self.doses, self.seeds, self.hours = x0, doses, seeds, hours
        self.timeout_s, self.retries, self.required = timeout_s, retries, tuple(features)
        self.startup_timeout_s = max(timeout_s, STARTUP_TIMEOUT_S)
        n, t = doses.shape[:2]
        self.features = empty_features(n, t)
        self.status = np.full(n, "", dtype=object)
        self.message = np.full(n, "", dtype=object)
        self.clamped = np.full(n, "{}", dtype=object)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.tasks: deque[np.ndarray] = deque()
        # Until the first ok run: per worker slot, the rest of each seed group it probed
        # (one run per X_0, see DEFAULT_FAIL_FAST_RUNS), taken back last-probed first so a
        # save/restore twin continues the X_0 it holds.
        self.waiting: dict[int, list[np.ndarray]] = {}
        self.workers: dict[int, Worker] = {}
        self.started: set[int] = set()
        self.counts: Counter[str] = Counter()

    # -- workers ---------------------------------------------------------
    def _start_worker(self, slot: int) -> Worker:
        """Start a worker and check its hello.

        The first start of a slot must succeed (a twin that cannot say hello
        is misconfigured: ContractError naming the command and its stderr).
        A restart that dies or hangs counts as a failed attempt of the run.
        A hello that breaks the contract always raises.
        """
        if self.stop.is_set():
            raise WorkerDied("pool is stopping")
        first = slot not in self.started
        self.started.add(slot)
        if not first:
            with self.lock:
                self.restarts_total += 1
                self.restarts += 0 if self.any_ok else 1
                tripped = (self.max_restarts and not self.any_ok
                           and self.restarts > self.max_restarts)
            if tripped:
                self._trip(f"workers restarted {self.max_restarts} times before any run "
                           "was ok")
        worker = Worker(self.command, self.env)
        self.workers[slot] = worker
        where = f"twin {shlex.join(self.command)}"
        try:
            msg = worker.ask({"op": "hello", "protocol": 1}, self.startup_timeout_s)
            hello = check_hello(msg, self.required, _UNITS)
        except ProtocolError as exc:
            self._drop_worker(slot)
            tail = worker.tail()
            raise ContractError(
                f"{where}: bad hello: {exc}" + (f"; stderr tail: {tail}" if tail else "")
            ) from None
        except (WorkerDied, WorkerTimeout) as exc:
            self._drop_worker(slot)
            tail = worker.tail()
            if first:
                what = str(exc) if isinstance(exc, WorkerDied) else (
                    f"no hello answer within {self.startup_timeout_s:g} s"
                    + (f"; stderr tail: {tail}" if tail else "")
                )
                raise ContractError(f"{where}: cannot start: {what}") from None
            if isinstance(exc, WorkerTimeout):
                raise WorkerTimeout(
                    f"restarted worker gave no hello within {self.startup_timeout_s:g} s"
                ) from None
            raise
        max_hours = hello["capabilities"]["max_hours"]
        if max_hours is not None and int(self.hours.max()) > max_hours:
            self._drop_worker(slot)
            raise ContractError(
                f"{where}: runs ask for {int(self.hours.max())} hours; the twin's hello "
                f"allows at most {max_hours}"
            )
        worker.hello = hello
        with self.lock:
            if self.hello_out is not None and not self.hello_out:
                self.hello_out.update({k: hello[k] for k in ("name", "version") if k in hello})
            self.take = max(1, min(hello["capabilities"].get("batch", 1), self.batch_size))
        return worker

    def _count(self, what: str) -> None:
        with self.lock:
            setattr(self, what, getattr(self, what) + 1)

    def worker_stats(self) -> dict[str, int]:
        """Worker trouble over the call: ``restarts`` (starts beyond each worker's first),
        ``crashes`` (died during a request), ``hangs`` (killed on a timeout),
        ``protocol_breaks`` (dropped for a malformed answer)."""
        with self.lock:
            return {"restarts": self.restarts_total, "crashes": self.crashes,
                    "hangs": self.hangs, "protocol_breaks": self.protocol_breaks}

    def _drop_worker(self, slot: int) -> None:
        worker = self.workers.pop(slot, None)
        if worker is not None:
            worker.kill()

    # -- runs ------------------------------------------------------------
    def _trip(self, why: str) -> None:
        """Circuit breaker: stop the pool with one line naming command, reason, first failure."""
        first = self.first_failure or "none recorded"
        raise ContractError(
            f"twin {shlex.join(self.command)}: stopped, {why} (first failure: {first}); "
            "fix the twin, or raise fail_fast_runs / max_restarts in its config"
        )

    def _record(self, i: int, status: str, message: str, values: np.ndarray | None,
                clamped: str = "{}") -> None:
        if values is not None and len(values):
            self.features[i, : len(values)] = values
        self.status[i] = status
        self.message[i] = message
        self.clamped[i] = clamped
        message = self.message[i]
        if status == "ok" and self.check_range:
            # a value outside the contract's range fails the run when a study stores it
            # (runs.plan.plausible); count it as failed now, for the progress line and the
            # breaker. The result itself is returned as the twin gave it.
            values = self.features[i]
            if ((values < _LO) | (values > _HI)).any():  # (NaN, a missing hour, is neither)
                st, msg = np.array([status], dtype=object), np.array([message], dtype=object)
                if mark_implausible(self.features[i : i + 1].copy(), st, msg):
                    status, message = str(st[0]), str(msg[0])
        with self.lock:
            self.counts[status] += 1
            self.settled += 1
            if status == "ok":
                self.any_ok = True
            else:
                self.failed_x0.add(int(self.seeds[i]))
                if not self.first_failure:
                    self.first_failure = f"{status}: {message}"
            tripped = (self.fail_fast_runs and not self.any_ok
                       and self.settled >= self.fail_fast_runs)
        if tripped:
            self._trip(f"its first {self.fail_fast_runs} runs, from {len(self.failed_x0)} "
                       "distinct X_0, all failed")

    def _request(self, i: int, request_id: str, x0: list[float] | None = None,
                 doses: list[list[float]] | None = None) -> dict[str, Any]:
        """The simulate request of run ``i``; ``x0`` and ``doses``: its rows as lists, when
        the caller converted a whole batch's at once."""
        hours = int(self.hours[i])
        request = {
            "op": "simulate",
            "id": request_id,
            "x0": dict(zip(FEATURES, self.x0[i].tolist() if x0 is None else x0, strict=True)),
            "doses": self.doses[i, :hours].tolist() if doses is None else doses[:hours],
            "hours": hours,
            "seed": int(self.seeds[i]),
        }
        if self.continue_while is not None:
            request["continue_while"] = self.continue_while[i]
        return request

    def _check(self, answer: Any, request_id: str, i: int, declared) -> Any:
        paths = None if self.continue_while is None else self.continue_while[i]
        return check_result(answer, request_id, int(self.hours[i]), self.required, declared,
                            FEATURES, paths)

    def _run_one(self, slot: int, i: int) -> None:
        attempts = self.retries + 1
        last_status, last_message = "error", ""
        for attempt in range(attempts):
            if self.stop.is_set():  # interrupted: do not restart workers
                return
            request_id = f"{i}.{attempt}"
            try:
                worker = self.workers.get(slot) or self._start_worker(slot)
                answer = worker.ask(self._request(i, request_id), self.timeout_s)
                checked = self._check(answer, request_id, i, worker.hello["declared_units"])
            except WorkerTimeout as exc:
                hung = self.workers.get(slot)
                self._count("hangs")
                self._drop_worker(slot)  # kill first: the stderr tail is then complete
                tail = hung.tail() if hung is not None else ""
                last_status = "timeout"
                last_message = (str(exc) or f"no answer within {self.timeout_s:g} s") + (
                    "; worker killed" + (f"; stderr tail: {tail}" if tail else "")
                )
                continue
            except WorkerDied as exc:
                self._count("crashes")
                self.workers.pop(slot, None)
                last_status, last_message = "error", str(exc)
                continue
            except ProtocolError as exc:
                # The stream can no longer be trusted to be in step: restart.
                self._count("protocol_breaks")
                self._drop_worker(slot)
                self._record(i, "error", f"malformed answer: {exc}", None)
                return
            if self.stop.is_set() and self.error is not None:
                return
            self._record(i, checked.status, checked.message, checked.values, checked.clamped)
            return
        self._record(
            i, last_status, f"{last_message} (failed {attempts} attempt(s))", None
        )

    def _launch(self, worker: Worker, idx: np.ndarray, after: _Batch | None) -> _Batch:
        """Send runs ``idx`` as one simulate_batch message; its answer is read by ``_land``.

        With ``after`` (a batch still in flight on the same worker) the twin reads this one
        when it has answered that one: the send may wait that long too.
        """
        ids = [f"{i}.0" for i in idx]
        x0s, doses = self.x0[idx].tolist(), self.doses[idx].tolist()
        msg = {"op": "simulate_batch",
               "requests": [self._request(int(i), r, x, d)
                            for i, r, x, d in zip(idx, ids, x0s, doses, strict=True)]}
        if worker.hello["capabilities"].get(ARRAYS):  # numbers as bytes, not as text
            msg["answer"] = ARRAYS
        limit = self.timeout_s * len(idx)
        start = time.monotonic() if after is None else after.deadline
        cap = max(MAX_LINE_BYTES, MAX_LINE_BYTES_PER_RUN_HOUR * int(self.hours[idx].sum()))
        batch = _Batch(idx, ids, worker, limit, start + limit, cap)
        # behind another batch, the twin reads this one once it has answered that one: a
        # rest not written by then is written when that answer is read (_land)
        if not worker.post(msg, batch.deadline if after is None else after.deadline):
            batch.unsent = True
            if after is None:
                batch.error = WorkerTimeout("the twin stopped reading its input")
        return batch

    def _collect(self, batch: _Batch, behind: _Batch | None) -> tuple[list[Any] | None,
                                                                        BaseException | None]:
        """The batch's results (envelope checked), or what went wrong with the worker."""
        if batch.error is not None:
            return None, batch.error
        cap = batch.max_line if behind is None else max(batch.max_line, behind.max_line)
        try:
            answer = batch.worker.answer(batch.deadline - time.monotonic(), max_line=cap)
            if answer.get("answer") == ARRAYS:  # checked here at once, run by run
                paths = None if self.continue_while is None else [
                    self.continue_while[int(i)] for i in batch.idx]
                return check_array_results(
                    answer, batch.ids, self.hours[batch.idx].tolist(), self.required,
                    batch.worker.hello["declared_units"], FEATURES, paths), None
            return check_results(answer, len(batch.idx)), None
        except (WorkerTimeout, WorkerDied, ProtocolError) as exc:
            return None, exc

    def _batch_failed(self, slot: int, batch: _Batch, exc: BaseException) -> None:
        """A batch not to be trusted as a whole: count it, drop its worker, say so."""
        self._count({WorkerTimeout: "hangs", WorkerDied: "crashes"}.get(
            type(exc), "protocol_breaks"))
        if self.workers.get(slot) is batch.worker:
            if isinstance(exc, WorkerDied):
                self.workers.pop(slot, None)
            else:
                self._drop_worker(slot)
        what = {WorkerTimeout: str(exc) or f"no answer within {batch.limit:g} s",
                WorkerDied: str(exc)}.get(type(exc), f"malformed answer: {exc}")
        print(f"[twin] batch of {len(batch.idx)} runs failed ({what}); worker restarted, "
              "retrying its runs one by one", file=sys.stderr, flush=True)

    def _keep(self, batch: _Batch, results: list[Any]) -> list[int] | None:
        """Record the valid results of a well-formed answer; return the runs to redo alone
        (None: the pool is stopping on an error, record nothing more)."""
        declared = batch.worker.hello["declared_units"]
        redo: list[int] = []
        for i, request_id, result in zip(batch.idx, batch.ids, results, strict=True):
            i = int(i)
            if isinstance(result, ProtocolError):  # an "arrays" run that broke a rule
                redo.append(i)
                continue
            try:
                checked = (result if isinstance(result, CheckedResult)
                           else self._check(result, request_id, i, declared))
            except ProtocolError:
                redo.append(i)
                continue
            if self.stop.is_set() and self.error is not None:
                return None
            self._record(i, checked.status, checked.message, checked.values, checked.clamped)
        return redo

    def _land(self, slot: int, batch: _Batch, behind: _Batch | None = None
              ) -> tuple[_Batch | None, np.ndarray | None]:
        """Read and record the answer of ``batch``; failed runs are retried one by one.

        A batch that cannot be trusted as a whole (worker died, hung, or the answer's
        envelope is broken) costs a restart and every run is retried alone, with the usual
        attempts; a batch attempt never counts against a run (the culprit is unknown).
        Within a well-formed answer, a result that breaks the rules is retried alone (and
        gets exactly the error message a plain request gets); valid results are kept.

        ``behind``: the next batch, already sent to the same worker. If ``batch`` fails, the
        twin never started ``behind`` (it answers in order), so its runs are handed back
        (second value) to be sent again as they would have been. Otherwise ``behind`` is
        returned still in flight, its time limit starting now, unless runs must be retried
        alone first (a plain request needs a quiet stream): then it is landed here too.
        """
        results, failure = self._collect(batch, behind)
        if failure is not None:
            self._batch_failed(slot, batch, failure)
            self._redo(slot, [int(i) for i in batch.idx])
            return None, (None if behind is None else behind.idx)
        redo = self._keep(batch, results)
        if redo is None:
            return None, None
        if behind is not None:
            behind.deadline = time.monotonic() + behind.limit  # its turn at the twin
            if behind.unsent and not behind.worker.flush(behind.deadline):
                behind.error = WorkerTimeout("the twin stopped reading its input")
            if redo or behind.error is not None:
                results, failure = self._collect(behind, None)
                if failure is not None:
                    self._batch_failed(slot, behind, failure)
                    more: list[int] | None = [int(i) for i in behind.idx]
                else:
                    more = self._keep(behind, results)
                    if more is None:
                        return None, None
                redo += more
                behind = None
        self._redo(slot, redo)
        return behind, None

    def _redo(self, slot: int, runs: list[int]) -> None:
        for i in runs:
            if self.stop.is_set():
                return
            self._run_one(slot, i)

    def _run_runs(self, slot: int, runs: np.ndarray, flight: _Batch | None = None
                  ) -> _Batch | None:
        """Runs in the given order: batches when the twin allows them, else one by one.

        Once a run was ok (the circuit breaker no longer judges the twin), the next batch
        is sent before the answer to the previous one is read, so the twin computes while
        this thread encodes, checks and records: at most ``in_flight`` batches are out, and
        the one still out is returned (``flight``, given back with the next runs).
        """
        pos = 0
        while pos < len(runs) and not self.stop.is_set():
            worker = self.workers.get(slot)
            size = 1
            if worker is not None:  # (a worker is (re)started by a plain run)
                cap = worker.hello["capabilities"].get("batch", 1)
                size = min(cap, self.batch_size, len(runs) - pos)
            if size <= 1 and flight is not None:  # a plain request needs a quiet stream
                flight, _ = self._land(slot, flight)
                continue
            if size <= 1:
                self._run_one(slot, int(runs[pos]))
                pos += 1
                continue
            assert worker is not None
            new = self._launch(worker, runs[pos : pos + size], flight)
            pos += size
            if flight is not None:
                flight, again = self._land(slot, flight, new)
                if again is not None:  # never started: send it again, as before
                    runs, pos = np.concatenate([again, runs[pos:]]), 0
            else:
                flight = new
            if flight is not None and not (self.in_flight > 1 and self.any_ok):
                flight, _ = self._land(slot, flight)
        return flight

    def _next_chunk(self, slot: int) -> np.ndarray | None:
        """The runs a worker does next (call with the lock held); None when none are left.

        Whole seed groups, in plan order, up to one batch's worth of runs. While the
        breaker is armed (no run ok yet), only the first run of each group is taken and the
        rest waits with this slot; after the first ok run (or when nothing else is left)
        the slot takes its waiting groups back, last probed first.
        """
        mine = self.waiting.setdefault(slot, [])
        probing = bool(self.fail_fast_runs) and not self.any_ok
        if mine and (not probing or not self.tasks):
            return mine.pop()
        if not self.tasks:
            return None
        chunk: list[np.ndarray] = []
        taken = 0
        while self.tasks and (not chunk or taken < self.take):
            group = self.tasks.popleft()
            if probing and len(group) > 1:
                mine.append(group[1:])
                group = group[:1]
            chunk.append(group)
            taken += len(group)
        return np.concatenate(chunk)

    def thread_main(self, slot: int) -> None:
        try:
            flight: _Batch | None = None  # a batch sent, its answer not yet read
            while not self.stop.is_set():
                with self.lock:
                    chunk = self._next_chunk(slot)
                if chunk is None:
                    break
                flight = self._run_runs(slot, chunk, flight)
            if flight is not None and not self.stop.is_set():
                self._land(slot, flight)
        except BaseException as exc:  # noqa: BLE001 - re-raised by the caller
            with self.lock:
                if self.error is None:
                    self.error = exc
            self.stop.set()
        finally:
            worker = self.workers.pop(slot, None)
            if worker is not None:
                if self.stop.is_set():
                    worker.kill()
                else:
                    worker.close()

    def kill_all(self) -> None:
        for slot in list(self.workers):
            worker = self.workers.get(slot)
            if worker is not None:
                worker.kill()


def start_worker(command: list[str], env: Mapping[str, str] | None, timeout_s: float,
                 features: Sequence[str] = FEATURES) -> Worker:
    """Start one worker of ``command`` and check its hello, as a pool's first start does.

    For a hello outside any simulate call: the worker gets ``max(timeout_s,
    STARTUP_TIMEOUT_S)`` to answer; a twin that cannot say hello, or whose hello breaks
    the contract, raises ContractError naming the command. The caller closes the worker.
    """
    pool = WorkerPool(command, env, np.empty((0, len(FEATURES))), np.empty((0, 1, 2)),
                      np.empty(0, dtype=np.uint64), np.ones(1, dtype=int), timeout_s, 0,
                      features)
    worker = pool._start_worker(0)
    pool.workers.pop(0, None)  # the caller owns it now
    return worker
