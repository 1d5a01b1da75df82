"""Build a twin from its config entry: ``twins: {name: {kind: ..., ...}}``."""

from __future__ import annotations

import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.runs.worker import DEFAULT_FAIL_FAST_RUNS, DEFAULT_MAX_RESTARTS
from twinfalsify.schema import ContractError, validate_trajectories
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.twins.base import Twin

BUILTIN_KINDS = ("oracle", "biased", "fitted")
KINDS = (*BUILTIN_KINDS, "python", "command")
# how, not what, to run
RUNNER_KEYS = ("protocol", "workers", "timeout_s", "retries", "env", "batch_size",
               "fail_fast_runs", "max_restarts")
# Runner keys that cannot change a finished run's numbers: the workflow keeps them out of
# a shard's params, so changing them reruns no shard
# (docs/how-to/run-workflow.md, "What reruns after which change").
EXECUTION_KEYS = ("workers", "timeout_s", "retries", "batch_size", "fail_fast_runs",
                  "max_restarts")
COMMAND_TIMEOUT_S = 600.0  # per run, for a kind command twin whose spec gives no timeout_s
#: the folder holding the twinfalsify package (a checkout's src/, or site-packages)
LIBRARY_ROOT = Path(__file__).resolve().parents[2]


def _library_pythonpath(rest: str | None) -> str:
    """PYTHONPATH for a twin subprocess that imports this very library (scripts run it from
    src/ without installing it): this src/ first, then ``rest``."""
    return os.pathsep.join(p for p in (str(LIBRARY_ROOT), rest) if p)


def with_execution_keys(spec: dict[str, Any], full: dict[str, Any]) -> dict[str, Any]:
    """``spec`` (a shard's params, execution-only keys left out so that changing them reruns
    no shard) completed with the execution-only keys of the config's ``full`` spec."""
    return {**spec, **{k: full[k] for k in EXECUTION_KEYS if k in full}}


def _load_context(context: dict[str, Any] | Path | str | None) -> dict[str, Any]:
    if context is None:
        return {}
    if isinstance(context, dict):
        return context
    path = Path(context)
    path = path / "twin_context.json" if path.is_dir() else path
    if not path.exists():
        raise ContractError(f"twin context {path} does not exist")
    try:
        ctx = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ContractError(f"twin context {path}: not JSON ({exc.msg})") from None
    # paths in the context are relative to its folder, so a moved or copied study stays valid
    if ctx.get("d0") and not Path(ctx["d0"]).is_absolute():
        ctx["d0"] = str(path.parent / ctx["d0"])
    return ctx


def _world(name: str, ctx: dict[str, Any]) -> SyntheticWorld:
    source = ctx.get("source", {})
    if not ctx:
        raise ContractError(
            f"twins.{name}: kind oracle/biased simulate the study's synthetic world: give its "
            "twin context (--context results/<study>/twin_context.json)"
        )
    if source.get("kind") != "synthetic":
        raise ContractError(
            f"twins.{name}: kind oracle/biased simulate the synthetic world and need "
            f"source.kind: synthetic (this study's source is {source.get('kind')!r})"
        )
    return SyntheticWorld.from_config(source.get("synthetic"))


def check_spec(name: str, spec: dict[str, Any], source: dict[str, Any]) -> None:
    """Raise ContractError (message starts ``twins.<name>``) for a spec that cannot build.

    What can be known from the config alone, before any data exists: the kind, the
    features of ``shift``/``scale`` and doses of ``dose_effect`` (checked by the builtin
    twin's own constructor, on a default world), a command for kind command that can start
    (``runs.command.check_command``), and a synthetic ``source`` for kinds that simulate
    the synthetic world.
    """
    kind = spec.get("kind")
    if kind not in KINDS:
        raise ContractError(f"twins.{name}.kind: unknown kind {kind!r}; choose one of "
                            f"{', '.join(KINDS)}")
    if kind in ("oracle", "biased") and source.get("kind") != "synthetic":
        raise ContractError(
            f"twins.{name}: kind {kind} simulates the synthetic world and needs "
            f"source.kind: synthetic (this study's source is {source.get('kind')!r})"
        )
    if kind == "biased":
        from twinfalsify.twins.builtin import BiasedTwin

        BiasedTwin(SyntheticWorld.from_config(source.get("synthetic")),
                   dose_effect=dict(spec.get("dose_effect", {})),
                   shift=dict(spec.get("shift", {})), scale=dict(spec.get("scale", {})),
                   name=name)
    elif any(spec.get(k) for k in ("shift", "scale", "dose_effect")):
        key = next(k for k in ("shift", "scale", "dose_effect") if spec.get(k))
        raise ContractError(f"twins.{name}.{key}: only kind biased takes {key} "
                            f"(this twin is kind {kind})")
    if kind == "python":
        python_source(name, spec)  # the factory's module must be findable
    elif any(spec.get(k) for k in ("factory", "options")):
        key = next(k for k in ("factory", "options") if spec.get(k))
        raise ContractError(f"twins.{name}.{key}: only kind python takes {key} (this twin is "
                            f"kind {kind})")
    if kind == "command" and not spec.get("command"):
        raise ContractError(f"twins.{name}: kind command needs a 'command' (string or list)")
    if kind == "command":
        from twinfalsify.runs.command import check_command

        check_command(name, spec, LIBRARY_ROOT)
    elif any(spec.get(k) for k in ("code", "code_exclude")):
        key = next(k for k in ("code", "code_exclude") if spec.get(k))
        raise ContractError(f"twins.{name}.{key}: only kind command takes {key} (this twin "
                            f"is kind {kind}; its code is the library's, tracked already)")


def make_twin(
    name: str, spec: dict[str, Any], context: dict[str, Any] | Path | str | None = None
) -> Twin:
    """The twin ``name`` described by ``spec``.

    context: {"source": <config source section>, "d0": <path of D0 parquet>} (or a
    folder/JSON file holding it as twin_context.json), needed by builtin twins.
    """
    kind = spec.get("kind")
    if kind == "python" and (spec.get("protocol") or int(spec.get("workers", 1)) > 1):
        # as the builtins: more than one worker means subprocesses over the protocol
        return served_builtin(name, spec, context, need_context=False)
    if spec.get("protocol") and kind in BUILTIN_KINDS:
        return served_builtin(name, spec, context)
    if kind == "python":
        return python_twin(name, spec)
    ctx = _load_context(context)
    if kind == "oracle":
        from twinfalsify.twins.builtin import OracleTwin

        return OracleTwin(_world(name, ctx), name=name)
    if kind == "biased":
        from twinfalsify.twins.builtin import BiasedTwin

        return BiasedTwin(
            _world(name, ctx),
            dose_effect=dict(spec.get("dose_effect", {})),
            shift=dict(spec.get("shift", {})),
            scale=dict(spec.get("scale", {})),
            name=name,
        )
    if kind == "fitted":
        from twinfalsify.twins.builtin import FittedTwin

        d0_path = ctx.get("d0")
        if not d0_path:
            raise ContractError(f"twins.{name}: kind fitted needs the study's D0 (context 'd0')")
        train = validate_trajectories(pd.read_parquet(d0_path), source=d0_path)
        return FittedTwin.fit(
            train,
            inputs=str(spec.get("inputs", "init")),
            residual_noise=bool(spec.get("residual_noise", False)),
            name=name,
        )
    if kind == "command":
        from twinfalsify.runs.protocol_twin import ProtocolTwin

        command = spec.get("command")
        if isinstance(command, str):
            command = shlex.split(command)
        if not command:
            raise ContractError(f"twins.{name}: kind command needs a 'command' (string or list)")
        opts = _runner_options(spec, COMMAND_TIMEOUT_S)
        if command[0] in ("python", "python3"):
            # "python" = the study's own interpreter, with this library importable, whatever
            # PATH says (a twin needing another interpreter, e.g. Pulse's, names its path).
            command = [sys.executable, *command[1:]]
            env = dict(opts["env"] or {})
            env["PYTHONPATH"] = _library_pythonpath(
                env.get("PYTHONPATH", os.environ.get("PYTHONPATH")))
            opts["env"] = env
        return ProtocolTwin(name, command, **opts)
    raise ContractError(f"twins.{name}: unknown kind {kind!r}; choose one of {', '.join(KINDS)}")


def _runner_options(spec: dict[str, Any], timeout_s: float) -> dict[str, Any]:
    return {
        "workers": int(spec.get("workers", 1)),
        "timeout_s": float(spec.get("timeout_s", timeout_s)),
        "retries": int(spec.get("retries", 2)),
        "env": spec.get("env"),
        "batch_size": int(spec.get("batch_size", 500)),
        "fail_fast_runs": int(spec.get("fail_fast_runs", DEFAULT_FAIL_FAST_RUNS)),
        "max_restarts": int(spec.get("max_restarts", DEFAULT_MAX_RESTARTS)),
    }


def _factory(name: str, spec: dict[str, Any]) -> tuple[str, str]:
    text = spec.get("factory")
    module, _, attr = str(text or "").partition(":")
    if not module or not attr:
        raise ContractError(f"twins.{name}.factory: kind python needs 'module:callable' "
                            f"(got {text!r}), e.g. factory: my_twin:make")
    return module, attr


def _with_path(spec: dict[str, Any]) -> None:
    """Put the spec's ``path`` (default: the working folder) first on sys.path."""
    folder = str(Path(spec.get("path") or ".").resolve())
    if folder not in sys.path:
        sys.path.insert(0, folder)


def python_source(name: str, spec: dict[str, Any]) -> Path:
    """The source file of a kind python twin's module (found, not imported)."""
    import importlib.util

    module, _ = _factory(name, spec)
    _with_path(spec)
    try:
        found = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        found = None
    if found is None or not found.origin or not Path(found.origin).is_file():
        raise ContractError(f"twins.{name}.factory: cannot find module {module!r} (from "
                            f"{Path(spec.get('path') or '.').resolve()}; set 'path' to the "
                            "folder holding it)")
    return Path(found.origin)


def python_fingerprint(spec: dict[str, Any], name: str = "twin") -> str:
    """SHA-256 (16 hex digits) of a kind python twin's module source; '' for other kinds:
    editing the module reruns the twin's shards (as a command twin's files do)."""
    import hashlib

    if spec.get("kind") != "python":
        return ""
    return hashlib.sha256(python_source(name, spec).read_bytes()).hexdigest()[:16]


def python_twin(name: str, spec: dict[str, Any]) -> Twin:
    """Call a kind python twin's factory in this process; check what it returns."""
    import importlib

    module, attr = _factory(name, spec)
    python_source(name, spec)
    factory = getattr(importlib.import_module(module), attr, None)
    if not callable(factory):
        raise ContractError(f"twins.{name}.factory: {module} has no callable {attr!r}")
    options = spec.get("options") or {}
    if not isinstance(options, dict):
        raise ContractError(f"twins.{name}.options: must be a mapping of keyword arguments")
    twin = factory(**options)
    if not callable(getattr(twin, "simulate", None)):
        raise ContractError(f"twins.{name}.factory: {module}:{attr} returned "
                            f"{type(twin).__name__}, which has no simulate(x0, doses, seeds) "
                            "(twins/base.py: the Twin interface)")
    if not isinstance(getattr(twin, "name", None), str):
        try:
            twin.name = name
        except AttributeError:
            raise ContractError(f"twins.{name}.factory: the twin needs a 'name' "
                                "attribute") from None
    return twin


def served_builtin(name: str, spec: dict[str, Any], context: Path | str | dict | None,
                   need_context: bool = True) -> Twin:
    """A builtin twin run as ``python -m twinfalsify.runs.serve`` subprocesses (ProtocolTwin).

    spec: the builtin spec plus ``protocol: true`` and the runner options
    ``workers`` (processes), ``timeout_s`` (per run, default 60 s), ``retries``,
    ``batch_size`` (most runs per simulate_batch message, default 500; the
    served twin accepts up to serve.BATCH_MAX).
    context: path of the study's twin_context.json (or its folder): the served
    process builds its twin from it, so it must be a file, not a dict. The
    served twin computes exactly what the in-process one does (builtin twins
    key their noise by seed and dose prefix), so results are bit-identical.
    """
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    inner = {k: v for k, v in spec.items() if k not in RUNNER_KEYS}
    if inner.get("kind") == "python":  # the served process imports from the same folder
        inner["path"] = str(Path(spec.get("path") or ".").resolve())
    command = [sys.executable, "-m", "twinfalsify.runs.serve", name,
               "--spec", json.dumps(inner, sort_keys=True)]
    if context is None or isinstance(context, dict):
        if need_context:
            raise ContractError(
                f"twins.{name}: protocol: true needs the study's twin context as a file "
                "(results/<study>/twin_context.json), not an in-memory dict"
            )
    else:
        path = Path(context).resolve()
        if not path.exists():
            raise ContractError(f"twin context {path} does not exist")
        command += ["--context", str(path)]
    opts = _runner_options(spec, 60.0)
    opts["env"] = {"PYTHONPATH": _library_pythonpath(os.environ.get("PYTHONPATH")),
                   **(opts["env"] or {})}
    return ProtocolTwin(name, command, **opts)
