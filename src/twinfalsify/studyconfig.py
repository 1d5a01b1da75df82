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
- ``source.meds``: the MEDS folder's metadata and shards, the code map and the label table
  (``sources.meds.study.source_error``; the codes themselves are checked by the source rule);
- ``twins.<name>``: the spec builds (``runs.registry.check_spec``: features of shift/scale,
  doses of dose_effect, a command for kind command, a synthetic source for oracle/biased).
"""

from __future__ import annotations

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


def study_config_error(config: Mapping[str, Any], schema_path: str | Path) -> str | None:
    """Withdrawn options, the schema check, then :func:`semantic_error`: the first problem as
    one line, or None. A withdrawn option is named with its reason before the schema would
    only say "not one of"."""
    return (removed_option_error(config) or config_error(dict(config), schema_path)
            or semantic_error(config))


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
