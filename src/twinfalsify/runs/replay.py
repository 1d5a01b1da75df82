"""Serve recorded twin answers (``runs.record``) as a twin: the same study, replayed exactly.

    python -m twinfalsify.runs.replay --data DIR

DIR holds ``answers-*.jsonl`` written by ``python -m twinfalsify.runs.record``. A
``simulate`` request is answered from the recording of the same X_0 (every feature,
exactly) and the same doses:

1. a recorded request with the same doses and hours: its answer, unchanged;
2. else a recorded run whose first ``hours`` doses equal the request's: its first
   ``hours`` hours (a twin's hour h depends only on X_0 and doses 1..h; this is what
   prefix branching relies on too). If that run failed before hour ``hours``, its
   failure is returned with the hours it completed.

Anything else is an ``error`` result naming what the recording holds, never a guess.
The seed is ignored unless the recording shows that it matters (two answers to the same
X_0 and doses differ), then it is part of the match. So a replay reproduces the recorded
study (same plan, same seeds) for any twin, and other plans only for a deterministic twin
such as Pulse.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from twinfalsify.runs import protocol
from twinfalsify.schema import ContractError

BATCH = 1000  # lookups are cheap: let the runner send large batches


def _x0_key(x0: Any) -> str:
    return json.dumps(x0, sort_keys=True, separators=(",", ":"))


def _doses(request: dict[str, Any], hours: int) -> tuple[tuple[float, float], ...]:
    return tuple((float(a), float(b)) for a, b in request["doses"][:hours])


def _fields(answer: dict[str, Any]) -> dict[str, Any]:
    return {k: answer[k] for k in ("status", "message", "hours", "clamped") if k in answer}


class ReplayTwin:
    """Answers ``simulate`` requests from a recording folder."""

    def __init__(self, data_dir: str | Path, name: str | None = None):
        self.data_dir = Path(data_dir)
        files = sorted(self.data_dir.glob("answers*.jsonl"))
        if not files:
            raise ContractError(f"{self.data_dir}: no answers*.jsonl recording here (make one "
                                "with python -m twinfalsify.runs.record)")
        self.recorded_hello: dict[str, Any] | None = None
        runs: list[tuple[dict, dict]] = []
        for f in files:
            for n, line in enumerate(f.read_text().splitlines(), 1):
                if not line.strip():
                    continue
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError as exc:
                    raise ContractError(f"{f}:{n}: not JSON ({exc.msg})") from None
                if "hello" in rec:
                    self._add_hello(rec["hello"], f, n)
                elif "request" in rec and "answer" in rec:
                    runs.append((rec["request"], rec["answer"]))
                else:
                    raise ContractError(f"{f}:{n}: neither a hello nor a request/answer pair")
        if self.recorded_hello is None:
            raise ContractError(f"{self.data_dir}: the recording holds no hello answer")
        self.name = name or str(self.recorded_hello["name"])
        self.deterministic = self._is_deterministic(runs)
        self.runs: dict[str, list[tuple[int, tuple, int | None, dict]]] = {}
        for req, ans in runs:
            h = int(req["hours"])
            seed = None if self.deterministic else int(req.get("seed", 0))
            self.runs.setdefault(_x0_key(req["x0"]), []).append(
                (h, _doses(req, h), seed, _fields(ans)))
        self.n_runs = len(runs)

    def _add_hello(self, hello: dict[str, Any], f: Path, n: int) -> None:
        if not hello.get("ok"):
            return  # a refused start (e.g. a bad data root) recorded no runs
        keep = ("name", "version", "features")
        if self.recorded_hello is None:
            self.recorded_hello = hello
        elif any(hello.get(k) != self.recorded_hello.get(k) for k in keep):
            raise ContractError(f"{f}:{n}: hello differs from the first one recorded "
                                "(two twins or versions mixed in one recording)")

    @staticmethod
    def _is_deterministic(runs: list[tuple[dict, dict]]) -> bool:
        seen: dict[tuple, str] = {}
        for req, ans in runs:
            h = int(req["hours"])
            key = (_x0_key(req["x0"]), _doses(req, h), h)
            fields = json.dumps(_fields(ans), sort_keys=True)
            if seen.setdefault(key, fields) != fields:
                return False
        return True

    def hello(self) -> dict[str, Any]:
        h = self.recorded_hello or {}
        caps = dict(h.get("capabilities") or {})
        caps.update({"save_restore": False, "batch": BATCH})
        return {"name": self.name, "version": f"{h.get('version', '?')} (replayed)",
                "features": h.get("features", []), "capabilities": caps}

    def simulate(self, request: dict[str, Any]) -> dict[str, Any]:
        x0, hours = request.get("x0"), request.get("hours")
        if not isinstance(x0, dict) or not isinstance(hours, int) or hours < 1:
            raise ContractError("simulate request: needs x0 (object) and hours (int >= 1)")
        doses = _doses(request, hours)
        seed = None if self.deterministic else int(request.get("seed", 0))
        cands = [r for r in self.runs.get(_x0_key(x0), []) if r[2] == seed]
        if not cands:
            return self._miss(f"no recorded run with this X_0 ({_x0_key(x0)})")
        for h, d, _, ans in cands:
            if h == hours and d == doses:
                return ans
        for h, d, _, ans in cands:
            if h >= hours and d[:hours] == doses:
                done = ans.get("hours", [])
                if len(done) >= hours:
                    return {"status": "ok", "message": f"prefix of a recorded {h}-hour run",
                            "hours": done[:hours], "clamped": ans.get("clamped", {})}
                return ans  # it failed before hour `hours`: the same failure
        held = sorted({d for _, d, _, _ in cands})
        return self._miss(f"no recorded run of this X_0 with doses {list(doses)}; it holds "
                          f"doses {[list(d) for d in held]}")

    def _miss(self, what: str) -> dict[str, Any]:
        return {"status": "error", "hours": [], "clamped": {},
                "message": f"replay of {self.data_dir} ({self.n_runs} recorded runs): {what}. "
                           "A changed cohort or design changes the runs: record them again"}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m twinfalsify.runs.replay",
                                 description="Serve a recording of runs.record as a twin.")
    ap.add_argument("--data", required=True, help="folder with answers-*.jsonl")
    ap.add_argument("--name", help="twin name in hello (default: the recorded one)")
    args = ap.parse_args(argv)
    try:
        twin = ReplayTwin(args.data, args.name)
    except ContractError as exc:
        return refuse(f"replay: {exc}")
    return protocol.serve_forever(twin.hello, twin.simulate)


def refuse(message: str) -> int:
    """Serve one hello answered ``ok: false`` with ``message`` (the runner stops with it)."""

    def hello() -> dict[str, Any]:
        raise ContractError(message)

    return protocol.serve_forever(hello, lambda request: {})


if __name__ == "__main__":
    sys.exit(main())
