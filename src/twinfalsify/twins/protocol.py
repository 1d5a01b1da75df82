"""The twin protocol, version 1: JSON Lines over a subprocess's stdin/stdout.

One JSON object per line in each direction; logs go to stderr, never stdout.

    -> {"op": "hello", "protocol": 1}
    <- {"op": "hello", "ok": true, "name": str, "version": str, "protocol": 1,
        "features": [{"name": str, "unit": str}, ...],
        "capabilities": {"save_restore": bool, "max_hours": int}}
    -> {"op": "simulate", "id": str, "x0": {feature: value, ...},
        "doses": [[iv_mL_per_h, vaso_ug_per_kg_min], ...], "hours": t, "seed": int}
    <- {"op": "result", "id": str, "status": "ok"|"init_failed"|"irreversible"|"error",
        "message": str, "hours": [{feature: value, ...}, ...],   # completed hours 1..s
        "clamped": {feature: [given, used], ...}}
    -> {"op": "shutdown"}
    <- {"op": "bye"}

``hours`` holds every hour that completed before a failure, so prefix nodes of
a failed run stay usable. The caller adds "timeout" when a run exceeds its time
limit. See docs/twin-protocol.md for the full description.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import IO, Any

PROTOCOL_VERSION = 1
FAILURE_STATUSES = ("init_failed", "irreversible", "error")


class ProtocolError(RuntimeError):
    """A message that does not follow the protocol."""


def encode(message: dict[str, Any]) -> str:
    return json.dumps(message, separators=(",", ":"), allow_nan=False) + "\n"


def decode(line: str) -> dict[str, Any]:
    try:
        msg = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"not JSON: {line[:200]!r} ({exc.msg})") from None
    if not isinstance(msg, dict) or "op" not in msg:
        raise ProtocolError(f"not a protocol message (no 'op'): {line[:200]!r}")
    return msg


def serve_forever(
    hello: Callable[[], dict[str, Any]],
    simulate: Callable[[dict[str, Any]], dict[str, Any]],
    stdin: IO[str] | None = None,
    stdout: IO[str] | None = None,
) -> int:
    """Answer protocol requests until shutdown or end of input; return an exit code.

    ``hello()`` returns the hello answer's fields; ``simulate(request)`` returns
    the result's fields (status, message, hours, clamped). An exception inside
    ``simulate`` becomes an "error" result for that request, not a dead worker.
    """
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
            answer = {"op": "hello", "ok": True, "protocol": PROTOCOL_VERSION, **hello()}
        elif op == "simulate":
            try:
                fields = simulate(msg)
            except Exception as exc:  # noqa: BLE001 - reported to the caller, never swallowed
                fields = {
                    "status": "error",
                    "message": f"{type(exc).__name__}: {exc}",
                    "hours": [],
                    "clamped": {},
                }
            answer = {"op": "result", "id": msg.get("id"), **fields}
        elif op == "shutdown":
            stdout.write(encode({"op": "bye"}))
            stdout.flush()
            return 0
        else:
            answer = {"op": "error", "message": f"unknown op {op!r}"}
        stdout.write(encode(answer))
        stdout.flush()
    return 0
