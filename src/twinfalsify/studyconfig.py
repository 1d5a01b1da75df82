"""Everything about a study config that can be checked before anything is computed.

The workflow calls :func:`study_config_error` when the Snakefile is parsed (common.smk), so
a bad value stops the run in one line before the first rule, not after hours of twin runs.
It adds to the schema check (``io.config_error``: types, ranges, non-finite numbers) the
checks that need the library itself, using the library's own validators and names rather
than copies of them:

- ``testing.methods``: every method and option is known (``inference.registry.make``);
- ``design.quantiles``: y_lo < y_up (the bounds are [q_lo, q_up] quantiles of D0);
- ``figures.*.outcome``: an outcome under test (``schema.OUTCOMES``);
- ``source.table``: the table files exist and have the contract's columns
  (``sources.table.check_headers``; their values are checked by the source rule, first);
- ``study`` and ``twins.<name>`` names: each is one folder name under results/
  (:func:`name_error`: not ``.``/``..`` or hidden, at most ``MAX_NAME`` characters);
- ``source.meds``: the MEDS folder's metadata and shards, the code map and the label table
  (``sources.meds.study.source_error``; the codes themselves are checked by the source rule);
- ``twins.<name>``: the spec builds (``runs.registry.check_spec``: features of shift/scale,
  doses of dose_effect, a command for kind command, a synthetic source for oracle/biased).
"""

from __future__ import annotations

import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from twinfalsify.design import N_DOSE_BINS
from twinfalsify.inference import registry as methods
from twinfalsify.io import config_error
from twinfalsify.runs.registry import check_spec
from twinfalsify.schema import OUTCOMES, ContractError

# Shards hold whole groups of leaves with the same first action (runs.plan), so a plan has
# at most this many non-empty shards.
N_ACTIONS = N_DOSE_BINS * N_DOSE_BINS

# A study or twin name is one folder name under results/ (results/<study>/twins/<twin>/),
# in file names too; well under the file systems' 255 bytes per name.
MAX_NAME = 100
NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")


def semantic_error(config: Mapping[str, Any]) -> str | None:
    """The first problem the schema cannot see, as one line naming the key, or None.

    Assumes ``config`` passed the schema (``io.config_error``).
    """
    problem = source_error(config.get("source") or {})
    if problem:
        return problem
    testing = config.get("testing", {})
    for name, opts in (testing.get("methods") or {}).items():
        try:
            methods.make(name, opts, seed=0)  # binds options, computes nothing
        except ContractError as exc:
            return f"config key {exc}"
    quantiles = (config.get("design") or {}).get("quantiles")
    if quantiles is not None and not quantiles[0] < quantiles[1]:
        return (f"config key design.quantiles: {list(quantiles)} must be increasing "
                "[y_lo quantile, y_up quantile], e.g. [0.2, 0.8]")
    for fig, opts in (config.get("figures") or {}).items():
        outcome = (opts or {}).get("outcome")
        if outcome is not None and outcome not in OUTCOMES:
            return (f"config key figures.{fig}.outcome: {outcome!r} is not an outcome under "
                    f"test; choose from {', '.join(OUTCOMES)}")
    for name, spec in (config.get("twins") or {}).items():
        try:
            check_spec(name, spec, config.get("source", {}))
        except ContractError as exc:
            return f"config key {exc}"
    return None


def source_error(source: Mapping[str, Any]) -> str | None:
    """A table source without a path, or whose files are missing or lack a contract
    column; a meds source whose folder, code map or label table breaks a rule
    (``sources.meds.study.source_error``): as one line; None otherwise (other kinds: None)."""
    if source.get("kind") == "meds":
        from twinfalsify.sources.meds.study import source_error as meds_error

        return meds_error(source.get("meds"))
    if source.get("kind") != "table":
        return None
    path = (source.get("table") or {}).get("path")
    if not path:
        return ("config key source.table.path: kind table needs the path of your "
                "trajectories (a Parquet or CSV file, or a folder of them)")
    from twinfalsify.sources.table import check_headers

    try:
        check_headers(path)
    except ContractError as exc:
        return f"config key source.table.path: {exc}".replace(
            "source.table.path: source.table.path: ", "source.table.path: ")
    return None


def data_folder_error(config: Mapping[str, Any]) -> str | None:
    """A MIMIC source whose folder cannot be found (config path, or the environment variable
    that overrides it), as one line naming the key, or None (other kinds: None).

    Not part of :func:`study_config_error`: a shipped config names no folder and is valid;
    the workflow checks it when it starts, before the first rule."""
    kind = (config.get("source") or {}).get("kind")
    if kind not in ("mimic3", "mimic4"):
        return None
    from twinfalsify.sources.mimic3.tables import resolve_dir
    from twinfalsify.sources.mimic_rule import layout_of

    try:
        resolve_dir(((config["source"].get(kind)) or {}).get("path"), layout_of(kind))
    except ContractError as exc:
        return f"config key source.{kind}.path: {exc}"
    return None


def study_config_error(config: Mapping[str, Any], schema_path: str | Path) -> str | None:
    """Withdrawn options, the schema check, then :func:`semantic_error`: the first problem as
    one line, or None. A withdrawn option is named with its reason before the schema would
    only say "not one of"."""
    return (removed_option_error(config) or name_error(config)
            or config_error(dict(config), schema_path) or semantic_error(config))


def name_error(config: Mapping[str, Any]) -> str | None:
    """A study or twin name that is not a plain folder name, as one line, or None.

    ``study: '..'`` would write the study beside results/, ``'.'`` into results/ itself, a
    twin named ``..`` into the study folder, and a name longer than a file system allows
    would fail at the first job. Values of the wrong type are left to the schema.
    """
    names: list[tuple[str, Any]] = [("study", config.get("study"))]
    twins = config.get("twins")
    if isinstance(twins, Mapping):
        names += [(f"twins.{n}", n) for n in twins]
    for key, name in names:
        if not isinstance(name, str):
            continue
        if len(name) > MAX_NAME:
            shown = key if len(key) <= 40 else f"{key[:40]}..."
            return (f"config key {shown}: a name of {len(name)} characters; "
                    f"at most {MAX_NAME} (it names a folder under results/)")
        if not NAME.fullmatch(name):
            return (f"config key {key}: {name!r} is not a folder name: use letters, digits, "
                    "'_', '-' and '.', not starting with '.' (it names a folder under "
                    "results/)")
    return None


def removed_option_error(config: Mapping[str, Any]) -> str | None:
    """A withdrawn option (``twin_runs.combine: product``) as one line saying why, or None."""
    runs = config.get("twin_runs")
    if isinstance(runs, Mapping) and runs.get("combine") == "product":
        from twinfalsify.inference.sequential import PRODUCT_REMOVED

        return f"config key twin_runs.{PRODUCT_REMOVED}"
    return None


def shard_count(config: Mapping[str, Any]) -> tuple[int, str | None]:
    """``twin_runs.n_shards`` capped at the number of actions, and a warning if capped."""
    asked = int((config.get("twin_runs") or {}).get("n_shards", 4))
    if asked <= N_ACTIONS:
        return asked, None
    return N_ACTIONS, (
        f"config key twin_runs.n_shards: {asked} asked, but a shard holds whole first-action "
        f"groups and there are {N_ACTIONS} actions: using {N_ACTIONS} shards"
    )


def shard_files(config: Mapping[str, Any], twin: str) -> list[str]:
    """The shard files of ``twin`` in a validated config (schema defaults set): the outputs
    of its shard jobs (fixed or adaptive mode), for ``snakemake --forcerun``, which reruns
    them and everything that follows, whether or not they exist."""
    if twin not in config["twins"]:
        raise ContractError(f"no twin named {twin!r} in the config; its twins: "
                            f"{', '.join(config['twins'])}")
    n, _ = shard_count(config)
    folder = "adaptive/shards" if config["twin_runs"]["mode"] == "adaptive" else "shards"
    return [f"results/{config['study']}/twins/{twin}/{folder}/{k}.parquet" for k in range(n)]


def main(argv: list[str] | None = None) -> int:
    """``python -m twinfalsify.studyconfig shards CONFIG TWIN``: the twin's shard files, one
    per line (docs/how-to/run-workflow.md, "Rerun one twin"); a bad config or an unknown twin
    is one line on stderr and exit status 2."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m twinfalsify.studyconfig")
    parser.add_argument("what", choices=["shards"])
    parser.add_argument("config", help="the study config (YAML)")
    parser.add_argument("twin", help="a twin's name in it")
    args = parser.parse_args(argv)
    from snakemake.utils import validate

    from twinfalsify.io import load_yaml_strict

    schema = Path(__file__).resolve().parents[2] / "workflow" / "schemas" / "config.schema.yaml"
    try:
        config = load_yaml_strict(args.config)
        if not isinstance(config, dict):
            raise ContractError(f"{args.config}: not a mapping of config keys")
        if problem := study_config_error(config, schema):
            raise ContractError(problem)
        validate(config, str(schema))  # the schema's defaults
        print("\n".join(shard_files(config, args.twin)))
    except (ContractError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
