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
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    script:
        "../../scripts/rejections_table.py"


rule figure_pvalues:
    input:
        f"{twin_dir()}/results.parquet",
    output:
        png=report(
            f"{twin_dir()}/figures/pvalues.png",
            caption="../report/pvalues.rst",
            category="p-values",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/pvalues.pdf",
    log:
        f"{LOGS}/twins/{{twin}}/figure_pvalues.log",
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    params:
        method=lambda w: next(iter(config["testing"]["methods"])),
    script:
        "../../scripts/figure_pvalues.py"
