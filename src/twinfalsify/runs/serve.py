"""Serve a builtin twin over the protocol: ``python -m twinfalsify.runs.serve <name>``.

    python -m twinfalsify.runs.serve <name> [--spec JSON] [--context DIR]

builds the twin with ``twinfalsify.runs.registry.make_twin(name, spec,
context_dir)`` and answers protocol v1 requests (docs/reference/twin-protocol.md) on
stdin/stdout until "shutdown" or end of input. The hello advertises
``capabilities.batch`` = BATCH_MAX and ``capabilities.arrays``: a ``simulate_batch``
message is answered with ONE vectorised ``twin.simulate`` call per group of requests of
equal length (``batch_handler``), in arrays when the caller asks for them; a plain
``simulate`` as a batch of one run.
Builtin twins key their noise by (seed, dose prefix) and compute every run's
numbers independently of the others in its batch, so the numbers are the
same bits as in one vectorised in-process call, however runs are batched.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify import __version__
from twinfalsify.runs.protocol import ARRAYS, serve_forever
from twinfalsify.runs.truncation import hours_needed, parse_paths
from twinfalsify.schema import FEATURE_TABLE, FEATURES, T_MAX, TWIN_STATUSES, ContractError
from twinfalsify.twins.base import Twin

BATCH_MAX = 1000  # runs per simulate_batch message a served builtin twin accepts


Parsed = tuple[list[float], np.ndarray, int, int, list | None]


def _parse(request: dict[str, Any]) -> Parsed:
    """(x0 values in FEATURES order, doses (hours, 2), hours, seed) of a simulate request.

    Raises ValueError naming the field and the problem.
    """
    x0 = request.get("x0")
    if not isinstance(x0, dict):
        raise ValueError("request field 'x0' must be an object {feature: value}")
    missing = [f for f in FEATURES if f not in x0]
    if missing:
        raise ValueError(f"request x0 lacks feature(s) {', '.join(missing)}")
    hours = request.get("hours")
    doses = np.asarray(request.get("doses"), dtype=float)
    if not isinstance(hours, int) or hours < 1:
        raise ValueError(f"request field 'hours' must be a positive integer, got {hours!r}")
    if doses.shape != (hours, 2):
        raise ValueError(f"request doses must be {hours} pairs [iv, vaso]; got {doses.shape}")
    seed = request.get("seed")
    if not isinstance(seed, int) or not 0 <= seed < 2**64:
        raise ValueError(f"request field 'seed' must be an integer in [0, 2^64), got {seed!r}")
    paths = request.get("continue_while")
    paths = None if paths is None else parse_paths(paths)
    return [float(x0[f]) for f in FEATURES], doses, hours, seed, paths


def _fields(rows: np.ndarray, status: Any, message: Any, clamped: Any,
            hours: int) -> dict[str, Any]:
    """One run -> the result fields (status, message, values in FEATURES order, clamped);
    ``serve_forever`` turns the values into the answer's hour objects or arrays.

    rows: the run's finite leading hours (s, len(FEATURES)); a twin
    status outside TWIN_STATUSES (or "timeout", which only the caller may
    give) and "ok" with fewer than ``hours`` finite hours become "error".
    """
    status = str(status)
    message = str(message or "")
    if status not in TWIN_STATUSES or status == "timeout":
        message = f"twin returned status {status!r}: {message}"
        status = "error"
    if status == "ok" and len(rows) < hours:
        status = "error"
        message = f"twin status ok but hour {len(rows) + 1} has non-finite values"
    if isinstance(clamped, str):
        clamped = {} if clamped == "{}" else json.loads(clamped)
    else:
        clamped = dict(clamped or {})
    return {"status": status, "message": message, "values": rows, "columns": FEATURES,
            "clamped": clamped}


def _simulate_parsed(twin: Twin, parsed: list[Parsed]) -> list[dict[str, Any]]:
    """One vectorised ``twin.simulate`` over requests of equal length -> result fields.

    A request with ``continue_while`` is truncated after the hours it still needs
    (``runs.truncation``): a builtin twin computes whole paths at no cost, so it answers
    as an engine that stops the run there would."""
    hours = parsed[0][2]
    frame = pd.DataFrame([p[0] for p in parsed], columns=list(FEATURES))
    doses = np.stack([p[1] for p in parsed])
    seeds = np.array([p[3] for p in parsed], dtype=np.uint64)
    res = twin.simulate(frame, doses, seeds)
    if res.features.shape != (len(parsed), hours, len(FEATURES)):
        raise ValueError(f"twin returned features of shape {res.features.shape}, expected "
                         f"{(len(parsed), hours, len(FEATURES))}")
    # hours completed = the leading hours whose every feature is finite
    done = np.cumprod(np.isfinite(res.features).all(axis=2), axis=1).sum(axis=1)
    values = np.asarray(res.features, dtype=float)
    out = []
    for k, p in enumerate(parsed):
        rows = values[k, : done[k]]
        cut = hours
        if p[4] is not None and res.status[k] == "ok" and len(rows) == hours:
            cut = hours_needed(p[4], rows, hours)
        fields = _fields(rows[:cut], res.status[k], res.message[k], res.clamped[k], cut)
        if cut < hours:
            fields["truncated"] = True
        out.append(fields)
    return out


def batch_handler(twin: Twin) -> Callable[[list[dict[str, Any]]], list[dict[str, Any]]]:
    """The ``simulate_batch`` callable for ``serve_forever`` around an in-process Twin.

    Requests are grouped by ``hours`` (one ``twin.simulate`` per group, since a
    Twin takes one dose array of shape (n, hours, 2)); results come back in
    request order. A request that does not parse gets its own "error" result;
    if the vectorised call of a group raises, that group's requests are
    simulated one at a time so each gets its own outcome.
    """

    def simulate_batch(requests: list[dict[str, Any]]) -> list[dict[str, Any]]:
        out: list[dict[str, Any] | None] = [None] * len(requests)
        groups: dict[int, list[int]] = {}
        parsed: dict[int, Parsed] = {}
        for k, request in enumerate(requests):
            try:
                parsed[k] = _parse(request)
            except Exception as exc:  # noqa: BLE001 - reported as this run's error
                out[k] = {"status": "error", "message": f"{type(exc).__name__}: {exc}",
                          "hours": [], "clamped": {}}
                continue
            groups.setdefault(parsed[k][2], []).append(k)
        for members in groups.values():
            try:
                fields = _simulate_parsed(twin, [parsed[k] for k in members])
            except Exception as exc:  # noqa: BLE001 - retried one run at a time below
                print(f"vectorised batch failed ({type(exc).__name__}: {exc}); "
                      "simulating its runs one at a time", file=sys.stderr, flush=True)
                fields = []
                for k in members:
                    try:
                        fields.extend(_simulate_parsed(twin, [parsed[k]]))
                    except Exception as one:  # noqa: BLE001 - this run's error
                        fields.append({"status": "error",
                                       "message": f"{type(one).__name__}: {one}",
                                       "hours": [], "clamped": {}})
            for k, f in zip(members, fields, strict=True):
                out[k] = f
        return out  # type: ignore[return-value]  # every slot filled above

    return simulate_batch


def handlers(
    twin: Twin, *, version: str = __version__, max_hours: int | None = T_MAX,
    batch: int | None = None,
) -> tuple[Callable[[], dict[str, Any]], Callable[[dict[str, Any]], dict[str, Any]]]:
    """The (hello, simulate) callables for ``serve_forever`` around an in-process Twin.

    batch: the ``capabilities.batch`` the hello advertises (None: not
    advertised, so callers send one run per message); pass
    ``simulate_batch=batch_handler(twin)`` to ``serve_forever`` with it.
    """

    def hello() -> dict[str, Any]:
        caps: dict[str, Any] = {"save_restore": False, "truncate": True}
        if max_hours is not None:
            caps["max_hours"] = max_hours
        if batch is not None:
            caps["batch"] = batch
            caps[ARRAYS] = True  # serve_forever answers a batch in arrays when asked
        return {
            "name": twin.name,
            "version": version,
            "features": [{"name": f.name, "unit": f.unit} for f in FEATURE_TABLE],
            "capabilities": caps,
        }

    def simulate(request: dict[str, Any]) -> dict[str, Any]:
        return _simulate_parsed(twin, [_parse(request)])[0]

    return hello, simulate


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="twinfalsify.runs.serve", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="twin name; also its kind (oracle, biased, fitted) "
                        "unless --spec gives one")
    parser.add_argument("--spec", default="{}",
                        help='twin spec as a JSON object, e.g. \'{"kind": "biased", '
                             '"shift": {"HR": 15}}\' (default: {"kind": NAME})')
    parser.add_argument("--context", type=Path, default=None,
                        help="the study's twin_context.json, or the results/<study>/ folder "
                             "holding it (written by rule twin_plan): the synthetic world's "
                             "config for oracle/biased, the D0 table for fitted")
    args = parser.parse_args(argv)
    try:
        spec = json.loads(args.spec)
    except json.JSONDecodeError as exc:
        parser.error(f"--spec is not JSON: {exc.msg}")
    if not isinstance(spec, dict):
        parser.error("--spec must be a JSON object")
    # stdout belongs to the protocol: anything the twin code prints goes to
    # stderr instead of corrupting the answer stream.
    protocol_out, sys.stdout = sys.stdout, sys.stderr
    # Imported here: the registry pulls in every builtin twin and is only
    # needed in the served process.
    from twinfalsify.runs.registry import make_twin

    spec.setdefault("kind", args.name)  # `serve oracle` means the oracle
    spec.pop("protocol", None)  # this process IS the served twin
    try:
        twin = make_twin(args.name, spec, args.context)
    except ContractError as exc:  # bad name, spec or context: one line, not a traceback
        sys.stdout = protocol_out
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    print(f"serving twin {twin.name!r} (protocol v1, batch {BATCH_MAX})", file=sys.stderr,
          flush=True)
    hello, simulate = handlers(twin, batch=BATCH_MAX)
    return serve_forever(hello, simulate, stdout=protocol_out,
                         simulate_batch=batch_handler(twin))


if __name__ == "__main__":
    sys.exit(main())
