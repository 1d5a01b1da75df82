# twinfalsify: causal falsification of digital twins (Cornish et al., JMLR 2026).
# Run the default study:  snakemake --cores 2
import time

from snakemake.utils import min_version

min_version("9.0")

# when this run started: the summary's warnings are printed at its end if it wrote them
STARTED = time.time()


# A study config given with --configfile replaces the default (no merging of twin lists).
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/source.smk"
include: "workflow/rules/design.smk"
include: "workflow/rules/twins.smk"
include: "workflow/rules/tests.smk"
include: "workflow/rules/adaptive.smk"
include: "workflow/rules/tables.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/calibration.smk"


rule all:
    default_target: True
    input:
        all_outputs(),


# A failed job's one-line error (run_rule) ends the run's output, after Snakemake's own
# closing lines, rather than sitting above them (twinfalsify.io.job_errors).
onerror:
    import atexit
    from twinfalsify.io import job_errors

    for _line in job_errors(*log):
        atexit.register(print, _line, file=sys.stderr, flush=True)


# The study's warnings (summary.md's "Warnings", also logged by the summary rule) end the
# run's output, after Snakemake's closing lines, when this run wrote the summary.
onsuccess:
    import atexit
    from twinfalsify.summary import warnings_in_summary

    _warned = [
        f"WARNING: {_w}" for _w in warnings_in_summary(f"{R}/summary.md", STARTED)
    ]
    if _warned:
        _warned.insert(0, f"The study's warnings ({R}/summary.md):")
        atexit.register(print, "\n".join(_warned), file=sys.stderr, flush=True)
