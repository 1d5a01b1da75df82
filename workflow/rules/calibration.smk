# Calibration harness: `snakemake --cores 2 calibration` (not part of `all`).
# Its own config file is an input of every rule, so editing it reruns the harness.
from pathlib import Path

import yaml

CAL = "results/calibration"
CAL_CONFIG = "config/calibration.yaml"
# The number of chunk jobs is part of the DAG, so it is read when the workflow is parsed
# (a workdir without the file, e.g. a study run elsewhere, must still parse).
CAL_CFG_TEXT = Path(CAL_CONFIG).read_text() if Path(CAL_CONFIG).exists() else "{}"
CAL_CHUNKS = list(range(int((yaml.safe_load(CAL_CFG_TEXT) or {}).get("chunks", 4))))


rule calibration:
    input:
        f"{CAL}/calibration.csv",
        f"{CAL}/adaptive.csv",
        f"{CAL}/summary.md",
        f"{CAL}/figures/power.png",
        f"{CAL}/figures/coverage.png",


rule calibration_chunk:
    input:
        config=CAL_CONFIG,
    output:
        tests=f"{CAL}/chunks/{{chunk}}/tests.parquet",
        coverage=f"{CAL}/chunks/{{chunk}}/coverage.parquet",
        widths=f"{CAL}/chunks/{{chunk}}/widths.parquet",
        timing=f"{CAL}/chunks/{{chunk}}/timing.parquet",
        adaptive=f"{CAL}/chunks/{{chunk}}/adaptive.parquet",
    log:
        f"{CAL}/logs/chunk_{{chunk}}.log",
    benchmark:
        f"{CAL}/benchmarks/chunk_{{chunk}}.tsv"
    wildcard_constraints:
        chunk=r"\d+",
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=3000,
        runtime=60,
    params:
        code=code("calibration_chunk"),
    script:
        "../../scripts/calibration_chunk.py"


rule calibration_report:
    input:
        config=CAL_CONFIG,
        tests=expand(f"{CAL}/chunks/{{chunk}}/tests.parquet", chunk=CAL_CHUNKS),
        coverage=expand(
            f"{CAL}/chunks/{{chunk}}/coverage.parquet",
            chunk=CAL_CHUNKS,
        ),
        widths=expand(f"{CAL}/chunks/{{chunk}}/widths.parquet", chunk=CAL_CHUNKS),
        timing=expand(f"{CAL}/chunks/{{chunk}}/timing.parquet", chunk=CAL_CHUNKS),
        adaptive=expand(
            f"{CAL}/chunks/{{chunk}}/adaptive.parquet",
            chunk=CAL_CHUNKS,
        ),
    output:
        table=report(
            f"{CAL}/calibration.csv",
            caption="../report/calibration.rst",
            category="Calibration",
        ),
        adaptive=f"{CAL}/adaptive.csv",
        dominance=f"{CAL}/dominance.csv",
        coverage=f"{CAL}/coverage.csv",
        widths=f"{CAL}/widths.csv",
        replicates=f"{CAL}/replicates.parquet",
        summary=f"{CAL}/summary.md",
        power_png=report(
            f"{CAL}/figures/power.png",
            caption="../report/calibration_power.rst",
            category="Calibration",
        ),
        power_pdf=f"{CAL}/figures/power.pdf",
        coverage_png=report(
            f"{CAL}/figures/coverage.png",
            caption="../report/calibration_coverage.rst",
            category="Calibration",
        ),
        coverage_pdf=f"{CAL}/figures/coverage.pdf",
    log:
        f"{CAL}/logs/report.log",
    benchmark:
        f"{CAL}/benchmarks/report.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        code=code("calibration_report"),
    script:
        "../../scripts/calibration_report.py"
