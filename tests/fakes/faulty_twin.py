"""A protocol twin for fault injection: ``python tests/fakes/faulty_twin.py --mode ...``.

Good runs return a deterministic, prefix-consistent trajectory: for a non-demographic
feature f at the end of hour h,

    x_h[f] = x0[f] + 0.001 (0.5 h + 0.01 sum_{s<=h} iv_s + 10 sum_{s<=h} vaso_s
                            + 0.001 (seed mod 97))

and age, sex, weight stay as in X_0 (pure arithmetic so tests can check values exactly;
see ``expected``). The factor 0.001 keeps a run from an X_0 inside the trajectory
contract's ranges inside them, so a study does not mark good runs ``implausible``.
Faults are chosen per seed, so one study mixes good and bad runs
deterministically. ``--mode MODE[:SELECTOR]`` may be repeated; SELECTOR is
``all`` (default), a comma list of seeds ``3,7,11``, or ``%K=R`` (seed mod K
equals R). The first matching mode wins. Per-run modes:

    crash          exit (code 3) mid-request after writing half an answer line
    close_stdout   close stdout mid-request and keep running (sleeps)
    crash_once     crash the first time a seed is seen (needs --state-dir), then work
    hang           never answer (sleeps)
    garbage        write a line that is not JSON
    malformed      write truncated JSON
    wrong_id       answer with another request id
    wrong_features rename the feature HR to heart_rate in the hours
    fewer_hours    status ok with one hour fewer than asked
    non_numeric    a feature value is a string
    irreversible   status irreversible during hour --irreversible-hour (hours before it kept)
    init_failed    status init_failed, no hours
    error          status error with a message
    slow           sleep --delay seconds, then answer normally
    clamp          clamp HR to at most 110 and report the clamp
    implausible    status ok, but HR = 1e300 in hour 2 (hour 1 if only one is asked)
    negative       status ok, but HR = -500 in hour 2 (hour 1 if only one is asked)
    batch_short    in a simulate_batch answer, leave this run's result out (the
                   answer then has too few results); a plain simulate is answered
                   normally
Faults the conformance check (``python -m twinfalsify.runs.check``) must name:

    chatty          answer, then write a log line on stdout (two lines for one request)
    nondeterministic  add fresh random noise to every value (equal seeds, unequal runs)
    lookahead       hour h depends on the doses of later hours (a prefix run differs)
    batch_differs   inside a simulate_batch, HR is 1 /min higher than in a plain simulate
    stale_restore   reuse the hours cached for the seed whatever the doses (a save/restore
                    keyed on X_0 alone); advertise it with --save-restore
    early_truncate  with continue_while, stop after hour 1 even when a path still holds
Wrong twins that speak the protocol perfectly (the check's behaviour rows must name them):

    shifted         hours shifted by one: the answer's hour 1 is X_0, hour h the good hour h-1
    dose2_ignored   the hour-2 dose is ignored (the hour-1 dose reused for hour 2)
    glucose_mmol    Glucose in mmol/L (the good value / 18.016), still labelled mg/dL
    x0_ignored      the same trajectory for every X_0 (a fixed patient replaces X_0)
    vaso_sign       the vasopressor lowers every output (its dose enters with a minus sign)
    fluid_tiny      the IV fluid's effect 1000x too small (mL/h read as L/h)
    vaso_ignored    the vasopressor changes nothing
    dose_lag        the dose of hour h acts in hour h + 1 (hour 1 sees no drug)
    batch_leak      inside a simulate_batch, a run starts where the previous run of the
                    batch left off in part (HR carries 1 % of the previous run's last HR)
    nacl_swap       Sodium and Chloride swapped in the answer
    drift           HR and Glucose grow by half their hour-1 value every hour after hour 1
Whole-twin modes (selector ignored): ``bad_hello`` (hello lacks HR),
``bad_units`` (HR in Hz), ``bad_protocol`` (hello says protocol 2), ``no_version`` (hello
has no version),
``no_hello`` (exit at once), ``unflushed`` (never flush stdout: answers sit in the pipe's
buffer until the twin exits), ``no_bye`` (shutdown is ignored: no bye, no exit until
stdin closes), ``silent_unknown`` (an unknown op gets no answer). ``--hello-delay S``
waits S seconds before each hello answer (a twin that takes long to start, but flushes).

``--batch N`` advertises ``capabilities.batch: N`` and answers
``simulate_batch`` messages run by run with the same modes: ``crash`` and
``hang`` kill or stall the whole batch, ``garbage`` and ``malformed`` replace
the whole batch answer, the other faults spoil only their own result.

``--engine-hours FILE`` appends, per request, the hours a save/restore twin like the Pulse
worker would simulate: it keeps the simulated dose prefixes of the current seed (X_0) only
and starts afresh when the seed changes, so a client that does not send an X_0's sequences
consecutively, in one pool, pays for shared prefixes again.

``--wobble W`` multiplies every non-demographic feature of hour h by 1 + W (-1)^(h + seed),
so runs cross the B-sets' medians from hour to hour (default 0: the formula above).
``--truncate`` advertises ``capabilities.truncate`` and stops a good run whose request
carries ``continue_while`` after the hours some path still needs (``runs.truncation``), as
the Pulse worker does; ``--engine-hours`` then counts only the hours it kept.

Every answer's message carries ``pid=<pid> start=<t0> end=<t1>`` (wall-clock
times around the work), so tests can check parallelism from the twins' own
timestamps; an answer given inside a simulate_batch of n runs adds ``batch=<n>``.
``--no-stamp`` leaves the stamp out: equal requests then get equal answers, failed runs'
messages included (a study whose results must be the same bytes run after run).
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from twinfalsify.runs.protocol import PROTOCOL_VERSION, ProtocolError, decode, encode
from twinfalsify.runs.truncation import hours_needed, parse_paths
from twinfalsify.schema import FEATURE_TABLE, FEATURES

RUN_MODES = (
    "ok", "crash", "close_stdout", "crash_once", "hang", "garbage", "malformed", "wrong_id",
    "wrong_features",
    "fewer_hours", "non_numeric", "irreversible", "init_failed", "error", "slow", "clamp",
    "batch_short", "implausible", "negative",
    "chatty", "nondeterministic", "lookahead", "batch_differs", "stale_restore",
    "early_truncate", "shifted", "dose2_ignored", "glucose_mmol", "x0_ignored",
    "vaso_sign", "fluid_tiny", "vaso_ignored", "dose_lag", "batch_leak", "nacl_swap", "drift",
)
DRIFTING = ("HR", "Glucose")
# the dose each mode answers as (iv, vaso) -> (iv, vaso)
DOSE_FAULTS = {"vaso_sign": (1.0, -1.0), "fluid_tiny": (1e-3, 1.0), "vaso_ignored": (1.0, 0.0)}
DEMOGRAPHICS = ("age", "sex", "weight")  # constant over a stay
TWIN_MODES = ("bad_hello", "bad_units", "bad_protocol", "no_hello", "no_bye",
              "silent_unknown", "unflushed", "no_version")


def expected(x0: dict[str, float], doses: Sequence[Sequence[float]], seed: int,
             wobble: float = 0.0) -> list[dict]:
    """The good-run answer: per-hour features (formula in the module docstring)."""
    hours, iv, vaso = [], 0.0, 0.0
    for h, (d_iv, d_vaso) in enumerate(doses, start=1):
        iv += float(d_iv)
        vaso += float(d_vaso)
        shift = 0.001 * (0.5 * h + 0.01 * iv + 10.0 * vaso + 0.001 * (seed % 97))
        factor = 1.0 + wobble * (-1) ** (h + seed)
        hours.append({f: float(x0[f]) if f in DEMOGRAPHICS else (float(x0[f]) + shift) * factor
                      for f in FEATURES})
    return hours


# x0_ignored: the patient every run starts from, whatever X_0 the request gives
FIXED_X0 = {"age": 65.0, "sex": 0.0, "weight": 80.0, "HR": 90.0, "SysBP": 115.0, "DiaBP": 60.0,
            "MeanBP": 78.0, "RR": 20.0, "Temp_C": 37.0, "Potassium": 4.1, "Sodium": 139.0,
            "Chloride": 104.0, "Glucose": 130.0, "Calcium": 8.4, "HCO3": 24.0, "paO2": 110.0,
            "paCO2": 40.0, "Arterial_pH": 7.38}
_PREFIXES: dict[str, Any] = {"seed": None, "done": set()}
_STALE: dict[int, list[dict]] = {}  # stale_restore: hours cached per seed, doses ignored
_LEAK: dict[str, float] = {}  # batch_leak: the last HR of the batch's previous run


def _log_engine_hours(path: Path, seed: int, doses: Sequence[Sequence[float]]) -> None:
    """Append the hours beyond the longest prefix this process holds for ``seed``."""
    if _PREFIXES["seed"] != seed:
        _PREFIXES.update(seed=seed, done=set())
    key = tuple(tuple(float(v) for v in d) for d in doses)
    s = len(key)
    while s > 0 and key[:s] not in _PREFIXES["done"]:
        s -= 1
    _PREFIXES["done"].update(key[:h] for h in range(s + 1, len(key) + 1))
    with path.open("a") as fh:
        fh.write(f"{len(key) - s}\n")


def _matches(selector: str, seed: int) -> bool:
    if selector in ("", "all"):
        return True
    if selector.startswith("%"):
        k, r = selector[1:].split("=")
        return seed % int(k) == int(r)
    return seed in {int(s) for s in selector.split(",") if s}


def _parse_modes(specs: Sequence[str]) -> list[tuple[str, str]]:
    out = []
    for spec in specs:
        mode, _, selector = spec.partition(":")
        if mode not in RUN_MODES + TWIN_MODES:
            raise SystemExit(f"faulty: unknown mode {mode!r}; choose from {RUN_MODES + TWIN_MODES}")
        out.append((mode, selector))
    return out


class _RawFault(Exception):
    """The answer stream itself is to be spoiled (mode garbage or malformed)."""

    def __init__(self, mode: str) -> None:
        super().__init__(mode)
        self.mode = mode


def _answer(msg: dict[str, Any], modes: list[tuple[str, str]], args: argparse.Namespace,
            batch: int = 0) -> tuple[dict[str, Any], str]:
    """The result answer to one simulate request and its mode; crash/hang happen here.

    batch: the size of the simulate_batch message it came in (0: a plain
    simulate); stamped into the message as ``batch=<n>`` so tests can see it.
    """
    out = sys.stdout
    seed = int(msg["seed"])
    mode = next((m for m, sel in modes if m in RUN_MODES and _matches(sel, seed)), "ok")
    t0 = time.time()
    x0, doses, hours_asked = msg["x0"], msg["doses"], int(msg["hours"])
    if mode == "x0_ignored":
        x0 = dict(FIXED_X0)
    if mode == "dose2_ignored" and len(doses) >= 2:
        doses = [doses[0], doses[0], *doses[2:]]
    elif mode in DOSE_FAULTS:
        gain = DOSE_FAULTS[mode]
        doses = [[float(d[0]) * gain[0], float(d[1]) * gain[1]] for d in doses]
    elif mode == "dose_lag":
        doses = [[0.0, 0.0], *doses[:-1]]
    hours = expected(x0, doses[:hours_asked], seed, args.wobble)
    if mode == "shifted":
        hours = [{f: float(x0[f]) for f in FEATURES}, *hours[:-1]]
    elif mode == "glucose_mmol":
        hours = [{**h, "Glucose": h["Glucose"] / 18.016} for h in hours]
    elif mode == "nacl_swap":
        hours = [{**h, "Sodium": h["Chloride"], "Chloride": h["Sodium"]} for h in hours]
    elif mode == "drift":
        hours = [{f: v * (1 + 0.5 * k) if f in DRIFTING else v for f, v in h.items()}
                 for k, h in enumerate(hours)]
    elif mode == "batch_leak" and batch:
        carry = _LEAK.get("HR")
        if carry is not None:
            hours = [{**h, "HR": h["HR"] + 0.01 * carry} for h in hours]
        _LEAK["HR"] = hours[-1]["HR"]
    cut = hours_asked
    if mode == "lookahead":  # every hour sees the whole request's IV total
        total = sum(float(d[0]) for d in doses[:hours_asked])
        hours = [{f: v if f in DEMOGRAPHICS else v + 1e-4 * total for f, v in h.items()}
                 for h in hours]
    elif mode == "nondeterministic":
        hours = [{f: v if f in DEMOGRAPHICS else v + 0.01 * random.random()
                  for f, v in h.items()} for h in hours]
    elif mode == "batch_differs" and batch:
        hours = [{**h, "HR": h["HR"] + 1.0} for h in hours]
    elif mode == "stale_restore":
        cached = _STALE.setdefault(seed, [])
        hours = cached[:hours_asked] + hours[len(cached):]
        cached.extend(hours[len(cached):])
    if args.truncate and msg.get("continue_while") is not None and mode in (
            "ok", "early_truncate"):
        cut = (1 if mode == "early_truncate" else
               hours_needed(parse_paths(msg["continue_while"]), hours, hours_asked))
    if args.engine_hours is not None:
        _log_engine_hours(args.engine_hours, seed, doses[:cut])
    answer: dict[str, Any] = {"op": "result", "id": msg["id"], "status": "ok",
                              "message": "", "hours": hours[:cut], "clamped": {}}
    if cut < hours_asked:
        answer["truncated"] = True
    if mode == "crash_once":
        if args.state_dir is None:
            raise SystemExit("faulty: crash_once needs --state-dir")
        marker = args.state_dir / f"seed-{seed}"
        if not marker.exists():
            marker.touch()
            mode = "crash"
    if mode == "crash":
        print(f"faulty: crashing on seed {seed}", file=sys.stderr, flush=True)
        out.write('{"op": "result", "id": ')  # half a line, then die
        out.flush()
        os._exit(3)
    if mode == "close_stdout":
        print(f"faulty: closing stdout on seed {seed}", file=sys.stderr, flush=True)
        out.flush()
        os.close(out.fileno())
        time.sleep(3600)
    if mode == "hang":
        print(f"faulty: hanging on seed {seed}", file=sys.stderr, flush=True)
        time.sleep(3600)
    if mode in ("garbage", "malformed"):
        raise _RawFault(mode)
    if mode == "slow":
        time.sleep(args.delay)
    if mode == "wrong_id":
        answer["id"] = f"{msg['id']}-other"
    elif mode == "wrong_features":
        answer["hours"] = [{("heart_rate" if k == "HR" else k): v for k, v in h.items()}
                           for h in hours]
    elif mode == "fewer_hours":
        answer["hours"] = hours[:-1]
    elif mode == "non_numeric":
        answer["hours"] = [{**h, "HR": "fast"} for h in hours]
    elif mode == "irreversible" and args.irreversible_hour <= hours_asked:
        answer.update(status="irreversible", hours=hours[: args.irreversible_hour - 1],
                      message=f"irreversible state during hour {args.irreversible_hour}")
    elif mode == "init_failed":
        answer.update(status="init_failed", hours=[], message="patient rejected")
    elif mode == "error":
        answer.update(status="error", hours=[], message="engine error")
    elif mode in ("implausible", "negative"):
        hours[min(1, len(hours) - 1)]["HR"] = 1e300 if mode == "implausible" else -500.0
    elif mode == "clamp" and float(x0["HR"]) > 110:
        answer["clamped"] = {"HR": [float(x0["HR"]), 110.0]}
        answer["hours"] = expected({**x0, "HR": 110.0}, doses[:hours_asked], seed)
    if args.no_stamp:
        return answer, mode
    stamp = f"pid={os.getpid()} start={t0:.6f} end={time.time():.6f}"
    if batch:
        stamp += f" batch={batch}"
    answer["message"] = f"{answer['message']} {stamp}".strip()
    return answer, mode


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="faulty_twin.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mode", action="append", default=[], help="MODE[:SELECTOR]")
    parser.add_argument("--delay", type=float, default=1.0, help="seconds per slow run")
    parser.add_argument("--hello-delay", type=float, default=0.0,
                        help="seconds before the hello answer (a slow start)")
    parser.add_argument("--irreversible-hour", type=int, default=2)
    parser.add_argument("--state-dir", type=Path, help="marker files for crash_once")
    parser.add_argument("--max-hours", type=int, default=None)
    parser.add_argument("--log-requests", type=Path, default=None,
                        help="append one line per simulate request to this file")
    parser.add_argument("--engine-hours", type=Path, default=None,
                        help="append the hours a prefix-caching engine would simulate")
    parser.add_argument("--batch", type=int, default=None,
                        help="advertise capabilities.batch = N (runs per simulate_batch)")
    parser.add_argument("--wobble", type=float, default=0.0,
                        help="scale hour h's features by 1 + W (-1)^(h + seed)")
    parser.add_argument("--truncate", action="store_true",
                        help="advertise capabilities.truncate and stop runs no path needs")
    parser.add_argument("--save-restore", action="store_true",
                        help="advertise capabilities.save_restore (the answers do not change)")
    parser.add_argument("--no-stamp", action="store_true",
                        help="no pid and times in the messages (deterministic answers)")
    args = parser.parse_args(argv)
    modes = _parse_modes(args.mode)
    twin_modes = {m for m, _ in modes if m in TWIN_MODES}
    print(f"faulty twin pid {os.getpid()} modes {args.mode}", file=sys.stderr, flush=True)
    if "no_hello" in twin_modes:
        print("faulty: no_hello mode, exiting", file=sys.stderr, flush=True)
        return 4

    out = sys.stdout
    if "unflushed" in twin_modes:  # block-buffered whatever PYTHONUNBUFFERED says
        out = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=65536)

    def send(message: dict[str, Any]) -> None:
        out.write(encode(message))
        if "unflushed" not in twin_modes:
            out.flush()

    def send_log(text: str) -> None:  # a log line where only protocol messages belong
        out.write(text + "\n")
        out.flush()

    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            msg = decode(line)
        except ProtocolError as exc:
            print(f"faulty: {exc}", file=sys.stderr, flush=True)
            continue
        if msg["op"] == "shutdown":
            if "no_bye" in twin_modes:
                print("faulty: no_bye mode, ignoring shutdown", file=sys.stderr, flush=True)
                continue
            send({"op": "bye"})
            return 0
        if msg["op"] == "hello":
            time.sleep(args.hello_delay)
            feats = [{"name": f.name, "unit": f.unit} for f in FEATURE_TABLE]
            if "bad_hello" in twin_modes:
                feats = [f for f in feats if f["name"] != "HR"]
            if "bad_units" in twin_modes:
                feats = [{**f, "unit": "Hz"} if f["name"] == "HR" else f for f in feats]
            caps: dict[str, Any] = {"save_restore": bool(args.save_restore)}
            if args.max_hours is not None:
                caps["max_hours"] = args.max_hours
            if args.batch is not None:
                caps["batch"] = args.batch
            if args.truncate:
                caps["truncate"] = True
            hello = {"op": "hello", "ok": True, "name": "faulty", "version": "1",
                     "protocol": 2 if "bad_protocol" in twin_modes else PROTOCOL_VERSION,
                     "features": feats, "capabilities": caps}
            if "no_version" in twin_modes:
                del hello["version"]
            send(hello)
            continue
        if msg["op"] == "simulate_batch":
            _LEAK.clear()  # batch_leak: the leak stays inside one batch
            results, raw, chatty = [], None, False
            for request in msg["requests"]:
                try:
                    answer, mode = _answer(request, modes, args, len(msg["requests"]))
                except _RawFault as fault:
                    raw = raw or fault.mode
                    continue
                chatty = chatty or mode == "chatty"
                if mode != "batch_short":
                    results.append(answer)
            batch_answer = {"op": "results", "results": results}
            if raw == "garbage":
                out.write("this is not JSON, it is a log line on stdout\n")
                out.flush()
            elif raw == "malformed":
                out.write(encode(batch_answer)[:40] + "\n")
                out.flush()
            else:
                send(batch_answer)
                if chatty:
                    send_log("INFO simulated a batch")
            continue
        if msg["op"] == "simulate" and args.log_requests is not None:
            with args.log_requests.open("a") as fh:
                fh.write(f"{msg['seed']}\n")
        if msg["op"] != "simulate":
            if "silent_unknown" not in twin_modes:
                send({"op": "error", "message": f"unknown op {msg['op']!r}"})
            continue
        try:
            answer, mode = _answer(msg, modes, args)
        except _RawFault as fault:
            if fault.mode == "garbage":
                out.write("this is not JSON, it is a log line on stdout\n")
            else:
                good = {"op": "result", "id": msg["id"], "status": "ok", "message": "",
                        "hours": expected(msg["x0"], msg["doses"][: int(msg["hours"])],
                                          int(msg["seed"])), "clamped": {}}
                out.write(encode(good)[:40] + "\n")
            out.flush()
            continue
        send(answer)
        if mode == "chatty":
            send_log(f"INFO simulated {msg['id']}")
    out.flush()  # what a buffered twin's exit does: stdin closed, buffer written
    return 0


if __name__ == "__main__":
    sys.exit(main())
