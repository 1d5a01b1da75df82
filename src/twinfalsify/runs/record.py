"""Record a protocol twin's answers, so that expensive runs can be replayed exactly.

    python -m twinfalsify.runs.record --out DIR -- COMMAND [ARGS...]

A transparent proxy between the runner and a twin command: every line the runner
writes goes to the twin unchanged, every answer comes back unchanged, and each
``hello`` answer and each (``simulate`` request, ``result`` answer) pair is appended
to ``DIR/answers-<pid>.jsonl`` (one file per proxy process, so parallel workers never
interleave lines). ``runs.replay`` serves such a folder as a twin. Typical use:
record a study once with the real engine (Pulse, on a cluster), commit the folder,
and let CI replay the same study in seconds.

What is recorded is what the runner received: values after the twin's own unit
conversion, its statuses, messages and ``clamped`` records, as JSON numbers (so a
replayed float is bit-identical). The one change the proxy makes: it withholds the
``arrays`` capability from the hello it passes on, so every answer comes as results
with JSON numbers, which is what it records. The twin's stderr passes through. If the twin dies,
the proxy exits with the twin's exit code, so the runner sees the same failure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from twinfalsify.runs.protocol import ARRAYS, ProtocolError, decode, encode

ANSWERING_OPS = ("hello", "simulate", "simulate_batch", "shutdown")


def _pairs(msg: dict[str, Any], answer: dict[str, Any]) -> list[dict[str, Any]]:
    """Recording lines for one request and its answer."""
    if msg["op"] == "hello":
        return [{"hello": answer}]
    if msg["op"] == "simulate":
        return [{"request": msg, "answer": answer}]
    if msg["op"] == "simulate_batch" and isinstance(answer.get("results"), list):
        return [{"request": r, "answer": a}
                for r, a in zip(msg.get("requests") or [], answer["results"], strict=False)]
    return []


def _without_arrays(hello_line: str) -> str:
    """The hello answer without the ``arrays`` capability (answers then come as results
    with JSON numbers, the form recorded); any other line unchanged."""
    try:
        hello = json.loads(hello_line)
    except json.JSONDecodeError:
        return hello_line
    caps = hello.get("capabilities") if isinstance(hello, dict) else None
    if not isinstance(caps, dict) or ARRAYS not in caps:
        return hello_line
    return encode({**hello, "capabilities": {k: v for k, v in caps.items() if k != ARRAYS}})


def proxy(command: Sequence[str], out_dir: Path, stdin: IO[str], stdout: IO[str]) -> int:
    """Forward ``stdin`` to the twin and its answers to ``stdout``; record; return exit code."""
    out_dir.mkdir(parents=True, exist_ok=True)
    log = open(out_dir / f"answers-{os.getpid()}.jsonl", "a", buffering=1)  # noqa: SIM115
    twin = subprocess.Popen(list(command), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, encoding="utf-8", bufsize=1)
    assert twin.stdin is not None and twin.stdout is not None
    try:
        for line in stdin:
            try:
                twin.stdin.write(line)
                twin.stdin.flush()
            except BrokenPipeError:
                break
            try:
                msg = decode(line)
            except ProtocolError:
                continue  # the twin ignores it too (and says so on stderr)
            if msg["op"] not in ANSWERING_OPS:
                continue
            answer_line = twin.stdout.readline()
            if not answer_line:
                break  # the twin died: the runner sees end of stream, as without the proxy
            if msg["op"] == "hello":
                answer_line = _without_arrays(answer_line)
            stdout.write(answer_line)
            stdout.flush()
            try:
                answer = json.loads(answer_line)
            except json.JSONDecodeError:
                continue  # a broken answer is the runner's to report; nothing to record
            for rec in _pairs(msg, answer):
                log.write(encode(rec))
            if msg["op"] == "shutdown":
                break
    finally:
        log.close()
        if twin.stdin:
            try:
                twin.stdin.close()
            except BrokenPipeError:
                pass
        code = twin.wait()
    return code


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m twinfalsify.runs.record",
        description="Record a protocol twin's answers (see runs.replay to serve them).",
    )
    ap.add_argument("--out", required=True, help="folder for answers-<pid>.jsonl")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- the twin command")
    args = ap.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("give the twin command after --")
    return proxy(command, Path(args.out), sys.stdin, sys.stdout)


if __name__ == "__main__":
    sys.exit(main())
