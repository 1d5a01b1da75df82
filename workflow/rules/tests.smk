rule tests:
    input:
        d=f"{R}/d.parquet",
        bins=f"{R}/design/bins.json",
        hypotheses=f"{R}/design/hypotheses.parquet",
        counts=f"{R}/observational/counts.parquet",
        follow=f"{R}/observational/follow.parquet",
        plan=f"{R}/twin_plan.json",
        runs=f"{twin_dir()}/runs.parquet",
    output:
        results=f"{twin_dir()}/results.parquet",
    log:
        f"{LOGS}/twins/{{twin}}/tests.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/tests.tsv"
    priority: 40
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        testing=canon(config["testing"]),
        seed=config["seed"],
        code=code("tests"),
    script:
        "../../scripts/tests.py"
