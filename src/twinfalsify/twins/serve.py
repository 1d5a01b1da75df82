"""Serve a builtin twin over the protocol: ``python -m twinfalsify.twins.serve <name>``.

    python -m twinfalsify.twins.serve <name> [--spec JSON] [--context DIR]

builds the twin with ``twinfalsify.twins.registry.make_twin(name, spec,
context_dir)`` and answers protocol v1 requests (docs/twin-protocol.md) on
stdin/stdout until "shutdown" or end of input. Each request is simulated as a
batch of one run; builtin twins key their noise by (seed, dose prefix), so the
numbers are the same as in a vectorised in-process call.
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
from twinfalsify.schema import FEATURE_TABLE, FEATURES, T_MAX, TWIN_STATUSES
from twinfalsify.twins.base import Twin
from twinfalsify.twins.protocol import serve_forever


def handlers(
    twin: Twin, *, version: str = __version__, max_hours: int | None = T_MAX
) -> tuple[Callable[[], dict[str, Any]], Callable[[dict[str, Any]], dict[str, Any]]]:
    """The (hello, simulate) callables for ``serve_forever`` around an in-process Twin."""

    def hello() -> dict[str, Any]:
        caps: dict[str, Any] = {"save_restore": False}
        if max_hours is not None:
            caps["max_hours"] = max_hours
        return {
            "name": twin.name,
            "version": version,
            "features": [{"name": f.name, "unit": f.unit} for f in FEATURE_TABLE],
            "capabilities": caps,
        }

    def simulate(request: dict[str, Any]) -> dict[str, Any]:
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
        frame = pd.DataFrame([{f: float(x0[f]) for f in FEATURES}])
        res = twin.simulate(frame, doses[None], np.array([seed], dtype=np.uint64))
        status = str(res.status[0])
        message = str(res.message[0] or "")
        done = []
        for h in range(hours):
            row = res.features[0, h]
            if not np.isfinite(row).all():
                break
            done.append(dict(zip(FEATURES, map(float, row), strict=True)))
        if status not in TWIN_STATUSES or status == "timeout":
            message = f"twin returned status {status!r}: {message}"
            status = "error"
        if status == "ok" and len(done) < hours:
            status = "error"
            message = f"twin status ok but hour {len(done) + 1} has non-finite values"
        clamped = res.clamped[0]
        clamped = json.loads(clamped) if isinstance(clamped, str) else dict(clamped or {})
        return {"status": status, "message": message, "hours": done, "clamped": clamped}

    return hello, simulate


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="twinfalsify.twins.serve", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="builtin twin name (see twinfalsify.twins.registry)")
    parser.add_argument("--spec", default="{}", help="twin spec as a JSON object")
    parser.add_argument("--context", type=Path, default=None,
                        help="directory with the study's files a fitted twin needs")
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
    from twinfalsify.twins.registry import make_twin

    twin = make_twin(args.name, spec, args.context)
    print(f"serving twin {twin.name!r} (protocol v1)", file=sys.stderr, flush=True)
    return serve_forever(*handlers(twin), stdout=protocol_out)


if __name__ == "__main__":
    sys.exit(main())
