# The tables of a study: rejections per twin (CSV and LaTeX), the action space.


rule rejections_table:
    input:
        f"{twin_dir()}/results.parquet",
    output:
        report(
            f"{twin_dir()}/tables/rejections.csv",
            caption="../report/rejections.rst",
            category="Rejections",
            subcategory="{twin}",
        ),
    log:
        f"{LOGS}/twins/{{twin}}/rejections_table.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/rejections_table.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    params:
        code=code("rejections_table"),
    script:
        "../../scripts/rejections_table.py"


rule table_rejections_tex:
    input:
        f"{twin_dir()}/tables/rejections.csv",
    output:
        report(
            f"{twin_dir()}/tables/rejections.tex",
            caption="../report/rejections_tex.rst",
            category="Rejections",
            subcategory="{twin}",
        ),
    log:
        f"{LOGS}/twins/{{twin}}/table_rejections_tex.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/table_rejections_tex.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        code=code("table_rejections_tex"),
    script:
        "../../scripts/table_rejections_tex.py"


rule table_action_space:
    input:
        f"{R}/tables/action_space.csv",
    output:
        csv=report(
            f"{R}/tables/action_space_grid.csv",
            caption="../report/action_space_grid.rst",
            category="Design",
        ),
        tex=f"{R}/tables/action_space.tex",
    log:
        f"{LOGS}/table_action_space.log",
    benchmark:
        f"{R}/benchmarks/table_action_space.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=1000,
        runtime=5,
    params:
        code=code("table_action_space"),
    script:
        "../../scripts/table_action_space.py"
