"""Build a twin from its config entry: ``twins: {name: {kind: ..., ...}}``."""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.schema import ContractError, validate_trajectories
from twinfalsify.sources.synthetic import SyntheticWorld
from twinfalsify.twins.base import Twin

BUILTIN_KINDS = ("oracle", "biased", "fitted")
KINDS = (*BUILTIN_KINDS, "command")


def _load_context(context: dict[str, Any] | Path | str | None) -> dict[str, Any]:
    if context is None:
        return {}
    if isinstance(context, dict):
        return context
    path = Path(context)
    path = path / "twin_context.json" if path.is_dir() else path
    if not path.exists():
        raise ContractError(f"twin context {path} does not exist")
    return json.loads(path.read_text())


def _world(name: str, ctx: dict[str, Any]) -> SyntheticWorld:
    source = ctx.get("source", {})
    if source.get("kind") != "synthetic":
        raise ContractError(
            f"twins.{name}: kind oracle/biased simulate the synthetic world and need "
            f"source.kind: synthetic (this study's source is {source.get('kind')!r})"
        )
    return SyntheticWorld.from_config(source.get("synthetic"))


def make_twin(
    name: str, spec: dict[str, Any], context: dict[str, Any] | Path | str | None = None
) -> Twin:
    """The twin ``name`` described by ``spec``.

    context: {"source": <config source section>, "d0": <path of D0 parquet>} (or a
    folder/JSON file holding it as twin_context.json), needed by builtin twins.
    """
    ctx = _load_context(context)
    kind = spec.get("kind")
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
        from twinfalsify.twins.protocol_twin import ProtocolTwin

        command = spec.get("command")
        if isinstance(command, str):
            command = shlex.split(command)
        if not command:
            raise ContractError(f"twins.{name}: kind command needs a 'command' (string or list)")
        return ProtocolTwin(
            name,
            command,
            workers=int(spec.get("workers", 1)),
            timeout_s=float(spec.get("timeout_s", 600.0)),
            retries=int(spec.get("retries", 2)),
            env=spec.get("env"),
        )
    raise ContractError(f"twins.{name}: unknown kind {kind!r}; choose one of {', '.join(KINDS)}")
