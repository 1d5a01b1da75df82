"""Rule twin_hello: start the twin once, check its hello, time one short run."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.io import log, run_rule, write_json  # noqa: E402
from twinfalsify.runs.command import watch_code  # noqa: E402
from twinfalsify.runs.hello import split_timing, twin_hello  # noqa: E402
from twinfalsify.runs.registry import LIBRARY_ROOT, with_execution_keys  # noqa: E402


def main(sm):
    name = sm.wildcards.twin
    spec = with_execution_keys(dict(sm.params.spec), sm.config["twins"][name])
    # files the twin writes that its fingerprint reads: recorded (runs.command.watch_code)
    written = Path(sm.output.hello).parent / "code_written" / "hello.json"
    with watch_code(spec, LIBRARY_ROOT, written):
        hello = twin_hello(name, spec)
    log.info("twin %s: %s; probe run %s", name, hello.get("hello") or hello["checked"],
             hello["probe"])
    probe = hello["probe"]
    if probe and probe["status"] != "ok":  # not fatal: the shards record each run's status
        log.warning("WARNING: twin %s: its one probe run (median X_0, %d hour(s), no doses) "
                    "ended %s: %s", name, probe["hours"], probe["status"], probe["message"])
    # the measured seconds go with the benchmarks: hello.json is the same at every run
    kept, timing = split_timing(hello)
    write_json(kept, sm.output.hello)
    write_json(timing, sm.output.timing)


run_rule(snakemake, main)  # noqa: F821
