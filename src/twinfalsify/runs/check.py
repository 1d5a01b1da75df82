"""Conformance check for a twin: does it speak the twin protocol the way a study needs?

    python -m twinfalsify.runs.check --spec '{"kind": "command", "command": "python my_twin.py"}'
    python -m twinfalsify.runs.check --config config/mine.yaml --twin mine

runs a short battery against the twin's command and prints one row per check (pass, fail
or skip) with, for each failure, what to change. Exit code 0 when nothing failed, 1
otherwise, 2 when the twin cannot be named (bad spec or config). The checks use the
study's own protocol client (``runs.worker.Worker``, ``runs.protocol.check_hello`` and
``check_result``), so a twin that passes them is accepted by a study's runs:

hello            the hello answer: protocol version, name and version strings, every
                 feature of the contract with its exact unit, well-formed capabilities
one answer       every request gets exactly one line (nothing else on stdout), an unknown
                 op an error answer, and the twin keeps serving
protocol         every simulate answer follows the rules (id, status, hours, features)
simulates        runs from a few shipped X_0 (synthetic-world patients) under three
                 dose sequences: at least one ok
ranges           every value inside the trajectory contract's range
deterministic    the same request twice (also on a fresh process) gives the same answer
prefix           a run of the first hours equals those hours of the longer run (the
                 randomness of hour h may depend only on seed and doses of hours 1..h)
batch            simulate_batch answers equal the single runs (if ``batch`` > 1)
save/restore     a run branched from a shared prefix equals the same run alone (if
                 ``save_restore``)
truncation       a truncated run keeps the hours a path still needs and equals the full
                 run there (if ``truncate``)
time             the slowest run against ``timeout_s`` (fails above half of it), and the
                 seconds per simulated hour a study's cost grows with
shutdown         ``shutdown`` is answered ``bye`` and the process exits with code 0

and then, on the answers, whether the twin behaves like a simulator of the patient it is
given (a twin can speak the protocol perfectly and still be wrong in these ways):

hour 1           hour 1 is not a copy of X_0 (hours shifted by one)
X_0              two different X_0 (same seed, same doses) give different trajectories
doses            each drug alone (IV fluid, then the vasopressor, the other at 0) given at
                 hour h changes some output at an hour >= h; a warning when it does not
                 ("the action at hour 2 changes nothing", "the vasopressor changes nothing
                 at any hour: ignored?"); fails when no drug ever changes its own hour
                 (doses applied one hour late)
effects          what each drug alone in hour 1 does to MAP, SBP and HR over the hours
                 (a table, mean of 3 seeds, beside what clinicians expect); a warning when
                 a drug lowers MAP or moves it by under 1 % of the other drug's change
units            each feature's hour-1 median against the data's (``--table``, or the
                 source of ``--config``) or else against X_0's: a ratio far from 1 is named
                 with the unit that explains it ("Glucose: twin median 6.1, data 128
                 mg/dL: mmol/L?"); two features of one unit each in the other's typical
                 range ("Sodium and Chloride swapped?"), and a median outside the feature's
                 typical range where the reference is inside it
drift            each feature's median over the ok runs at hours 2.. inside its typical
                 range when it is at hour 1 ("HR: twin median 91 at hour 1, 228 at hour 4
                 (typical 50-140 /min): drifts after hour 1?")
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twinfalsify.runs.protocol import (
    ProtocolError,
    check_hello,
    check_result,
    check_results,
    encode,
)
from twinfalsify.runs.worker import (
    SHUTDOWN_GRACE_S,
    STARTUP_TIMEOUT_S,
    Worker,
    WorkerDied,
    WorkerTimeout,
    resolve_command,
)
from twinfalsify.schema import FEATURE_TABLE, FEATURES, STAY_ID, T_MAX, TIME, ContractError
from twinfalsify.unitscreen import against_reference, drifts, outside_typical, swapped

UNITS = {f.name: f.unit for f in FEATURE_TABLE}
# per run, when the spec gives no timeout_s: the study's own default, so that a twin the
# check passes is not timed out by the study
DEFAULT_TIMEOUT_S = 600.0
PHYSIOLOGY = [k for k, f in enumerate(FEATURE_TABLE) if f.kind != "demographic"]
# How long to listen for stray stdout lines after a process's first answer, after every answer
# of a process that wrote one, and after the battery's last answer. Other answers get no
# wait: a line already there is still read, and one arriving later is read in place of the
# next answer (a protocol problem, never missed).
QUIET_S = 0.2
# Dose sequences every X_0 is run under: none, fluids only, fluids and a vasopressor
# (iv_fluid mL/h, vasopressor ug/kg/min per hour), within the ranges a study sends.
DOSES = (
    ((0.0, 0.0),) * T_MAX,
    ((250.0, 0.0), (250.0, 0.0), (100.0, 0.0), (0.0, 0.0)),
    ((100.0, 0.1), (100.0, 0.2), (50.0, 0.3), (50.0, 0.3)),
)
BRANCH = ((100.0, 0.1), (100.0, 0.2), (0.0, 0.0), (500.0, 0.0))  # shares 2 hours with DOSES[2]
# The dose components, each given alone (the other at 0) in one hour for the doses and
# effects checks: (name, amount, unit); a 1 L bolus over an hour, a high vasopressor dose.
COMPONENTS = (("IV fluid", 1000.0, "mL/h"), ("vasopressor", 0.5, "ug/kg/min"))
SEEDS = (4343, 4344, 4345)  # the effects table averages these (a noisy twin's sign holds)
EFFECT_FEATURES = ("MeanBP", "SysBP", "HR")
SHORT = {"MeanBP": "MAP", "SysBP": "SBP", "HR": "HR"}
SIZE_RATIO = 0.01  # one drug's largest MAP change under this share of the other's is named


@dataclass
class Outcome:
    """One row of the report: ``ok`` True (pass), False (fail) or None (skipped)."""

    name: str
    ok: bool | None
    detail: str
    fix: str = ""
    warn: bool = False  # passed, but with a warning the author should read
    info: list[str] = field(default_factory=list)  # lines printed under the row (a table)


FIXES = {
    "starts": "make the command start the twin from a shell as written (absolute paths or "
              "paths relative to where the study runs; 'python' means the study's Python)",
    "hello": "answer the first line {\"op\": \"hello\", ...} with {\"op\": \"hello\", \"ok\": "
             "true, \"name\", \"version\", \"protocol\": 1, \"features\": [{\"name\", \"unit\"} "
             "for all 18 contract features, units exactly as in docs/reference/twin-protocol.md], "
             "\"capabilities\": {...}}",
    "one answer": "write exactly one JSON line per request and flush; send logs to stderr "
                  "(print(..., file=sys.stderr)); answer an unknown op with {\"op\": "
                  "\"error\", \"message\": ...}",
    "protocol": "echo the request's id, use a status of ok | init_failed | irreversible | "
                "error, give exactly 'hours' hour objects with status ok, each with every "
                "declared feature as a finite number",
    "simulates": "build a patient from x0 (clamp what your model cannot take and report it "
                 "in 'clamped') and simulate the doses; turn exceptions into status error "
                 "with a message",
    "ranges": "convert to the contract's units (e.g. degC, mg/dL for glucose and calcium, "
              "mmol/L for electrolytes); a value outside the range is stored as a failed run",
    "deterministic": "draw every random number from a generator seeded by the request's "
                     "seed (and the doses so far), never from the clock or a global state",
    "prefix": "make hour h depend only on x0, seed and the doses of hours 1..h (no look "
              "ahead at later doses, no randomness consumed per request length)",
    "batch": "answer simulate_batch with the result each request gets alone, in order; or "
             "drop 'batch' from the capabilities",
    "save/restore": "restore the state saved after the shared dose prefix of the same x0 "
                    "and seed (key the cache on seed and doses); or advertise "
                    "save_restore: false",
    "truncation": "stop only after the hours some continue_while path still needs "
                  "(runs.truncation.hours_needed) and answer the same values as the full "
                  "run; or drop 'truncate' from the capabilities",
    "time": "raise the twin's timeout_s in the config, or make a run faster",
    "shutdown": "answer {\"op\": \"shutdown\"} with {\"op\": \"bye\"}, then exit with code 0",
    "hour 1": "answer with the state at the END of each hour 1..hours: the first hour object "
              "is after one hour of the first dose, never X_0 itself",
    "X_0": "build the simulated patient from the request's x0 (not a fixed or cached "
           "patient)",
    "doses": "apply the dose of hour h (doses[h-1]) during hour h; a twin that "
             "truly ignores a drug can keep the warning",
    "effects": "check the sign and unit of each drug's effect (IV fluid in mL/h, the "
               "vasopressor as norepinephrine-equivalent ug/kg/min); a twin whose drug truly "
               "acts this way can keep the warning",
    "drift": "look for a state that grows hour by hour: a step in minutes taken as hours, a "
             "rate applied per call, a unit converted again at every hour",
    "units": "convert every output to the contract's unit (docs/reference/twin-protocol.md, "
             "'Features'): the unit named after '?' is the one the values look like",
}
FIX_LAG = ("apply the dose of hour h (doses[h-1]) during hour h: the answer's hour h is the "
           "state at the END of hour h, after that hour's dose (not the state before it)")
# how long the check waits for a twin's first answer before it tells a slow start from an
# unflushed stdout (``Check._first_hello``)
FIRST_ANSWER_S = 5.0


class _Unflushed(Exception):
    """The twin's answers sit in an unflushed stdout buffer."""


HINT_UNFLUSHED = ("flush stdout after every answer: print(..., flush=True) or "
                  "sys.stdout.flush() (or run python -u); a pipe holds unflushed lines")
HINT_SLOW_START = ("if the twin needs long to start (loading a model, an engine), raise "
                   "timeout_s in its config entry (hello waits max(timeout_s, "
                   f"{STARTUP_TIMEOUT_S:g} s))")
HINT_EXIT = ("the twin exited mid-run: the stderr tail above says why; catch exceptions "
             "per request and answer {\"status\": \"error\", \"message\": ...} instead of "
             "exiting")


def shipped_x0(n: int = 4, seed: int = 11) -> list[dict[str, float]]:
    """X_0 of ``n`` synthetic-world patients: the median, then the extremes of MeanBP and
    HR in a 400-stay draw (varied physiology, every value in the contract's range)."""
    from twinfalsify.sources.synthetic import generate

    x0 = generate({"n_stays": 400}, seed=seed)
    x0 = x0[x0[TIME] == 0].set_index(STAY_ID)[list(FEATURES)]
    med = (x0 - x0.median()).abs().div(x0.std() + 1e-12).sum(axis=1).idxmin()
    picks = [med, x0["MeanBP"].idxmin(), x0["MeanBP"].idxmax(), x0["HR"].idxmax()]
    out, seen = [], set()
    for sid in picks:
        if sid not in seen:
            seen.add(sid)
            out.append({f: float(x0.at[sid, f]) for f in FEATURES})
    return out[:n]


def x0_from_table(path: str | Path, n: int = 4) -> list[dict[str, float]]:
    """X_0 (hour 0) of the first ``n`` stays of a trajectory table (``sources.table``)."""
    from twinfalsify.sources.table import read_table

    traj = read_table(path)
    first = traj[traj[TIME] == 0].head(n)
    return [{f: float(v) for f, v in zip(FEATURES, row, strict=True)}
            for row in first[list(FEATURES)].to_numpy()]


@dataclass
class _Run:
    """One simulate request and what came back."""

    request: dict[str, Any]
    status: str = ""
    values: np.ndarray | None = None  # (hours, F) contract order
    seconds: float = 0.0
    problem: str = ""  # protocol breach, crash or timeout, as one phrase
    stray: list[str] = field(default_factory=list)  # stdout lines after the answer


@dataclass
class Checker:
    """Drives twin processes for the checks; keeps every failure as an Outcome."""

    command: list[str]
    env: dict[str, str] | None
    timeout_s: float
    startup_timeout_s: float | None = None  # hello wait; None: max(timeout_s, 60 s)
    outcomes: list[Outcome] = field(default_factory=list)
    hello: dict[str, Any] = field(default_factory=dict)
    _workers: list[Worker] = field(default_factory=list)
    _worker: Worker | None = None  # the process the battery runs on
    _quiet: dict[int, bool] = field(default_factory=dict)  # process -> no stray line yet
    _ids: int = 0

    # -- plumbing ----------------------------------------------------------------------
    def add(self, name: str, ok: bool | None, detail: str, fix: str = "",
            warn: bool = False, info: list[str] | None = None) -> None:
        if ok is False or warn:
            fix = fix or FIXES.get(name, "")
        self.outcomes.append(Outcome(name, ok, detail, fix, warn, list(info or [])))

    def start(self) -> Worker:
        worker = Worker(self.command, self.env)
        self._workers.append(worker)
        return worker

    def stray(self, worker: Worker, wait: bool = True) -> list[str]:
        """Lines the twin wrote after its answer (there must be none); ``wait`` listens for
        QUIET_S first."""
        if wait:
            time.sleep(QUIET_S)
        lines = []
        while not worker.lines.empty():
            line = worker.lines.get_nowait()
            if line is None:
                worker.lines.put(None)  # keep the end-of-stream mark for the next read
                break
            if line.strip():
                lines.append(line.rstrip("\n"))
        return lines

    def request(self, x0: dict[str, float], doses: Sequence[Sequence[float]], seed: int,
                **extra: Any) -> dict[str, Any]:
        self._ids += 1
        return {"op": "simulate", "id": f"check.{self._ids}", "x0": x0,
                "doses": [list(d) for d in doses], "hours": len(doses), "seed": seed, **extra}

    def simulate(self, worker: Worker, request: dict[str, Any]) -> _Run:
        """Send one request; a crash, hang or broken answer is the run's ``problem``."""
        run = _Run(request)
        t0 = time.monotonic()
        try:
            msg = worker.ask(request, self.timeout_s)
            run.seconds = time.monotonic() - t0
            res = check_result(msg, request["id"], request["hours"], FEATURES,
                               self.hello["declared_units"], FEATURES,
                               request.get("continue_while"))
        except WorkerTimeout:
            run.seconds = time.monotonic() - t0
            run.problem = f"no answer within timeout_s = {self.timeout_s:g} s"
            worker.kill()
            return run
        except WorkerDied as exc:
            what = "closed its stdout" if "closed its stdout" in str(exc) else "exited"
            run.problem = f"the twin {what} during the run ({exc})"
            return run
        except ProtocolError as exc:
            run.problem = f"broken answer: {exc}"
            worker.kill()  # its stream may be out of step, as in a study
            return run
        run.status, run.values = res.status, res.values
        run.stray = self.stray(worker, wait=not self._quiet.get(id(worker), False))
        self._quiet[id(worker)] = not run.stray
        if res.status != "ok":
            run.problem = ""  # a failure status is a legal answer
            run.status = f"{res.status}: {res.message}".strip(": ")
        return run

    def close_all(self) -> None:
        for worker in self._workers:
            if worker.proc.returncode is None:
                worker.kill()

    # -- the checks --------------------------------------------------------------------
    def check_hello(self) -> Worker | None:
        """Start the first worker and check its hello; None when nothing else can run."""
        try:
            resolve_command(self.command, self.env)
            worker = self.start()
        except (FileNotFoundError, PermissionError, ContractError) as exc:
            self.add("starts", False, str(exc))
            return None
        try:
            msg = self._first_hello(worker)
        except _Unflushed as exc:
            self.add("hello", False, str(exc), HINT_UNFLUSHED)
            return None
        except WorkerTimeout:
            self.add("hello", False, *self._why_no_hello(worker))
            return None
        except WorkerDied as exc:
            self.add("starts", False, f"the twin exited before answering hello: {exc}")
            return None
        except ProtocolError as exc:
            self.add("hello", False, f"hello answer: {exc}")
            return None
        try:
            self.hello = check_hello(msg, FEATURES, UNITS)
        except ProtocolError as exc:
            self.add("hello", False, str(exc))
            return None
        caps = self.hello["capabilities"]
        shown = {k: v for k, v in caps.items() if v not in (None, False)}
        self.add("hello", True, f"{self.hello['name']} {self.hello['version']}, "
                 f"{len(self.hello['declared_units'])} features, capabilities "
                 f"{json.dumps(shown) if shown else 'none'}")
        max_hours = caps.get("max_hours")
        if max_hours is not None and max_hours < T_MAX:
            self.add("hello", False, f"max_hours {max_hours} < T = {T_MAX}: a study asks for "
                     f"up to {T_MAX} hours (or set design.horizon <= {max_hours})")
        return worker

    def _first_hello(self, worker: Worker) -> dict[str, Any]:
        """The hello answer, within ``hello_wait``; a twin silent for FIRST_ANSWER_S is
        told apart from a slow starter at once: a second copy is sent hello with its stdin
        closed, which makes a buffering twin exit and flush. When that copy answers while
        the first, started earlier, is still silent, the first holds its answer in an
        unflushed buffer (``_Unflushed``)."""
        hello = {"op": "hello", "protocol": 1}
        first = min(FIRST_ANSWER_S, self.hello_wait)
        try:
            return worker.ask(hello, first)
        except WorkerTimeout:
            if self.hello_wait <= first:
                raise
        probe = self.start()
        try:
            assert probe.proc.stdin is not None
            os.write(probe.proc.stdin.fileno(), encode(hello).encode("utf-8"))
            probe.proc.stdin.close()
        except OSError:
            pass
        answered: list[bool] = []

        def probe_answered() -> bool:
            while not answered and not probe.lines.empty():
                line = probe.lines.get_nowait()
                if line is None:
                    break
                if '"hello"' in line:
                    answered.append(True)
            return bool(answered)

        try:
            return worker.answer(self.hello_wait - first, until=probe_answered)
        except WorkerTimeout:
            if not answered:
                raise
        try:  # the first copy may have answered in the same instant
            return worker.answer(1.0)
        except WorkerTimeout:
            raise _Unflushed(f"no answer within {first:g} s: does the twin flush stdout "
                             "after each line? (a second copy answered hello only when its "
                             "stdin was closed, the first, started earlier, is still "
                             "silent)") from None
        finally:
            probe.kill()

    @property
    def hello_wait(self) -> float:
        """How long a hello may take: as in a study, unless the caller set it."""
        if self.startup_timeout_s is not None:
            return self.startup_timeout_s
        return max(self.timeout_s, STARTUP_TIMEOUT_S)

    def _why_no_hello(self, worker: Worker) -> tuple[str, str]:
        """(detail, fix) for a hello that did not come: closing stdin makes a buffering
        twin exit and flush, so an answer arriving then shows unflushed stdout."""
        detail = f"no hello answer within {self.hello_wait:g} s"
        alive = worker.proc.poll() is None
        try:
            assert worker.proc.stdin is not None
            worker.proc.stdin.close()
        except (OSError, ValueError):
            pass
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            try:
                line = worker.lines.get(timeout=max(deadline - time.monotonic(), 0.0))
            except Exception:  # noqa: BLE001 - queue.Empty
                break
            if line is None:
                break
            if '"hello"' in line:
                return (detail + "; the hello answer came only when stdin was closed: "
                        "stdout is not flushed", HINT_UNFLUSHED)
        worker.kill()
        tail = worker.tail()
        if alive:
            return (detail + " (the twin was running" + (f"; stderr tail: {tail})" if tail
                                                         else ", silent on stderr)"),
                    f"{HINT_SLOW_START}; or {HINT_UNFLUSHED}")
        return detail + (f"; stderr tail: {tail}" if tail else ""), HINT_EXIT

    def run_battery(self, worker: Worker, x0s: list[dict[str, float]]) -> list[_Run]:
        """Every X_0 under every dose sequence; checks protocol, stdout, statuses, ranges."""
        hours = min(T_MAX, self.hello["capabilities"].get("max_hours") or T_MAX)
        runs, stray = [], []
        pairs = [(i, x0, j, doses) for i, x0 in enumerate(x0s) for j, doses in enumerate(DOSES)]
        for i, x0, j, doses in pairs:
            if sum("timeout" in r.problem for r in runs) >= 2:
                break  # each costs timeout_s: two say enough
            run = self.simulate(worker, self.request(x0, doses[:hours], 1000 + 10 * i + j))
            runs.append(run)
            if run.stray:
                stray.append(f"after the answer to {run.request['id']}: {run.stray[0]!r}")
            if run.problem:  # a new process, as a study's runner starts one
                worker = self.fresh()
        if runs and not runs[-1].problem and (late := self.stray(worker)):
            stray.append(f"after the answer to {runs[-1].request['id']}: {late[0]!r}")
        self._worker = worker
        broken = [r for r in runs if r.problem and "timeout" not in r.problem]
        self.add("protocol", not broken,
                 f"{len(runs) - len(broken)} of {len(runs)} answers follow the protocol"
                 + (f"; first: {broken[0].problem}" if broken else ""),
                 fix=HINT_EXIT if broken and "exited during" in broken[0].problem else "")
        # one request = one answer: stray lines, and an unknown op answered with an error
        unknown = self._unknown_op(worker)
        problems = stray + ([unknown] if unknown else [])
        self.add("one answer", not problems,
                 problems[0] if problems else "one line per request, unknown op answered")
        ok = [r for r in runs if r.status == "ok"]
        failed = [r for r in runs if r.status and r.status != "ok"]
        detail = f"{len(ok)} of {len(runs)} runs ok ({len(x0s)} X_0 x {len(DOSES)} dose " \
                 f"sequences, {hours} h)"
        if failed:
            detail += f"; {len(failed)} answered {failed[0].status!r}"
        if len(runs) < len(pairs):
            detail += f"; stopped after {len(runs)} of {len(pairs)} runs (2 timeouts)"
        self.add("simulates", bool(ok), detail)
        out = []
        for r in ok:
            lo = np.array([f.lo for f in FEATURE_TABLE])
            hi = np.array([f.hi for f in FEATURE_TABLE])
            with np.errstate(invalid="ignore"):
                bad = np.argwhere((r.values < lo) | (r.values > hi))
            if len(bad):
                h, k = bad[0]
                feat = FEATURE_TABLE[k]
                out.append(f"{r.request['id']} hour {h + 1}: {feat.name} = "
                           f"{r.values[h, k]:g} outside [{feat.lo:g}, {feat.hi:g}] {feat.unit}")
        if ok:
            self.add("ranges", not out, out[0] if out else
                     f"every value of {len(ok)} ok runs inside the contract's ranges")
        else:
            self.add("ranges", None, "no ok run to look at")
        timed_out = [r for r in runs if "timeout" in r.problem]
        slowest = max((r.seconds for r in runs), default=0.0)
        if timed_out:
            self.add("time", False, f"{len(timed_out)} run(s) without an answer within "
                     f"timeout_s = {self.timeout_s:g} s")
        else:
            answered = [r for r in ok if r.values is not None and len(r.values)]
            sim_hours = sum(len(r.values) for r in answered)
            per_hour = (f"; {sum(r.seconds for r in answered) / sim_hours:.3g} s per "
                        "simulated hour" if sim_hours else "")
            self.add("time", slowest <= 0.5 * self.timeout_s,
                     f"slowest run {slowest:.3g} s for {hours} h, timeout_s {self.timeout_s:g}"
                     f" s" + (" (more than half of it)" if slowest > 0.5 * self.timeout_s
                              else "") + per_hour)
        return runs

    def _hello_quietly(self, worker: Worker) -> None:
        try:
            worker.ask({"op": "hello", "protocol": 1}, max(self.timeout_s, STARTUP_TIMEOUT_S))
        except (WorkerTimeout, WorkerDied, ProtocolError):
            pass

    def _unknown_op(self, worker: Worker) -> str:
        if worker.proc.poll() is not None:
            return ""
        try:
            msg = worker.ask({"op": "conformance_check_unknown_op"}, min(self.timeout_s, 5.0))
        except WorkerTimeout:
            worker.kill()
            return "no answer to an unknown op (answer {\"op\": \"error\", ...})"
        except (WorkerDied, ProtocolError) as exc:
            worker.kill()
            return f"unknown op: {exc}"
        if msg.get("op") != "error":
            return f"unknown op answered with op {msg.get('op')!r}, expected 'error'"
        return ""

    def main(self) -> Worker:
        """The process the battery ran on, or a new one if it had to be stopped."""
        if self._worker is None or self._worker.proc.poll() is not None:
            self._worker = self.fresh()
        return self._worker

    def fresh(self) -> Worker:
        worker = self.start()
        self._hello_quietly(worker)
        return worker

    def same(self, a: _Run, b: _Run, hours: int | None = None) -> str:
        """'' when the runs agree (status and every value of the first ``hours``)."""
        if a.problem or b.problem:
            return a.problem or b.problem
        if a.status != b.status:
            return f"status {a.status!r} vs {b.status!r}"
        va, vb = a.values[:hours], b.values[:hours]
        if va.shape != vb.shape:
            return f"{len(va)} vs {len(vb)} hours"
        diff = np.argwhere(~((va == vb) | (np.isnan(va) & np.isnan(vb))))
        if len(diff):
            h, k = diff[0]
            return f"hour {h + 1} {FEATURES[k]}: {va[h, k]:.17g} vs {vb[h, k]:.17g}"
        return ""

    def check_determinism(self, ref: _Run) -> None:
        again = self.simulate(self.main(), dict(ref.request, id="check.again"))
        other = self.simulate(self.fresh(), dict(ref.request, id="check.fresh"))
        diff = self.same(ref, again) or self.same(ref, other)
        self.add("deterministic", not diff, diff and f"same request, same seed: {diff}"
                 or "same request twice and on a fresh process: identical answers")

    def check_prefix(self, ref: _Run) -> None:
        req = ref.request
        short = self.simulate(self.main(), self.request(req["x0"], req["doses"][:2],
                                                         req["seed"]))
        diff = self.same(ref, short, 2)
        self.add("prefix", not diff, diff and f"2-hour run vs the first 2 hours of a "
                 f"{req['hours']}-hour run: {diff}" or "a 2-hour run equals the first 2 hours "
                 "of the 4-hour run")

    def check_batch(self, runs: list[_Run]) -> None:
        size = int(self.hello["capabilities"].get("batch", 1))
        if size <= 1:
            self.add("batch", None, "not advertised (the study sends one run per message)")
            return
        singles = [r for r in runs if not r.problem][:min(size, 6)]
        if not singles:
            self.add("batch", None, "no answered run to compare a batch with")
            return
        requests = [dict(r.request, id=f"batch.{k}") for k, r in enumerate(singles)]
        worker = self.main()
        try:
            msg = worker.ask({"op": "simulate_batch", "requests": requests},
                             self.timeout_s * len(requests))
            results = check_results(msg, len(requests))
            diffs = []
            for k, (req, res, single) in enumerate(zip(requests, results, singles,
                                                      strict=True)):
                got = check_result(res, req["id"], req["hours"], FEATURES,
                                   self.hello["declared_units"], FEATURES)
                status = got.status if got.status == "ok" else \
                    f"{got.status}: {got.message}".strip(": ")
                d = self.same(single, _Run(req, status, got.values))
                if d and not (single.status != "ok" and status.split(":")[0]
                              == single.status.split(":")[0]):
                    diffs.append(f"run {k}: {d}")
            stray = self.stray(worker)
            if stray:
                diffs.append(f"a line after the batch answer: {stray[0]!r}")
        except WorkerTimeout:
            worker.kill()
            diffs = [f"no answer to a batch of {len(requests)} within "
                     f"{self.timeout_s * len(requests):g} s"]
        except (WorkerDied, ProtocolError) as exc:
            worker.kill()
            diffs = [f"batch answer: {exc}"]
        self.add("batch", not diffs, diffs[0] if diffs else
                 f"a batch of {len(requests)} equals the runs one by one")

    def check_save_restore(self, x0: dict[str, float]) -> None:
        if not self.hello["capabilities"].get("save_restore"):
            self.add("save/restore", None, "not advertised")
            return
        worker = self.main()
        first = self.simulate(worker, self.request(x0, DOSES[2], 77))
        branched = self.simulate(worker, self.request(x0, BRANCH, 77))
        alone = self.simulate(self.fresh(), self.request(x0, BRANCH, 77))
        diff = self.same(alone, branched) or first.problem
        self.add("save/restore", not diff, diff and f"a run sharing 2 hours with the previous "
                 f"run vs the same run alone: {diff}" or "a run branched from a shared "
                 "prefix equals the same run alone")

    def check_truncation(self, x0: dict[str, float]) -> None:
        if not self.hello["capabilities"].get("truncate"):
            self.add("truncation", None, "not advertised")
            return
        worker = self.main()
        full = self.simulate(worker, self.request(x0, DOSES[1], 91))
        notes = []
        # a path that holds for 2 hours needs 3; one that never holds needs 1
        for paths, need in (([[["HR", "any", 0.0], ["HR", "any", 0.0]]], 3),
                            ([[["HR", "<=", -1.0]]], 1)):
            run = self.simulate(worker, self.request(x0, DOSES[1], 91, continue_while=paths))
            if run.problem:
                notes.append(run.problem)
                break
            n = len(run.values)
            diff = self.same(full, run, n) if n else ""
            if diff:
                notes.append(f"truncated run after {n} h vs the full run: {diff}")
            elif n < need:
                notes.append(f"{n} hours where {need} are needed")
        self.add("truncation", not notes, notes[0] if notes else
                 "stops only where no path needs more, values equal to the full run")

    # -- behaviour: a twin that speaks the protocol can still simulate the wrong thing ----
    @staticmethod
    def _ok_runs(runs: Sequence[_Run]) -> list[_Run]:
        return [r for r in runs if r.status == "ok" and r.values is not None
                and len(r.values)]

    def check_hour1(self, runs: Sequence[_Run]) -> None:
        ok = self._ok_runs(runs)
        if not ok:
            self.add("hour 1", None, "no ok run to look at")
            return
        copies = 0
        for r in ok:
            x0 = np.array([r.request["x0"][f] for f in FEATURES], dtype=float)
            # every physiological feature unchanged after an hour: X_0 handed back as hour 1
            copies += bool(np.array_equal(r.values[0, PHYSIOLOGY], x0[PHYSIOLOGY]))
        self.add("hour 1", copies < len(ok),
                 f"hour 1 equals X_0 in all {len(ok)} ok runs (every physiological feature): "
                 "hours shifted by one?" if copies == len(ok) else
                 f"hour 1 differs from X_0 in {len(ok) - copies} of {len(ok)} ok runs")

    def check_x0(self, x0s: Sequence[dict[str, float]], hours: int) -> None:
        if len(x0s) < 2:
            self.add("X_0", None, "one X_0 only: nothing to compare")
            return
        worker = self.main()
        a = self.simulate(worker, self.request(x0s[0], DOSES[1][:hours], 4242))
        b = self.simulate(self.main(), self.request(x0s[1], DOSES[1][:hours], 4242))
        if a.status != "ok" or b.status != "ok":
            self.add("X_0", None, f"runs answered {a.problem or a.status!r} and "
                     f"{b.problem or b.status!r}: nothing to compare")
            return
        differ = [f for f in FEATURES if x0s[0][f] != x0s[1][f]]
        same = not self.same(a, b)
        self.add("X_0", not same,
                 f"the same trajectory from 2 X_0 that differ in {len(differ)} features "
                 f"(e.g. {differ[0]} {x0s[0][differ[0]]:.4g} vs {x0s[1][differ[0]]:.4g}), same "
                 "seed and doses: X_0 is ignored" if same else
                 "2 different X_0 (same seed and doses) give different trajectories")

    def _effect_run(self, x0: dict[str, float], hours: int, seed: int,
                    component: int | None = None, hour: int = 1) -> _Run:
        """A run from no drug at all; ``component`` (0 IV fluid, 1 vasopressor) given alone
        at ``hour``, in the amount of COMPONENTS."""
        doses = [[0.0, 0.0] for _ in range(hours)]
        if component is not None:
            doses[hour - 1][component] = COMPONENTS[component][1]
        return self.simulate(self.main(), self.request(x0, doses, seed))

    def check_doses(self, x0: dict[str, float], hours: int) -> None:
        """Each dose component alone at each hour: does it change an output of that hour or
        later (a warning when not), and does any change show up in its own hour (a dose
        applied one hour late fails)?  Then what each drug does to MAP, SBP and HR."""
        base = self._effect_run(x0, hours, SEEDS[0])
        if base.status != "ok" or base.values is None or len(base.values) < hours:
            self.add("doses", None, f"the run without drugs answered "
                     f"{base.problem or base.status!r}")
            self.add("effects", None, "no run without drugs to compare with")
            return
        silent: dict[int, list[int]] = {0: [], 1: []}
        own_hour, later_only, compared = 0, 0, 0
        for c in (0, 1):
            for h in range(1, hours + 1):
                run = self._effect_run(x0, hours, SEEDS[0], c, h)
                if run.status != "ok" or run.values is None or len(run.values) < hours:
                    continue
                compared += 1
                a, b = run.values[:hours], base.values[:hours]
                moved = ~((a == b) | (np.isnan(a) & np.isnan(b)))
                changed = np.flatnonzero(moved[h - 1:].any(axis=1))
                if not len(changed):
                    silent[c].append(h)
                elif changed[0] == 0:
                    own_hour += 1
                else:
                    later_only += 1
        if not compared:
            self.add("doses", None, "no ok run with a drug given to compare")
        else:
            self._doses_row(silent, own_hour, later_only, hours)
        self._effects_row(x0, hours, base)

    def _doses_row(self, silent: dict[int, list[int]], own_hour: int, later_only: int,
                   hours: int) -> None:
        both = sorted(set(silent[0]) & set(silent[1]))
        notes = []
        if both:
            notes.append(f"the action at hour {both[0]} changes nothing" if len(both) == 1
                         else f"the actions at hours {', '.join(map(str, both))} change "
                         "nothing")
        for c in (0, 1):
            alone = [h for h in silent[c] if h not in both]
            name = COMPONENTS[c][0]
            if len(silent[c]) == hours and not both == list(range(1, hours + 1)):
                notes.append(f"the {name} changes nothing at any hour: ignored?")
            elif alone:
                notes.append(f"the {name} at hour{'s' if len(alone) > 1 else ''} "
                             f"{', '.join(map(str, alone))} changes nothing")
        amounts = " or ".join(f"{n} {a:g} {u}" for n, a, u in COMPONENTS)
        if later_only and not own_hour:
            self.add("doses", False, "a drug given in hour h first changes an output at "
                     f"hour h + 1, never in its own hour ({later_only} runs): doses applied "
                     "one hour late?"
                     + (f" ({'; '.join(notes)})" if notes else ""),
                     fix=FIX_LAG)
        elif notes:
            self.add("doses", True, "; ".join(notes) + f" ({amounts} given alone at that "
                     "hour; every output of that hour and later equal)", warn=True)
        else:
            self.add("doses", True, f"each drug alone at hour h changes an output at hour h "
                     f"or later (h = 1..{hours}; {amounts})")

    def _effects_row(self, x0: dict[str, float], hours: int, base: _Run) -> None:
        """Each drug alone in hour 1 against no drug, averaged over SEEDS: the table of its
        effect on EFFECT_FEATURES, and a warning for a wrong sign or a size far from the
        other drug's."""
        cols = [FEATURES.index(f) for f in EFFECT_FEATURES]
        deltas: dict[int, list[np.ndarray]] = {0: [], 1: []}
        for k, seed in enumerate(SEEDS):
            b = base if k == 0 else self._effect_run(x0, hours, seed)
            if b.status != "ok" or b.values is None or len(b.values) < hours:
                continue
            for c in (0, 1):
                run = self._effect_run(x0, hours, seed, c, 1)
                if run.status == "ok" and run.values is not None and len(run.values) >= hours:
                    deltas[c].append(run.values[:hours, cols] - b.values[:hours, cols])
        if not deltas[0] or not deltas[1]:
            self.add("effects", None, "no ok pair of runs with and without a drug")
            return
        mean = {c: np.mean(deltas[c], axis=0) for c in (0, 1)}  # (hours, len(cols))
        table = [f"{'':<40}" + "".join(f"{f'hour {h}':>10}" for h in range(1, hours + 1))]
        for c in (0, 1):
            name, amount, unit = COMPONENTS[c]
            label = f"{name} {amount:g} {unit}, hour 1"
            for j, feat in enumerate(EFFECT_FEATURES):
                table.append(f"{label if j == 0 else '':<34}{SHORT[feat]:<6}" + "".join(
                    f"{v:>+10.3g}" for v in mean[c][:, j]))
        table += [f"(each drug alone in hour 1, the change against no drug, mean of "
                  f"{len(deltas[0])} seeds; clinicians",
                  " expect a vasopressor to raise MAP and SBP within the hour, a fluid bolus to "
                  "raise MAP",
                  " less and later; HR may go either way)"]
        notes = []
        m = EFFECT_FEATURES.index("MeanBP")
        for c in (0, 1):
            name = COMPONENTS[c][0]
            signs = [np.mean(d[:, m]) for d in deltas[c]]
            if all(s < 0 for s in signs):
                notes.append(f"the {name} lowers MAP (mean {np.mean(signs):+.3g} mmHg over "
                             f"hours 1-{hours}): a sign error?")
        size = {c: float(np.max(np.abs(mean[c][:, m]))) for c in (0, 1)}
        if min(size.values()) > 0 and min(size.values()) < SIZE_RATIO * max(size.values()):
            small = min(size, key=size.get)
            other = 1 - small
            notes.append(f"the {COMPONENTS[small][0]}'s largest MAP change "
                         f"({size[small]:.3g} mmHg) is under {SIZE_RATIO:.0%} of the "
                         f"{COMPONENTS[other][0]}'s ({size[other]:.3g} mmHg): one drug's "
                         "dose in the wrong unit (mL vs L, ug vs mg)?")
        detail = "; ".join(notes) if notes else (
            "each drug's effect on MAP has the expected sign (the table below)")
        self.add("effects", True, detail, warn=bool(notes), info=table)

    def check_units(self, runs: Sequence[_Run], reference: dict[str, float] | None,
                    ref_name: str) -> None:
        ok = self._ok_runs(runs)
        if not ok:
            self.add("units", None, "no ok run to look at")
            self.add("drift", None, "no ok run to look at")
            return
        first = np.array([r.values[0] for r in ok])
        twin = dict(zip(FEATURES, np.nanmedian(first, axis=0), strict=True))
        if reference is None:
            reference = {f: float(np.median([r.request["x0"][f] for r in ok]))
                         for f in FEATURES}
        screened = [f for f in FEATURES if f != "sex" and f in reference]
        found = swapped({f: float(twin[f]) for f in screened})
        named = {f for m in found for f in screened if m.startswith(f) or f" and {f} " in m}
        for f in screened:
            if f in named:
                continue
            m = (against_reference(f, float(twin[f]), reference[f], ref_name=ref_name)
                 or outside_typical(f, float(twin[f]), reference[f], ref_name=ref_name))
            if m:
                found.append(m)
        self.add("units", not found, found[0] + (f" (and {len(found) - 1} more: "
                 + "; ".join(found[1:]) + ")" if len(found) > 1 else "") if found else
                 f"every feature's hour-1 median within a factor 2 of "
                 f"{'the data' if ref_name == 'data' else ref_name}'s and inside its typical "
                 f"range where that is ({len(ok)} ok runs)")
        # later hours: a median inside the typical range at hour 1 and outside it later
        # (of the runs inside the contract's ranges: the others are failed runs in a study)
        lo = np.array([f.lo for f in FEATURE_TABLE])
        hi = np.array([f.hi for f in FEATURE_TABLE])
        longest = max(len(r.values) for r in ok)
        full = [r.values for r in ok if len(r.values) == longest
                and not ((r.values < lo) | (r.values > hi)).any()]
        if not full:
            self.add("drift", None, "no ok run inside the contract's ranges to look at")
            return
        by_hour = np.nanmedian(np.array(full), axis=0)  # (hours, F)
        drift = [m for k, f in enumerate(FEATURES) if f not in named
                 for m in [drifts(f, [float(v) for v in by_hour[:, k]])] if m]
        self.add("drift", not drift, drift[0] + (f" (and {len(drift) - 1} more)"
                 if len(drift) > 1 else "") if drift else
                 f"every feature's median inside its typical range at hours 2-{len(by_hour)} "
                 "where it is at hour 1")

    def check_shutdown(self) -> None:
        worker = self.main()
        try:
            msg = worker.ask({"op": "shutdown"}, SHUTDOWN_GRACE_S)
            problem = "" if msg.get("op") == "bye" else f"answered op {msg.get('op')!r}"
        except WorkerTimeout:
            problem = f"no bye within {SHUTDOWN_GRACE_S:g} s"
        except (WorkerDied, ProtocolError) as exc:
            problem = f"no bye: {exc}"
        code = None
        if not problem:
            try:
                code = worker.proc.wait(timeout=SHUTDOWN_GRACE_S)
            except Exception:  # noqa: BLE001 - subprocess.TimeoutExpired
                problem = f"bye, but still running {SHUTDOWN_GRACE_S:g} s later"
        if not problem and code != 0:
            problem = f"bye, then exit code {code}"
        worker.kill()
        self.add("shutdown", not problem, problem or "bye, exit code 0")


def run_checks(command: Sequence[str], env: dict[str, str] | None = None,
               timeout_s: float = DEFAULT_TIMEOUT_S,
               x0s: list[dict[str, float]] | None = None,
               reference: dict[str, float] | None = None, ref_name: str = "X_0",
               startup_timeout_s: float | None = None) -> list[Outcome]:
    """Every check against ``command``; the report's rows in order.

    reference: the data's hour-1 median per feature (``data_reference``) for the unit
    screen; None compares the twin's hour 1 with the X_0 it was given.
    """
    checker = Checker(list(command), env, float(timeout_s), startup_timeout_s)
    try:
        worker = checker.check_hello()
        if worker is None:
            return checker.outcomes
        x0s = x0s or shipped_x0()
        runs = checker.run_battery(worker, x0s)
        steps: list[tuple[str, Callable[[], None]]] = []
        # the reference run: ok, 3+ hours, doses changing over time (a look-ahead shows)
        ref = next((r for r in sorted(runs, key=lambda r: r.request["doses"] != [
            list(d) for d in DOSES[1][:r.request["hours"]]])
            if r.status == "ok" and r.request["hours"] >= 3), None)
        if ref is None:
            for name in ("deterministic", "prefix"):
                checker.add(name, None, "no ok run of 3+ hours to compare")
        else:
            steps += [("deterministic", lambda: checker.check_determinism(ref)),
                      ("prefix", lambda: checker.check_prefix(ref))]
        steps += [("batch", lambda: checker.check_batch(runs)),
                  ("save/restore", lambda: checker.check_save_restore(x0s[0])),
                  ("truncation", lambda: checker.check_truncation(x0s[0])),
                  ("shutdown", checker.check_shutdown)]
        hours = min(T_MAX, checker.hello["capabilities"].get("max_hours") or T_MAX)
        behaviour: list[Callable[[], None]] = [
            lambda: checker.check_hour1(runs),
            lambda: checker.check_x0(x0s, hours),
            lambda: checker.check_doses(x0s[0], hours),
            lambda: checker.check_units(runs, reference, "data" if reference else ref_name)]
        steps[-1:-1] = [(str(k), step) for k, step in enumerate(behaviour)]
        for _, step in steps:
            step()
    finally:
        checker.close_all()
    return checker.outcomes


def report(outcomes: list[Outcome]) -> str:
    """The pass / fail table, a fix under each failure, and a last line with the verdict."""
    width = max(len(o.name) for o in outcomes)
    lines = []
    for o in outcomes:
        mark = "WARN" if o.warn and o.ok is not False else \
            {True: "pass", False: "FAIL", None: "skip"}[o.ok]
        lines.append(f"{o.name:<{width}}  {mark}  {o.detail}")
        lines.extend(f"{'':<{width}}        {line}" for line in o.info)
        if o.fix:
            lines.append(f"{'':<{width}}        fix: {o.fix}")
    failed = [o.name for o in outcomes if o.ok is False]
    warned = [o.name for o in outcomes if o.warn and o.ok is not False]
    lines.append(f"{len(failed)} check(s) failed: {', '.join(dict.fromkeys(failed))}"
                 if failed else "all checks passed")
    if warned:
        lines[-1] += f" ({len(warned)} warning(s): {', '.join(warned)})"
    return "\n".join(lines)


def data_reference(trajectories: Any) -> dict[str, float]:
    """The hour-1 median of every feature in a trajectory frame (the unit screen's
    reference: what a twin's hour 1 should resemble)."""
    hour1 = trajectories[trajectories[TIME] == 1]
    return {f: float(hour1[f].median()) for f in FEATURES if hour1[f].notna().any()}


def data_of_config(config: dict[str, Any]) -> Any | None:
    """The study's trajectories when they are cheap to get (a table source, or the
    synthetic world drawn afresh); None for a source that needs an extraction."""
    source = config.get("source") or {}
    if source.get("kind") == "table" and (source.get("table") or {}).get("path"):
        from twinfalsify.sources.table import read_table

        return read_table(source["table"]["path"])
    if source.get("kind") == "synthetic":
        from twinfalsify.sources.synthetic import generate

        return generate(source.get("synthetic"), seed=int(config.get("seed", 0)))
    return None


def _x0_of(trajectories: Any, n: int = 4) -> list[dict[str, float]]:
    first = trajectories[trajectories[TIME] == 0].head(n)
    return [{f: float(v) for f, v in zip(FEATURES, row, strict=True)}
            for row in first[list(FEATURES)].to_numpy()]



def command_of(spec: dict[str, Any], name: str = "twin") -> tuple[list[str], dict | None, float]:
    """(command, env, timeout_s) of a ``kind: command`` twin spec, as a study starts it; a
    ``kind: python`` twin is checked served over the protocol, as a study with
    ``workers`` > 1 runs it (its timeout_s default is then the served twins' 60 s)."""
    from twinfalsify.runs.registry import make_twin

    if spec.get("kind") not in ("command", "python"):
        raise ContractError(f"twins.{name}: the check runs twins of kind command or python "
                            f"(this one is kind {spec.get('kind')!r}); the builtin twins "
                            "conform by construction")
    if spec.get("kind") == "python":
        spec = {**spec, "protocol": True}
    twin = make_twin(name, spec)
    timeout = float(twin.timeout_s)
    env = None
    if twin.env:
        import os

        env = {**os.environ, **twin.env}
    return twin.command, env, timeout


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m twinfalsify.runs.check",
        description="Check that a twin speaks the twin protocol as a study needs.")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--spec", help="the twin's config entry as JSON, e.g. "
                       "'{\"kind\": \"command\", \"command\": [\"python\", \"my_twin.py\"]}'")
    which.add_argument("--config", help="a study config (with --twin)")
    parser.add_argument("--twin", help="the twin's name in --config")
    parser.add_argument("--x0", help="take the X_0 of the first 4 stays of this trajectory "
                        "table instead of the shipped synthetic patients")
    parser.add_argument("--table", help="a trajectory table (the table contract): its first "
                        "4 stays give the X_0 and its hour-1 medians the unit screen's "
                        "reference (with --config: the study's source does, if cheap)")
    parser.add_argument("--timeout-s", type=float, help="per-run time limit (default: the "
                        f"spec's timeout_s, else {DEFAULT_TIMEOUT_S:g})")
    args = parser.parse_args(argv)
    if args.spec is not None:
        try:
            spec = json.loads(args.spec)
        except json.JSONDecodeError as exc:
            raise ContractError(f"--spec: not JSON ({exc.msg})") from None
        if not isinstance(spec, dict):
            raise ContractError("--spec: must be a JSON object like {\"kind\": \"command\", "
                                "\"command\": [...]}")
        name = "twin"
    else:
        if not args.twin:
            raise ContractError("--config needs --twin NAME")
        from twinfalsify.io import load_yaml_strict

        twins = (load_yaml_strict(args.config) or {}).get("twins") or {}
        if args.twin not in twins:
            raise ContractError(f"{args.config}: no twin {args.twin!r} under twins (found "
                                f"{', '.join(twins) or 'none'})")
        spec, name = twins[args.twin], args.twin
    command, env, timeout = command_of(spec, name)
    if args.timeout_s is not None:
        timeout = args.timeout_s
    data = None
    if args.table:
        from twinfalsify.sources.table import read_table

        data = read_table(args.table)
    elif args.config:
        from twinfalsify.io import load_yaml_strict

        data = data_of_config(load_yaml_strict(args.config) or {})
    if data is not None:
        from twinfalsify.sources.table import unit_suspects

        for message in unit_suspects(data):
            print(f"note: the data look atypical, so the units row compares the twin with "
                  f"them as they are: {message}", flush=True)
    x0s = x0_from_table(args.x0) if args.x0 else (_x0_of(data) if data is not None else None)
    reference = data_reference(data) if data is not None else None
    print(f"checking twin {shlex.join(command)} (timeout_s {timeout:g}; units against "
          f"{'the data' if reference else 'X_0'})", flush=True)
    t0 = time.monotonic()
    outcomes = run_checks(command, env, timeout, x0s, reference)
    print(report(outcomes))
    print(f"({time.monotonic() - t0:.1f} s)")
    return 1 if any(o.ok is False for o in outcomes) else 0


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(lambda: main(), "twinfalsify.runs.check"))
