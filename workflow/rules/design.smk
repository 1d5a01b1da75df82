rule design:
    input:
        d0=f"{R}/d0.parquet",
        d=f"{R}/d.parquet",
    output:
        actions=f"{R}/design/actions.json",
        bins=f"{R}/design/bins.json",
        hypotheses=f"{R}/design/hypotheses.parquet",
        report=f"{R}/design/report.csv",
        action_space=report(
            f"{R}/tables/action_space.csv",
            caption="../report/action_space.rst",
            category="Design",
        ),
    log:
        f"{LOGS}/design.log",
    benchmark:
        f"{R}/benchmarks/design.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        design=canon(config["design"]),
        code=code("design"),
    script:
        "../../scripts/design.py"


rule observational_side:
    input:
        d=f"{R}/d.parquet",
        actions=f"{R}/design/actions.json",
        bins=f"{R}/design/bins.json",
        hypotheses=f"{R}/design/hypotheses.parquet",
    output:
        counts=f"{R}/observational/counts.parquet",
        follow=f"{R}/observational/follow.parquet",
    log:
        f"{LOGS}/observational_side.log",
    benchmark:
        f"{R}/benchmarks/observational_side.tsv"
    priority: 40
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=6000,
        runtime=30,
    params:
        seed=config["seed"],
        code=code("observational_side"),
    script:
        "../../scripts/observational_side.py"
