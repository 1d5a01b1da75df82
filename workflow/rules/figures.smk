# The figures of a study: per twin, and of the design (confounding).


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
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_pvalues.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    params:
        code=code("figure_pvalues_methods"),
    script:
        "../../scripts/figure_pvalues_methods.py"


rule figure_longitudinal:
    input:
        **STUDY_TWIN_INPUTS,
    output:
        png=report(
            f"{twin_dir()}/figures/longitudinal.png",
            caption="../report/longitudinal.rst",
            category="Bounds over time",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/longitudinal.pdf",
        csv=f"{twin_dir()}/figures/longitudinal.csv",
    log:
        f"{LOGS}/twins/{{twin}}/figure_longitudinal.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_longitudinal.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        figures=canon(config["figures"]),
        testing=canon(config["testing"]),
        quantiles=canon(config["design"]["quantiles"]),
        code=code("figure_longitudinal"),
    script:
        "../../scripts/figure_longitudinal.py"


rule figure_histograms:
    input:
        **STUDY_TWIN_INPUTS,
    output:
        png=report(
            f"{twin_dir()}/figures/histograms.png",
            caption="../report/histograms.rst",
            category="Outcome histograms",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/histograms.pdf",
    log:
        f"{LOGS}/twins/{{twin}}/figure_histograms.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_histograms.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        figures=canon(config["figures"]),
        testing=canon(config["testing"]),
        code=code("figure_histograms"),
    script:
        "../../scripts/figure_histograms.py"


rule figure_sample_sizes:
    input:
        f"{twin_dir()}/results.parquet",
    output:
        png=report(
            f"{twin_dir()}/figures/sample_sizes.png",
            caption="../report/sample_sizes.rst",
            category="Sample sizes",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/sample_sizes.pdf",
    log:
        f"{LOGS}/twins/{{twin}}/figure_sample_sizes.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_sample_sizes.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    params:
        code=code("figure_sample_sizes"),
    script:
        "../../scripts/figure_sample_sizes.py"


rule figure_propensity:
    input:
        f"{twin_dir()}/results.parquet",
    output:
        png=report(
            f"{twin_dir()}/figures/propensity.png",
            caption="../report/propensity.rst",
            category="Sample sizes",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/propensity.pdf",
    log:
        f"{LOGS}/twins/{{twin}}/figure_propensity.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_propensity.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=2000,
        runtime=5,
    params:
        code=code("figure_propensity"),
    script:
        "../../scripts/figure_propensity.py"


rule figure_sensitivity:
    input:
        **STUDY_TWIN_INPUTS,
    output:
        png=report(
            f"{twin_dir()}/figures/sensitivity.png",
            caption="../report/sensitivity.rst",
            category="Sensitivity",
            subcategory="{twin}",
        ),
        pdf=f"{twin_dir()}/figures/sensitivity.pdf",
        csv=f"{twin_dir()}/tables/sensitivity.csv",
    log:
        f"{LOGS}/twins/{{twin}}/figure_sensitivity.log",
    benchmark:
        f"{R}/benchmarks/twins/{{twin}}/figure_sensitivity.tsv"
    priority: 30
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=6000,
        runtime=30,
    params:
        figures=canon(config["figures"]),
        testing=canon(config["testing"]),
        seed=config["seed"],
        code=code("figure_sensitivity"),
    script:
        "../../scripts/figure_sensitivity.py"


rule figure_confounding:
    input:
        d=f"{R}/d.parquet",
        actions=f"{R}/design/actions.json",
    output:
        png=report(
            f"{R}/figures/confounding.png",
            caption="../report/confounding.rst",
            category="Design",
        ),
        pdf=f"{R}/figures/confounding.pdf",
    log:
        f"{LOGS}/figure_confounding.log",
    benchmark:
        f"{R}/benchmarks/figure_confounding.tsv"
    conda:
        "../../envs/twinfalsify.yaml"
    resources:
        mem_mb=4000,
        runtime=10,
    params:
        figures=canon(config["figures"]),
        source=canon(config["source"]),
        seed=config["seed"],
        code=code("figure_confounding"),
    script:
        "../../scripts/figure_confounding.py"
