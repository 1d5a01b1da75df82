import json
from pathlib import Path

import sys

from snakemake.utils import validate

SRC = Path(workflow.basedir) / "src"
sys.path.insert(0, str(SRC))
from twinfalsify.io import load_yaml_strict, unwritable  # noqa: E402
from twinfalsify.provenance import code_fingerprint  # noqa: E402
from twinfalsify.runs.registry import EXECUTION_KEYS  # noqa: E402
from twinfalsify.schema import ContractError  # noqa: E402
from twinfalsify.studyconfig import shard_count, study_config_error  # noqa: E402


# Everything that can be checked from the config alone is checked here, at parse time,
# before any job runs, in one line naming the key (Snakemake's own message prints the whole
# schema), then Snakemake's validate for the schema's defaults.
def _config_problem():
    for configfile in workflow.configfiles:
        try:
            load_yaml_strict(configfile)  # a key written twice: YAML keeps the last
        except ContractError as exc:
            return str(exc)
    return study_config_error(
        config, Path(workflow.basedir) / "workflow/schemas/config.schema.yaml"
    )


_problem = _config_problem()
if _problem:
    raise ValueError(f"invalid config: {_problem}")
validate(config, schema="../schemas/config.schema.yaml")

STUDY = config["study"]
R = f"results/{STUDY}"
TWINS = list(config["twins"])
N_SHARDS, _shard_warning = shard_count(config)
if _shard_warning:
    print(f"WARNING: {_shard_warning}", file=sys.stderr)
LOGS = f"{R}/logs"


# a results folder that cannot be written stops the run now, not after the first rules
if not getattr(workflow, "dryrun", False) and (_unwritable := unwritable(R)):
    raise ValueError(_unwritable)


def code(script, extra=()):
    """Fingerprint of the library modules ``scripts/<script>.py`` imports (transitively).

    A params value: Snakemake reruns a job whose params changed, so a change in library
    code reruns exactly the rules whose scripts reach it (twinfalsify.provenance).
    """
    return code_fingerprint(
        Path(workflow.basedir) / "scripts" / f"{script}.py", SRC, extra
    )


wildcard_constraints:
    twin="|".join(TWINS),
    shard=r"\d+",


def canon(section):
    """Config section with its keys sorted at every level: a params value whose repr (what
    Snakemake compares to decide a rerun) ignores key order. A plain dict, not a JSON string,
    so the report shows it without escaped quotes; rule scripts read it as it is."""
    if isinstance(section, dict):
        return {k: canon(section[k]) for k in sorted(section)}
    if isinstance(section, (list, tuple)):
        return [canon(v) for v in section]
    return section


def twin_dir(twin="{twin}"):
    return f"{R}/twins/{twin}"


def all_outputs():
    # adaptive mode simulates only the runs that decide something: outputs that need every
    # twin run (bounds over time, histograms, sensitivity, the summary) are not built then
    adaptive = config["twin_runs"].get("mode", "fixed") == "adaptive"
    out = [
        f"{R}/tables/action_space.csv",
        f"{R}/design/report.csv",
        f"{R}/tables/action_space_grid.csv",
        f"{R}/tables/action_space.tex",
    ]
    if not adaptive:
        out += [f"{R}/summary.md", f"{R}/summary.html"]
    if config["source"]["kind"] == "synthetic":  # the truth is known only there
        out += [f"{R}/figures/confounding.{ext}" for ext in ("png", "pdf")]
    figures = ["pvalues", "sample_sizes", "propensity"]
    if not adaptive:
        figures += ["longitudinal", "histograms", "sensitivity"]
    for twin in TWINS:
        out += [
            f"{twin_dir(twin)}/results.parquet",
            f"{twin_dir(twin)}/tables/rejections.csv",
            f"{twin_dir(twin)}/tables/rejections.tex",
        ]
        out += [
            f"{twin_dir(twin)}/figures/{f}.{ext}"
            for f in figures
            for ext in ("png", "pdf")
        ]
    return out


# --- Cluster resources (threads, mem_mb, runtime) for the twin stage -----------------
# Seconds of wall time per simulated twin-hour, per twin kind. Builtin twins are vectorised
# numpy (milliseconds); a `command` twin is budgeted as Pulse 4.2, measured at ~150 s wall per
# simulated hour per engine (docs/reference/benchmarks.md, Pulse). Only used to size Slurm
# requests: a local run ignores runtime.
SECONDS_PER_TWIN_HOUR = {
    "oracle": 0.01,
    "biased": 0.01,
    "fitted": 0.01,
    "command": 150.0,
}


def shard_spec(wildcards):
    """The twin's spec without its execution-only keys, as a params value (canon)."""
    spec = config["twins"][wildcards.twin]
    return canon({k: v for k, v in spec.items() if k not in EXECUTION_KEYS})


def served_modules(twin):
    """Library modules a twin runs as a subprocess (``python -m twinfalsify.X``): they are
    not imported by the rule script, so they are named for its code fingerprint."""
    spec = config["twins"][twin]
    if spec.get("protocol") and spec["kind"] != "command":
        return ["twinfalsify.runs.serve"]
    command = spec.get("command") or []
    words = command.split() if isinstance(command, str) else command
    return [w for w in words if w.startswith("twinfalsify.")]


def twin_spec(wildcards):
    return config["twins"][wildcards.twin]


def shard_threads(wildcards):
    """One core per twin worker process (a Pulse engine is single-threaded)."""
    return int(twin_spec(wildcards).get("workers", 1))


def shard_mem_mb(wildcards, threads):
    """Builtin twins hold the shard's node table in memory; a twin served over the protocol
    runs one process per worker (Pulse: ~110 MB per engine, plus headroom)."""
    spec = twin_spec(wildcards)
    if spec["kind"] == "command" or spec.get("protocol"):
        return 1000 + 250 * threads
    return 4000


def shard_runtime(wildcards, input, threads):
    """Slurm time limit in minutes: twin-hours in this shard x seconds per hour / workers.

    Twin-hours = X_0 count x the hours of the shard's leaf sequences (the prefix tree shares
    prefixes, so this is an upper bound). Doubled for safety, at least 10 minutes.
    """
    plan = json.loads(Path(input.plan).read_text())
    m = len(plan["x0_stay_ids"])
    leaves = plan["shards"][int(wildcards.shard)]
    hours = m * sum(len(str(leaf).split("-")) for leaf in leaves)
    seconds = (
        hours * SECONDS_PER_TWIN_HOUR[twin_spec(wildcards)["kind"]] / max(threads, 1)
    )
    return max(10, int(2 * seconds / 60) + 1)


def mimic3_data():
    """Resolved MIMIC-III folder + file fingerprint (mimic3 source only): a new folder or
    a changed file reruns the extraction (twinfalsify.sources.mimic3_rule.data_params).
    """
    if config["source"]["kind"] != "mimic3":
        return ""
    from twinfalsify.sources.mimic3_rule import data_params

    return data_params(config["source"].get("mimic3"))


def table_source_files():
    """The files of a table source (kind table, else none): inputs of the rule, so an
    edited, added or removed file reruns it (twinfalsify.sources.table)."""
    if config["source"]["kind"] != "table":
        return []
    from twinfalsify.sources.table import table_files

    return [str(f) for f in table_files(config["source"]["table"]["path"]).files]
