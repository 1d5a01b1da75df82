# Adaptive (sequential) twin runs: twin_runs.mode = adaptive (docs/explanation/sequential.md).
# Each shard simulates batch by batch and stops decided hypotheses; tests_adaptive merges
# the shards and corrects the anytime-valid p-values. In adaptive mode its output is the
# twin's results.parquet (ruleorder below), so tables and figures follow unchanged.
ADAPTIVE = config["twin_runs"]["mode"] == "adaptive"
ADAPTIVE_OUT = twin_dir() if ADAPTIVE else f"{twin_dir()}/adaptive"


rule twin_shard_adaptive:
    input:
        # the twin's hello is checked and its cost printed before its first shard
        cost=f"{R}/benchmarks/twins/{{twin}}/cost.json",
        plan=f"{R}/twin_plan.json",
        context=f"{R}/twin_context.json",
        d=f"{R}/d.parquet",
        actions=f"{R}/design/actions.json",
        bins=f"{R}/design/bins.json",
        hypotheses=f"{R}/design/hypotheses.parquet",
        counts=f"{R}/observational/counts.parquet",
        follow=f"{R}/observational/follow.parquet",
    output:
        runs=f"{twin_dir()}/adaptive/shards/{{shard}}.parquet",
        decisions=f"{twin_dir()}/adaptive/shards/{{shard}}.decisions.parquet",
        summary=f"{twin_dir()}/adaptive/shards/{{shard}}.json",
    log:
        f"{LOGS}/twins/{{twin}}/adaptive_shard_{{shard}}.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/adaptive_shard_{{shard}}.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    threads: 1
    resources:
        mem_mb=6000,
        runtime=240,
    params:
        spec=shard_spec,
        runs=canon(config["twin_runs"]),
        testing=canon(config["testing"]),
        seed=config["seed"],
        code=lambda w: shard_code(w.twin, "twin_adaptive_shard"),
    script:
        "../../scripts/twin_adaptive_shard.py"


rule tests_adaptive:
    input:
        runs=expand(
            f"{R}/twins/{{{{twin}}}}/adaptive/shards/{{shard}}.parquet",
            shard=range(N_SHARDS),
        ),
        decisions=expand(
            f"{R}/twins/{{{{twin}}}}/adaptive/shards/{{shard}}.decisions.parquet",
            shard=range(N_SHARDS),
        ),
        summaries=expand(
            f"{R}/twins/{{{{twin}}}}/adaptive/shards/{{shard}}.json",
            shard=range(N_SHARDS),
        ),
        plan=f"{R}/twin_plan.json",
        d=f"{R}/d.parquet",
        bins=f"{R}/design/bins.json",
        hypotheses=f"{R}/design/hypotheses.parquet",
        counts=f"{R}/observational/counts.parquet",
        follow=f"{R}/observational/follow.parquet",
    output:
        results=f"{ADAPTIVE_OUT}/results.parquet",
        summary=f"{twin_dir()}/adaptive/summary.json",
    log:
        f"{LOGS}/twins/{{twin}}/tests_adaptive.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/tests_adaptive.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=8000,
        runtime=30,
    params:
        testing=canon(config["testing"]),
        code=code("twin_adaptive_tests"),
    script:
        "../../scripts/twin_adaptive_tests.py"


ruleorder: tests_adaptive > tests
