import json
import re
import shlex
from pathlib import Path

import sys

from snakemake.sourcecache import LocalSourceFile
from snakemake.utils import validate

# The workflow's own sources, found relative to this file: in a checkout, and when the
# workflow is deployed as a module from a local path or a git URL (workflow.basedir is then
# the deploying folder). A checkout's library (../../src) comes first; a workflow deployed
# from git uses the twinfalsify installed beside Snakemake, of the workflow's own version.
SCHEMA = str(workflow.source_path("../schemas/config.schema.yaml"))
_here = workflow.current_basedir
_checkout_src = (
    Path(_here.get_path_or_uri(secret_free=True)).parents[1] / "src"
    if isinstance(_here, LocalSourceFile)
    else None
)
if _checkout_src is not None and (_checkout_src / "twinfalsify").is_dir():
    sys.path.insert(0, str(_checkout_src))
else:
    _init = Path(workflow.source_path("../../src/twinfalsify/__init__.py")).read_text()
    WORKFLOW_VERSION = re.search(r'__version__ = "([^"]+)"', _init).group(1)
    _install = (
        f"pip install 'twinfalsify @ git+<the repository URL>@v{WORKFLOW_VERSION}'"
    )
    try:
        import twinfalsify
    except ImportError:
        raise ValueError(
            f"this workflow (twinfalsify {WORKFLOW_VERSION}) needs its library: {_install}"
        ) from None
    if twinfalsify.__version__ != WORKFLOW_VERSION:
        raise ValueError(
            f"this workflow is twinfalsify {WORKFLOW_VERSION} but the installed library is "
            f"{twinfalsify.__version__}: install the library of the workflow's tag "
            f"({_install})"
        )
import twinfalsify  # noqa: E402

SRC = Path(twinfalsify.__file__).resolve().parents[1]
from twinfalsify.io import freeze_heap, load_yaml_strict, unwritable  # noqa: E402
from twinfalsify.provenance import (
    PROTOCOL_CLIENT_MODULES,
    code_fingerprint,
    code_scope,
    script_modules,
)  # noqa: E402
from twinfalsify.runs.plan import shard_runtime_minutes  # noqa: E402
from twinfalsify.runs.registry import EXECUTION_KEYS  # noqa: E402
from twinfalsify.schema import ContractError  # noqa: E402
from twinfalsify.figure_ids import figure_ids_error  # noqa: E402
from twinfalsify.studyconfig import (
    data_folder_error,
    shard_count,
    study_config_error,
)  # noqa: E402


# Everything that can be checked from the config alone is checked here, at parse time,
# before any job runs, in one line naming the key (Snakemake's own message prints the whole
# schema), then Snakemake's validate for the schema's defaults.
def _config_problem():
    for configfile in workflow.configfiles:
        try:
            load_yaml_strict(configfile)  # a key written twice: YAML keeps the last
        except ContractError as exc:
            return str(exc)
    return study_config_error(config, SCHEMA)


_problem = _config_problem()
if _problem:
    raise ValueError(f"invalid config: {_problem}")
validate(config, schema="../schemas/config.schema.yaml")
# a MIMIC folder that is not there stops the run now, not at the first rule
if _problem := data_folder_error(config):
    raise ValueError(f"invalid config: {_problem}")

STUDY = config["study"]
R = f"results/{STUDY}"
TWINS = list(config["twins"])
N_SHARDS, _shard_warning = shard_count(config)
if _shard_warning:
    print(f"WARNING: {_shard_warning}", file=sys.stderr)
LOGS = f"{R}/logs"


def _code_paths_problem():
    from twinfalsify.runs.command import code_paths_error, code_written_error

    for name, spec in config["twins"].items():
        if problem := code_paths_error(name, spec, "results"):
            return problem
        # a file the twin wrote in an earlier job, still in its fingerprint
        if problem := code_written_error(name, spec, f"{R}/twins/{name}", SRC):
            return problem
    return None


if _problem := _code_paths_problem():
    raise ValueError(f"invalid config: {_problem}")


def _figure_ids_problem():
    """Figure hyp_ids of the config against the study's hypotheses, once they exist."""
    hyps = Path(f"{R}/design/hypotheses.parquet")
    if not hyps.is_file() or not config.get("figures"):
        return None
    import pandas as pd

    try:
        ids = pd.read_parquet(hyps, columns=["hyp_id"])["hyp_id"]
    except (
        Exception
    ):  # noqa: BLE001 - a damaged file: the design rule reruns and says so
        return None
    return figure_ids_error(config, ids)


if _problem := _figure_ids_problem():
    raise ValueError(f"invalid config: {_problem}")


# a results folder that cannot be written stops the run now, not after the first rules
if not getattr(workflow, "dryrun", False) and (_unwritable := unwritable(R)):
    raise ValueError(_unwritable)


# the rule scripts that run twins; the protocol client (provenance.PROTOCOL_CLIENT_MODULES)
# counts only for theirs, and only for a twin that runs through it (shard_code)
TWIN_SCRIPTS = ("twin_shard", "twin_adaptive_shard")


def code(script, extra=(), leave=()):
    """Fingerprint of the library modules ``scripts/<script>.py`` imports (transitively).

    A params value: Snakemake reruns a job whose params changed, so a change in library
    code reruns exactly the rules whose scripts reach it (twinfalsify.provenance), as this
    config uses them: a rule that tests also depends on the methods in use (bound by name),
    and no rule on another source kind's package or a method not in use (code_scope).
    """
    path = workflow.source_path(f"../../scripts/{script}.py")
    used, leave_out = code_scope(config, all_methods=script.startswith("calibration"))
    if script not in TWIN_SCRIPTS:  # only a shard script starts twin processes
        leave = (*leave, *PROTOCOL_CLIENT_MODULES)
    if "twinfalsify.inference.registry" in script_modules(path, SRC, extra):
        extra = (*extra, *used)
    return code_fingerprint(path, SRC, extra, [*leave_out, *leave])


wildcard_constraints:
    twin="|".join(re.escape(t) for t in TWINS),
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
    adaptive = config["twin_runs"]["mode"] == "adaptive"
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
        if not adaptive:  # each rejection in clinical words, with its figure
            out.append(f"{twin_dir(twin)}/explained.html")
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
    "python": 150.0,  # unknown cost, as a command twin: a generous Slurm budget
}


def shard_spec(wildcards):
    """The twin's spec without its execution-only keys, as a params value (canon)."""
    spec = config["twins"][wildcards.twin]
    spec = {k: v for k, v in spec.items() if k not in EXECUTION_KEYS}
    # a string runs as its words: the same params
    if isinstance(spec.get("command"), str):
        spec["command"] = shlex.split(spec["command"])
    return canon(spec)


def served_twin(spec):
    """Whether a twin runs through the protocol client: a command twin, a twin served with
    ``protocol: true``, a python twin with more than one worker."""
    return bool(
        spec["kind"] == "command"
        or spec.get("protocol")
        or (spec["kind"] == "python" and int(spec.get("workers", 1)) > 1)
    )


def served_modules(twin):
    """Library modules a twin runs as a subprocess (``python -m twinfalsify.X``): they are
    not imported by the rule script, so they are named for its code fingerprint."""
    spec = config["twins"][twin]
    if spec.get("protocol") and spec["kind"] != "command":
        return ["twinfalsify.runs.serve"]
    if spec["kind"] == "python" and int(spec.get("workers", 1)) > 1:
        return ["twinfalsify.runs.serve"]
    command = spec.get("command") or []
    words = shlex.split(command) if isinstance(command, str) else command
    return [w for w in words if w.startswith("twinfalsify.")]


_COMMAND_CODE = {}


def shard_code(twin, script="twin_shard"):
    """A twin shard's `code` param (fixed or adaptive `script`): library modules its script
    reaches (and the served ones); for a `command` twin also the fingerprint of the files
    it runs (its script, files its command names, its spec's `code:` list; contents only),
    so editing them reruns exactly its shards and what follows (twinfalsify.runs.command).
    """
    spec = config["twins"][twin]
    fingerprint = code(
        script,
        served_modules(twin),
        () if served_twin(spec) else PROTOCOL_CLIENT_MODULES,
    )
    if spec["kind"] == "python":  # the factory module's source
        from twinfalsify.runs.registry import python_fingerprint

        return f"{fingerprint}+{python_fingerprint(spec, twin)}"
    if spec["kind"] != "command":
        return fingerprint
    if twin not in _COMMAND_CODE:  # once per parse, not once per shard job
        from twinfalsify.runs.command import command_fingerprint

        _COMMAND_CODE[twin] = command_fingerprint(config["twins"][twin], SRC)
    return f"{fingerprint}+{_COMMAND_CODE[twin]}"


def twin_spec(wildcards):
    return config["twins"][wildcards.twin]


def shard_threads(wildcards):
    """One core per twin worker process (a Pulse engine is single-threaded)."""
    return int(twin_spec(wildcards).get("workers", 1))


def shard_mem_mb(wildcards, threads):
    """Builtin twins hold the shard's node table in memory; a twin served over the protocol
    runs one process per worker (Pulse: ~110 MB per engine, plus headroom)."""
    spec = twin_spec(wildcards)
    if spec["kind"] in ("command", "python") or spec.get("protocol"):
        return 1000 + 250 * threads
    return 4000


def shard_runtime(wildcards, input, threads):
    """Slurm time limit in minutes (twinfalsify.runs.plan.shard_runtime_minutes): per run
    of the shard, its hours x seconds per twin-hour of the twin's kind, capped for a
    protocol/command twin by its timeout_s (the runner kills a run at that limit); summed,
    over the workers, doubled for safety, at least 10 minutes."""
    spec = twin_spec(wildcards)
    served = served_twin(spec)
    minutes = shard_runtime_minutes(
        json.loads(Path(input.plan).read_text()),
        int(wildcards.shard),
        SECONDS_PER_TWIN_HOUR[spec["kind"]],
        float(spec.get("timeout_s", 600.0)) if served else None,
        threads,
    )
    if (
        on_slurm()
        and minutes > RUNTIME_WARN_MINUTES
        and wildcards.twin not in _RUNTIME_WARNED
    ):
        # said once per twin, when the jobs are planned: a queue may refuse such a job, or
        # hold it for days
        _RUNTIME_WARNED.add(wildcards.twin)
        print(
            f"WARNING: twin {wildcards.twin}: shard {wildcards.shard} asks Slurm for "
            f"{minutes} minutes ({minutes / 1440:.1f} days); raise twin_runs.n_shards or the "
            "twin's workers, or lower its timeout_s",
            file=sys.stderr,
        )
    return minutes


def on_slurm():
    """True when the jobs go to Slurm (``--executor slurm``, the slurm profile): only
    there is a shard's time limit worth a word."""
    plugin = workflow.executor_plugin
    return plugin is not None and plugin.name == "slurm"


# a shard's Slurm time limit above a day is worth a warning
RUNTIME_WARN_MINUTES = 24 * 60
_RUNTIME_WARNED = set()


def mimic_data():
    """Resolved MIMIC folder + file fingerprint (mimic3 and mimic4 sources; meds: its
    shards, code map and labels): a new folder or a changed file reruns the extraction
    (twinfalsify.sources.mimic_rule.data_params, twinfalsify.sources.meds.study.fingerprint).
    """
    kind = config["source"]["kind"]
    if kind == "meds":
        from twinfalsify.sources.meds.study import fingerprint

        return fingerprint(config["source"]["meds"])
    if kind not in ("mimic3", "mimic4"):
        return ""
    from twinfalsify.sources.mimic_rule import data_params

    return data_params(config["source"].get(kind), kind)


def table_source_files():
    """The files of a table source (kind table, else none): inputs of the rule, so an
    edited, added or removed file reruns it (twinfalsify.sources.table)."""
    if config["source"]["kind"] != "table":
        return []
    from twinfalsify.sources.table import table_files

    return [str(f) for f in table_files(config["source"]["table"]["path"]).files]


# Everything summary.load_study_twin needs for one twin (wildcard {twin}).
STUDY_TWIN_INPUTS = {
    "d0": f"{R}/d0.parquet",
    "d": f"{R}/d.parquet",
    "actions": f"{R}/design/actions.json",
    "bins": f"{R}/design/bins.json",
    "hypotheses": f"{R}/design/hypotheses.parquet",
    "counts": f"{R}/observational/counts.parquet",
    "follow": f"{R}/observational/follow.parquet",
    "plan": f"{R}/twin_plan.json",
    "runs": f"{twin_dir()}/runs.parquet",
    "results": f"{twin_dir()}/results.parquet",
}
