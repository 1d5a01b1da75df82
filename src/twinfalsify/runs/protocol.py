"""The twin protocol, version 1: JSON Lines over a subprocess's stdin/stdout.

One JSON object per line in each direction; logs go to stderr, never stdout.

    -> {"op": "hello", "protocol": 1}
    <- {"op": "hello", "ok": true, "name": str, "version": str, "protocol": 1,
        "features": [{"name": str, "unit": str}, ...],
        "capabilities": {"save_restore": bool, "max_hours": int, "batch": int}}
    -> {"op": "simulate", "id": str, "x0": {feature: value, ...},
        "doses": [[iv_mL_per_h, vaso_ug_per_kg_min], ...], "hours": t, "seed": int,
        "continue_while": [[[feature, ">"|"<="|"any", number], ...], ...]}  # optional
    <- {"op": "result", ..., "truncated": true}   # status ok, fewer hours: see below
    <- {"op": "result", "id": str, "status": "ok"|"init_failed"|"irreversible"|"error",
        "message": str, "hours": [{feature: value, ...}, ...],   # completed hours 1..s
        "clamped": {feature: [given, used], ...}}
    -> {"op": "simulate_batch", "requests": [<simulate request>, ...]}   # optional
    <- {"op": "results", "results": [<result answer>, ...]}             # same order
    -> {"op": "simulate_batch", "requests": [...], "answer": "arrays"}  # optional
    <- {"op": "results", "answer": "arrays", "ids": [...], "status": [...],
        "message": [...], "hours": [s_1, ...], "features": [name, ...],
        "values": base64(float64 little-endian, run by run, hour by hour, feature by
        feature), "clamped": [{...}, ...], "truncated": [bool, ...]}   # or as above
    -> {"op": "shutdown"}
    <- {"op": "bye"}

``hours`` holds every hour that completed before a failure, so prefix nodes of
a failed run stay usable. ``continue_while`` (sent only to a twin whose hello advertises
``capabilities.truncate``) lets the twin stop a run once no path of boxes still holds on
its completed hours (``runs.truncation``): it answers status ok with those hours and
``"truncated": true``, which the caller checks against the same rule. The caller adds
"timeout" when a run exceeds its time limit. ``simulate_batch`` is an optional
capability within version 1: the caller sends it only to a twin whose hello advertises
``capabilities.batch``
> 1 (``serve_forever`` answers it for every twin). ``"answer": "arrays"`` is asked only of
a twin whose hello advertises ``capabilities.arrays``: the same results as columns, the
numbers as raw float64 bytes, which spares both sides formatting and parsing every number
as text; a twin may still answer with the plain list, and the caller accepts both. See
docs/reference/twin-protocol.md for the full description.
"""

from __future__ import annotations

import base64
import gc
import json
import math
import sys
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import IO, Any

import numpy as np

from twinfalsify.runs.truncation import hours_needed

PROTOCOL_VERSION = 1
FAILURE_STATUSES = ("init_failed", "irreversible", "error")
ARRAYS = "arrays"  # the capability, and the simulate_batch "answer" asking for it


class ProtocolError(RuntimeError):
    """A message that does not follow the protocol."""


def encode(message: dict[str, Any]) -> str:
    return json.dumps(message, separators=(",", ":"), allow_nan=False) + "\n"


def decode(line: str) -> dict[str, Any]:
    try:
        msg = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ProtocolError(
            f"not JSON: stdout must carry only protocol JSON (logs go to stderr): got "
            f"{line[:200]!r} ({exc.msg})"
        ) from None
    if not isinstance(msg, dict) or "op" not in msg:
        raise ProtocolError(f"not a protocol message (no 'op'): {line[:200]!r}")
    return msg


def _hour_objects(fields: dict[str, Any]) -> dict[str, Any]:
    """Result fields with ``hours`` as the protocol's objects {feature: value}.

    A server's simulate functions may return ``values`` (array (hours, len(columns))) and
    ``columns`` instead of ``hours``: converted here, once, only for a plain answer."""
    if "values" not in fields:
        return fields
    out = {k: v for k, v in fields.items() if k not in ("values", "columns")}
    cols = list(fields["columns"])
    out["hours"] = [dict(zip(cols, row, strict=True))
                    for row in np.asarray(fields["values"], float).tolist()]
    return out


def _arrays_answer(requests: list[dict[str, Any]], fields: list[dict[str, Any]]
                   ) -> dict[str, Any] | None:
    """The "arrays" form of a batch's results, or None when the runs do not share one list
    of features (the plain answer is sent instead)."""
    cols: list[str] | None = None
    blocks = []
    for f in fields:
        if "values" in f:
            names, vals = list(f["columns"]), np.asarray(f["values"], float)
        else:
            hours = f.get("hours") or []
            if not hours:
                blocks.append(np.empty((0, 0)))
                continue
            names = list(hours[0])
            if any(list(h) != names for h in hours):
                return None
            vals = np.array([list(h.values()) for h in hours], dtype=float)
        if len(vals) == 0:
            blocks.append(np.empty((0, 0)))
            continue
        if cols is None:
            cols = names
        elif names != cols:
            return None
        blocks.append(vals)
    cols = cols or []
    flat = np.concatenate([b.reshape(-1) for b in blocks]) if blocks else np.empty(0)
    return {
        "op": "results", "answer": ARRAYS,
        "ids": [r.get("id") for r in requests],
        "status": [f["status"] for f in fields],
        "message": [f.get("message", "") for f in fields],
        "hours": [len(b) for b in blocks],
        "features": cols,
        "values": base64.b64encode(flat.astype("<f8").tobytes()).decode("ascii"),
        "clamped": [f.get("clamped", {}) for f in fields],
        "truncated": [bool(f.get("truncated", False)) for f in fields],
    }


def _error_fields(exc: BaseException) -> dict[str, Any]:
    return {"status": "error", "message": f"{type(exc).__name__}: {exc}", "hours": [],
            "clamped": {}}


def _simulate_one(
    simulate: Callable[[dict[str, Any]], dict[str, Any]], request: Any
) -> dict[str, Any]:
    """One result answer; an exception inside ``simulate`` becomes an "error" result."""
    if not isinstance(request, dict):
        return {"op": "result", "id": None, "status": "error",
                "message": f"request must be an object, got {type(request).__name__}",
                "hours": [], "clamped": {}}
    try:
        fields = _hour_objects(simulate(request))
    except Exception as exc:  # noqa: BLE001 - reported to the caller, never swallowed
        fields = _error_fields(exc)
    return {"op": "result", "id": request.get("id"), **fields}


def _answer_batch(
    msg: dict[str, Any],
    simulate: Callable[[dict[str, Any]], dict[str, Any]],
    simulate_batch: Callable[[list[dict[str, Any]]], list[dict[str, Any]]] | None,
) -> dict[str, Any]:
    """The "results" answer to a simulate_batch message.

    With ``simulate_batch`` the whole batch is computed in one call; if that
    call raises or returns the wrong number of results, every request is
    answered on its own by ``simulate`` instead, so one bad request never
    costs the other runs of its batch their results.
    """
    requests = msg.get("requests")
    if not isinstance(requests, list):
        return {"op": "error",
                "message": f"simulate_batch field 'requests' must be a list, got "
                           f"{type(requests).__name__}"}
    if simulate_batch is not None and all(isinstance(r, dict) for r in requests):
        try:
            fields = simulate_batch(requests)
        except Exception as exc:  # noqa: BLE001 - falls back to one request at a time
            print(f"simulate_batch failed ({type(exc).__name__}: {exc}); answering the "
                  "batch one request at a time", file=sys.stderr, flush=True)
            fields = None
        if fields is not None and len(fields) == len(requests):
            if msg.get("answer") == ARRAYS:
                packed = _arrays_answer(requests, fields)
                if packed is not None:
                    return packed
            return {"op": "results", "results": [
                {"op": "result", "id": r.get("id"), **_hour_objects(f)}
                for r, f in zip(requests, fields, strict=True)
            ]}
    return {"op": "results", "results": [_simulate_one(simulate, r) for r in requests]}


def serve_forever(
    hello: Callable[[], dict[str, Any]],
    simulate: Callable[[dict[str, Any]], dict[str, Any]],
    stdin: IO[str] | None = None,
    stdout: IO[str] | None = None,
    *,
    simulate_batch: Callable[[list[dict[str, Any]]], list[dict[str, Any]]] | None = None,
) -> int:
    """Answer protocol requests until shutdown or end of input; return an exit code.

    ``hello()`` returns the hello answer's fields, or raises when the twin cannot run at
    all (missing engine, bad data root): the answer is then ``ok: false`` with the
    exception's text as ``message``, and the server exits with code 2, so the caller stops
    at once instead of retrying every run. ``simulate(request)`` returns
    the result's fields (status, message, hours, clamped). An exception inside
    ``simulate`` becomes an "error" result for that request, not a dead worker.
    ``simulate_batch(requests)``, optional, returns one such fields object per
    request, in order (a vectorised twin computes a batch at once); without it
    a "simulate_batch" message is answered by calling ``simulate`` per request,
    so every twin served here accepts batches (whether the caller sends any
    depends on the ``batch`` capability the hello advertises). The process's heap is frozen
    first (:func:`gc.freeze`, as :func:`twinfalsify.io.freeze_heap` does without importing
    pandas): the twin lives as long as the process.
    """
    gc.freeze()
    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout
    for line in stdin:
        if not line.strip():
            continue
        try:
            msg = decode(line)
        except ProtocolError as exc:
            print(f"protocol error: {exc}", file=sys.stderr)
            continue
        op = msg["op"]
        if op == "hello":
            try:
                answer = {"op": "hello", "ok": True, "protocol": PROTOCOL_VERSION, **hello()}
            except Exception as exc:  # noqa: BLE001 - the twin cannot run: say why, then stop
                stdout.write(encode({"op": "hello", "ok": False, "protocol": PROTOCOL_VERSION,
                                     "message": str(exc) or type(exc).__name__}))
                stdout.flush()
                print(f"hello failed: {exc}", file=sys.stderr, flush=True)
                return 2
        elif op == "simulate":
            answer = _simulate_one(simulate, msg)
        elif op == "simulate_batch":
            answer = _answer_batch(msg, simulate, simulate_batch)
        elif op == "shutdown":
            stdout.write(encode({"op": "bye"}))
            stdout.flush()
            return 0
        else:
            answer = {"op": "error", "message": f"unknown op {op!r}"}
        stdout.write(encode(answer))
        stdout.flush()
    return 0


# ---------------------------------------------------------------------------
# Client-side validation (used by runs.worker). Every check raises
# ProtocolError with a message naming the field and the problem, so the
# runner can record it as the run's "error" message.

RESULT_STATUSES = ("ok", *FAILURE_STATUSES)


def _is_number(value: Any) -> bool:
    # bool is an int subclass in Python; a twin sending true/false for a
    # feature value is broken, not numeric.
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_hello(
    msg: dict[str, Any], required: Sequence[str], units: Mapping[str, str]
) -> dict[str, Any]:
    """Validate a hello answer; return it with defaults filled in.

    The twin must speak protocol ``PROTOCOL_VERSION``, declare every feature in
    ``required`` (it may declare more), and use, for every declared feature
    that appears in ``units``, exactly that unit (the trajectory contract's
    MIMIC units: a twin converts to them, the caller never guesses).
    """
    if msg.get("op") != "hello":
        raise ProtocolError(f"expected a hello answer, got op {msg.get('op')!r}")
    if msg.get("ok") is not True:
        raise ProtocolError(f"hello answer has ok = {msg.get('ok')!r}: {msg.get('message', '')}")
    if msg.get("protocol") != PROTOCOL_VERSION:
        raise ProtocolError(
            f"twin speaks protocol {msg.get('protocol')!r}; this runner speaks {PROTOCOL_VERSION}"
        )
    for key in ("name", "version"):
        if not isinstance(msg.get(key), str):
            raise ProtocolError(f"hello field {key!r} must be a string, got {msg.get(key)!r}")
    feats = msg.get("features")
    if not isinstance(feats, list) or not all(
        isinstance(f, dict) and isinstance(f.get("name"), str) and isinstance(f.get("unit"), str)
        for f in feats
    ):
        raise ProtocolError(
            "hello field 'features' must be a list of {\"name\": str, \"unit\": str} objects"
        )
    declared = {f["name"]: f["unit"] for f in feats}
    missing = [name for name in required if name not in declared]
    if missing:
        raise ProtocolError(f"hello does not declare required feature(s) {', '.join(missing)}")
    wrong = [
        f"{name} in {unit!r} (expected {units[name]!r})"
        for name, unit in declared.items()
        if name in units and unit != units[name]
    ]
    if wrong:
        raise ProtocolError(f"hello declares wrong unit(s): {'; '.join(wrong)}")
    caps = msg.get("capabilities", {})
    if not isinstance(caps, dict):
        raise ProtocolError(f"hello field 'capabilities' must be an object, got {caps!r}")
    # "batch" is not filled in (a hello without it reads as before); callers
    # use caps.get("batch", 1).
    caps = {"save_restore": False, "max_hours": None, **caps}
    if not isinstance(caps["save_restore"], bool):
        raise ProtocolError("capability 'save_restore' must be true or false")
    if not isinstance(caps.get("truncate", False), bool):
        raise ProtocolError("capability 'truncate' must be true or false")
    if caps["max_hours"] is not None and not (
        isinstance(caps["max_hours"], int) and caps["max_hours"] >= 1
    ):
        raise ProtocolError("capability 'max_hours' must be a positive integer or absent")
    if not isinstance(caps.get(ARRAYS, False), bool):
        raise ProtocolError(f"capability {ARRAYS!r} must be true or false")
    batch = caps.get("batch", 1)
    if not (isinstance(batch, int) and not isinstance(batch, bool) and batch >= 1):
        raise ProtocolError(
            f"capability 'batch' must be a positive integer (runs per simulate_batch "
            f"message) or absent, got {batch!r}"
        )
    return {**msg, "capabilities": caps, "declared_units": declared}


def check_results(msg: dict[str, Any], n: int) -> list[Any]:
    """Validate a simulate_batch answer's envelope; return its ``n`` result objects.

    Each result is then checked on its own with ``check_result`` (so one bad
    result does not condemn the others).
    """
    if msg.get("op") != "results":
        raise ProtocolError(
            f"expected op 'results' (answer to simulate_batch), got {msg.get('op')!r}: "
            f"{msg.get('message', '')}"
        )
    results = msg.get("results")
    if not isinstance(results, list):
        raise ProtocolError(f"field 'results' must be a list, got {type(results).__name__}")
    if len(results) != n:
        raise ProtocolError(f"{len(results)} results for a batch of {n} requests")
    return results


_LAYOUTS: dict[tuple, tuple[np.ndarray, np.ndarray] | None] = {}


def _fast_values(
    rows: list[Any], required: Sequence[str], declared: Collection[str], columns: Sequence[str]
) -> np.ndarray | None:
    """Hour values in ``columns`` order when every rule of check_result holds, else None.

    The common case at C speed (a batch of thousands of runs is checked
    value by value otherwise): every hour an object with the same keys, in
    the same order, all declared, every required one present, every value a
    finite int or float (not bool, which is an int subclass). None sends the
    caller to the checking loop, which names the first problem.
    """
    if not rows:
        return np.empty((0, len(columns)))
    first = rows[0]
    if type(first) is not dict:
        return None
    keys = tuple(first)
    cache_key = (keys, tuple(required), tuple(declared), tuple(columns))
    layout = _LAYOUTS.get(cache_key, False)
    if layout is False:
        ok = set(keys) <= set(declared) and set(required) <= set(keys)
        index = {name: j for j, name in enumerate(columns)}
        src = [j for j, k in enumerate(keys) if k in index]
        layout = (np.array(src, dtype=int), np.array([index[keys[j]] for j in src], dtype=int)
                  ) if ok else None
        if len(_LAYOUTS) < 64:  # a twin uses one or two key orders; bound it anyway
            _LAYOUTS[cache_key] = layout
    if layout is None:
        return None
    if any(type(r) is not dict or tuple(r) != keys for r in rows):
        return None
    flat = [v for r in rows for v in r.values()]
    if not set(map(type, flat)) <= {float, int}:
        return None
    try:
        arr = np.array(flat, dtype=float).reshape(len(rows), len(keys))
    except OverflowError:
        return None
    if not np.isfinite(arr).all():
        return None
    values = np.full((len(rows), len(columns)), np.nan)
    values[:, layout[1]] = arr[:, layout[0]]
    return values


def _checked_values(
    rows: list[Any], required: Sequence[str], declared: Collection[str], columns: Sequence[str]
) -> np.ndarray:
    """Hour values in ``columns`` order, checked one by one; raises naming the first problem."""
    index = {name: j for j, name in enumerate(columns)}
    values = np.full((len(rows), len(columns)), np.nan)
    declared_set = set(declared)
    for h, row in enumerate(rows, start=1):
        if not isinstance(row, dict):
            raise ProtocolError(f"hour {h} must be an object of feature values")
        unknown = sorted(set(row) - declared_set)
        if unknown:
            raise ProtocolError(f"hour {h} has unknown feature(s) {', '.join(unknown)}")
        missing = [name for name in required if name not in row]
        if missing:
            raise ProtocolError(f"hour {h} lacks feature(s) {', '.join(missing)}")
        for name, value in row.items():
            if not _is_number(value) or not math.isfinite(value):
                raise ProtocolError(
                    f"hour {h} feature {name} is not a finite number: {value!r}"
                )
            if name in index:
                values[h - 1, index[name]] = float(value)
    return values


@dataclass
class CheckedResult:
    """A validated simulate answer: ``values`` is (hours completed, len(columns))."""

    status: str
    message: str
    values: np.ndarray
    clamped: str  # JSON object text


def check_result(
    msg: dict[str, Any],
    request_id: str,
    hours: int,
    required: Sequence[str],
    declared: Collection[str],
    columns: Sequence[str],
    continue_while: list | None = None,
) -> CheckedResult:
    """Validate a simulate answer for ``request_id`` that asked for ``hours`` hours.

    Rules (docs/reference/twin-protocol.md, "result"): op is "result"; id echoes the
    request; status is one of RESULT_STATUSES; "hours" is a list of at most
    ``hours`` objects, exactly ``hours`` when status is "ok"; every hour object
    holds a finite number for every feature in ``required`` and no feature the
    twin did not declare in hello (``declared``); "clamped" is an object
    {feature: [given, used]}. Values are returned in ``columns`` order, NaN for
    a column the twin did not report.
    """
    if not isinstance(msg, dict):
        raise ProtocolError(f"a result must be an object, got {type(msg).__name__}")
    if msg.get("op") != "result":
        raise ProtocolError(
            f"expected op 'result', got {msg.get('op')!r}: {msg.get('message', '')}"
        )
    if msg.get("id") != request_id:
        raise ProtocolError(f"answer id {msg.get('id')!r} does not match request id {request_id!r}")
    status = msg.get("status")
    if status not in RESULT_STATUSES:
        raise ProtocolError(
            f"status {status!r} is not one of {', '.join(RESULT_STATUSES)}"
        )
    message = msg.get("message", "")
    if not isinstance(message, str):
        raise ProtocolError(f"field 'message' must be a string, got {type(message).__name__}")
    rows = msg.get("hours")
    if not isinstance(rows, list):
        raise ProtocolError(f"field 'hours' must be a list, got {type(rows).__name__}")
    if len(rows) > hours:
        raise ProtocolError(f"{len(rows)} hours returned, more than the {hours} asked for")
    truncated = status == "ok" and len(rows) < hours
    if truncated and (msg.get("truncated") is not True or continue_while is None):
        raise ProtocolError(
            f"status ok but only {len(rows)} of {hours} hours returned "
            "(a twin that stops early must report init_failed, irreversible or error, or "
            "'truncated': true when the request's continue_while allows it)"
        )
    values = _fast_values(rows, required, declared, columns)
    if values is None:
        values = _checked_values(rows, required, declared, columns)
    if truncated:
        need = hours_needed(continue_while, values, hours, columns)
        if len(rows) < need:
            raise ProtocolError(
                f"truncated after hour {len(rows)}, but a continue_while path still holds "
                f"(hour {need} is needed)")
    return CheckedResult(status, message, values, _clamped_text(msg.get("clamped", {})))


def _clamped_text(clamped: Any) -> str:
    """A result's ``clamped`` record as JSON text; raises unless {feature: [given, used]}."""
    if not isinstance(clamped, dict) or not all(
        isinstance(v, list) and len(v) == 2 and all(_is_number(x) for x in v)
        for v in clamped.values()
    ):
        raise ProtocolError(
            f"field 'clamped' must be an object {{feature: [given, used]}}, got {clamped!r}"
        )
    return json.dumps(clamped, sort_keys=True) if clamped else "{}"


def check_array_results(
    msg: dict[str, Any],
    request_ids: Sequence[str],
    hours: Sequence[int],
    required: Sequence[str],
    declared: Collection[str],
    columns: Sequence[str],
    continue_while: Sequence[list | None] | None = None,
) -> list[CheckedResult | ProtocolError]:
    """Validate a simulate_batch answer in the "arrays" form; one entry per request.

    The answer's envelope (op, the lists' lengths, the feature list, the bytes of
    ``values``) must hold, else ProtocolError is raised: the batch as a whole cannot be
    trusted. Each run is then held to check_result's rules (id, status, message, at most
    the hours asked for and all of them for "ok" unless truncated as allowed, finite
    values, ``clamped``); a run that breaks one gets its ProtocolError in the list, to be
    asked again on its own, as a broken result of a plain answer is.
    """
    n = len(request_ids)
    if msg.get("op") != "results" or msg.get("answer") != ARRAYS:
        raise ProtocolError(f"expected op 'results' with answer 'arrays', got op "
                            f"{msg.get('op')!r}: {msg.get('message', '')}")
    lists = {k: msg.get(k) for k in ("ids", "status", "message", "hours", "clamped",
                                      "truncated")}
    for key, value in lists.items():
        if not isinstance(value, list) or len(value) != n:
            raise ProtocolError(f"field {key!r} must be a list of {n} entries (one per "
                                f"request), got {type(value).__name__}"
                                f"{f' of {len(value)}' if isinstance(value, list) else ''}")
    feats = msg.get("features")
    if not isinstance(feats, list) or not all(isinstance(f, str) for f in feats) \
            or len(set(feats)) != len(feats):
        raise ProtocolError("field 'features' must be a list of distinct feature names")
    unknown = sorted(set(feats) - set(declared))
    if unknown:
        raise ProtocolError(f"field 'features' has unknown feature(s) {', '.join(unknown)}")
    counts = lists["hours"]
    if not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts):
        raise ProtocolError("field 'hours' must hold each run's number of hours (integers >= 0)")
    try:
        raw = base64.b64decode(msg.get("values"), validate=True)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"field 'values' must be base64 text: {exc}") from None
    total = sum(counts) * len(feats)
    if len(raw) != 8 * total:
        raise ProtocolError(f"field 'values' holds {len(raw) // 8} numbers; the hours and "
                            f"features ask for {total}")
    rows = np.frombuffer(raw, dtype="<f8").astype(float).reshape(sum(counts), len(feats))
    missing = [name for name in required if name not in feats]
    index = {name: j for j, name in enumerate(columns)}
    src = [j for j, f in enumerate(feats) if f in index]
    mapped = np.full((len(rows), len(columns)), np.nan)  # the batch's hours in columns order
    mapped[:, [index[feats[j]] for j in src]] = rows[:, src]
    finite = np.isfinite(rows).all(axis=1)
    out: list[CheckedResult | ProtocolError] = []
    start = 0
    for i in range(n):
        s = slice(start, start + counts[i])
        start = s.stop
        try:
            out.append(_array_result(
                lists["ids"][i], lists["status"][i], lists["message"][i], mapped[s],
                None if finite[s].all() else rows[s], lists["clamped"][i],
                lists["truncated"][i], request_ids[i], int(hours[i]), missing, feats, columns,
                None if continue_while is None else continue_while[i]))
        except ProtocolError as exc:
            out.append(exc)
    return out


def _array_result(rid: Any, status: Any, message: Any, values: np.ndarray,
                  broken: np.ndarray | None, clamped: Any, truncated: Any, request_id: str,
                  hours: int, missing: list[str], feats: list[str], columns: Sequence[str],
                  continue_while: list | None) -> CheckedResult:
    """One run of an "arrays" answer under check_result's rules: ``values`` its hours in
    ``columns`` order; ``broken`` its hours as sent when one holds a non-finite number."""
    if rid != request_id:
        raise ProtocolError(f"answer id {rid!r} does not match request id {request_id!r}")
    if status not in RESULT_STATUSES:
        raise ProtocolError(f"status {status!r} is not one of {', '.join(RESULT_STATUSES)}")
    if not isinstance(message, str):
        raise ProtocolError(f"field 'message' must be a string, got {type(message).__name__}")
    s = len(values)
    if s > hours:
        raise ProtocolError(f"{s} hours returned, more than the {hours} asked for")
    if s and missing:
        raise ProtocolError(f"hour 1 lacks feature(s) {', '.join(missing)}")
    if broken is not None:
        h, j = np.argwhere(~np.isfinite(broken))[0]
        raise ProtocolError(f"hour {h + 1} feature {feats[j]} is not a finite number: "
                            f"{broken[h, j]!r}")
    cut = status == "ok" and s < hours
    if cut and (truncated is not True or continue_while is None):
        raise ProtocolError(
            f"status ok but only {s} of {hours} hours returned "
            "(a twin that stops early must report init_failed, irreversible or error, or "
            "'truncated': true when the request's continue_while allows it)"
        )
    if cut:
        need = hours_needed(continue_while, values, hours, columns)
        if s < need:
            raise ProtocolError(
                f"truncated after hour {s}, but a continue_while path still holds "
                f"(hour {need} is needed)")
    return CheckedResult(status, message, values, _clamped_text(clamped))
