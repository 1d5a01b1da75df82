rule twin_plan:
    input:
        d=f"{R}/d.parquet",
        d0=f"{R}/d0.parquet",
        hypotheses=f"{R}/design/hypotheses.parquet",
    output:
        plan=f"{R}/twin_plan.json",
        context=f"{R}/twin_context.json",
    log:
        f"{LOGS}/twin_plan.log",
    benchmark:
        f"{R}/benchmarks/twin_plan.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=10,
    params:
        runs=canon(config["twin_runs"]),
        seed=config["seed"],
        source=canon(config["source"]),
        code=code("twin_plan"),
    script:
        "../../scripts/twin_plan.py"


# The twin's hello is checked, and one short run timed, before the expensive work: the rule
# has no data inputs, so it runs at the start, next to the extraction, and every shard of
# the twin waits for it. Its params are the shard's (spec without execution keys, code), so
# it reruns only when the twin's shards would. Its priority puts it first when cores are few.
rule twin_hello:
    output:
        hello=f"{twin_dir()}/hello.json",
        # the probe run's measured seconds: a measurement, kept with the benchmarks
        timing=f"{R}/benchmarks/twins/{{twin}}/probe.json",
    log:
        f"{LOGS}/twins/{{twin}}/hello.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/hello.tsv"
    priority: 50
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=1000,
        runtime=lambda w: 10 + int(config["twins"][w.twin].get("timeout_s", 600)) // 30,
    params:
        spec=shard_spec,
        code=lambda w: f"{shard_code(w.twin)}+{code('twin_hello')}",
    script:
        "../../scripts/twin_hello.py"


# Engine-hours the plan asks of the twin and the projected wall time on its workers, said
# before any shard runs.
rule twin_cost:
    input:
        plan=f"{R}/twin_plan.json",
        hello=f"{twin_dir()}/hello.json",
        timing=f"{R}/benchmarks/twins/{{twin}}/probe.json",
    output:
        # a projection from a measured time: with the benchmarks, not the results
        f"{R}/benchmarks/twins/{{twin}}/cost.json",
    log:
        f"{LOGS}/twins/{{twin}}/cost.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/cost.tsv"
    priority: 40
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    # workers is read from the config by the script: an execution key, as for the shards
    params:
        code=code("twin_cost"),
    script:
        "../../scripts/twin_cost.py"


rule twin_shard:
    input:
        # the shard waits for the hello and the cost line; both rerun only when the twin's
        # spec or code, or the plan, changed, which reruns the shard anyway (not ancient():
        # Snakemake then skips the shard's own params check when the cost job reruns)
        cost=f"{R}/benchmarks/twins/{{twin}}/cost.json",
        plan=f"{R}/twin_plan.json",
        context=f"{R}/twin_context.json",
        d=f"{R}/d.parquet",
        actions=f"{R}/design/actions.json",
    output:
        f"{R}/twins/{{twin}}/shards/{{shard}}.parquet",
    log:
        f"{LOGS}/twins/{{twin}}/shard_{{shard}}.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/shard_{{shard}}.tsv"
    priority: 40
    group:
        "twin_shards"
    conda:
        "../../envs/twinfalsify.yaml"
    # twin processes of a protocol/command twin (workers) = cores the job uses
    threads: shard_threads
    resources:
        mem_mb=shard_mem_mb,
        runtime=shard_runtime,
    # what a run computes, not how it is run: changing workers, timeout_s, retries,
    # batch_size, fail_fast_runs or max_restarts reruns no shard (the script reads them
    # from the config); a served or command twin's library modules are in its code
    params:
        spec=shard_spec,
        code=lambda w: shard_code(w.twin),
    script:
        "../../scripts/twin_shard.py"


rule twin_runs:
    input:
        shards=expand(
            f"{R}/twins/{{{{twin}}}}/shards/{{shard}}.parquet", shard=range(N_SHARDS)
        ),
        plan=f"{R}/twin_plan.json",
    output:
        runs=f"{twin_dir()}/runs.parquet",
        summary=f"{twin_dir()}/run_summary.json",
    log:
        f"{LOGS}/twins/{{twin}}/runs.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/runs.tsv"
    priority: 40
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=6000,
        runtime=20,
    params:
        code=code("twin_runs"),
    script:
        "../../scripts/twin_runs.py"
