# What a reader opens first: the rejections explained, per twin, and the study's summary.


report: "../report/workflow.rst"


rule explain_rejections:
    input:
        **STUDY_TWIN_INPUTS,
    output:
        report(
            f"{twin_dir()}/explained.html",
            caption="../report/explained.rst",
            category="Rejections explained",
            subcategory="{twin}",
        ),
    log:
        f"{LOGS}/twins/{{twin}}/explain_rejections.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/explain_rejections.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        figures=canon(config["figures"]),
        testing=canon(config["testing"]),
        quantiles=canon(config["design"]["quantiles"]),
        code=code("explain_rejections"),
    script:
        "../../scripts/explain_rejections.py"


rule summary:
    input:
        d0=f"{R}/d0.parquet",
        d=f"{R}/d.parquet",
        hypotheses=f"{R}/design/hypotheses.parquet",
        actions=f"{R}/design/actions.json",
        bins=f"{R}/design/bins.json",
        counts=f"{R}/observational/counts.parquet",
        follow=f"{R}/observational/follow.parquet",
        plan=f"{R}/twin_plan.json",
        runs=[f"{twin_dir(t)}/runs.parquet" for t in TWINS],
        results=[f"{twin_dir(t)}/results.parquet" for t in TWINS],
    output:
        md=f"{R}/summary.md",
        html=report(
            f"{R}/summary.html",
            caption="../report/summary.rst",
            category="Summary",
        ),
    log:
        f"{LOGS}/summary.log",
    benchmark:
        f"{R}/benchmarks/summary.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=5,
    params:
        study=STUDY,
        twins=TWINS,
        testing=canon(config["testing"]),
        seed=config["seed"],
        code=code("summary"),
    script:
        "../../scripts/summary.py"
