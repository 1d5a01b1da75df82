# twinfalsify: causal falsification of digital twins (Cornish et al., JMLR 2026).
# Run the default study:  snakemake --cores 2
#
# The workflow itself is workflow/Snakefile (the Snakemake workflow catalog's layout, and the
# file a deployment loads as a module: docs/how-to/deploy.md). It is included as the
# `include:` directive does, keeping its default target (rule all), which a plain include
# would drop.
workflow.include("workflow/Snakefile", overwrite_default_target=True)
