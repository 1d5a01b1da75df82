rule trajectories:
    input:
        table_source_files(),
    output:
        f"{R}/trajectories.parquet",
    log:
        f"{LOGS}/trajectories.log",
    benchmark:
        f"{R}/benchmarks/trajectories.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=60,
    params:
        source=canon(config["source"]),
        data=mimic_data(),
        seed=config["seed"],
        code=code("trajectories"),
    script:
        "../../scripts/trajectories.py"


rule split:
    input:
        f"{R}/trajectories.parquet",
    output:
        d0=f"{R}/d0.parquet",
        d=f"{R}/d.parquet",
    log:
        f"{LOGS}/split.log",
    benchmark:
        f"{R}/benchmarks/split.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        d0_fraction=config["split"]["d0_fraction"],
        split_by=config["split"]["by"],
        seed=config["seed"],
        code=code("split"),
    script:
        "../../scripts/split.py"
