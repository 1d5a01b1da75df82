import json

from snakemake.utils import validate

validate(config, schema="../schemas/config.schema.yaml")

STUDY = config["study"]
R = f"results/{STUDY}"
TWINS = list(config["twins"])
N_SHARDS = int(config["twin_runs"].get("n_shards", 4))
LOGS = f"{R}/logs"


wildcard_constraints:
    twin="|".join(TWINS),
    shard=r"\d+",


def canon(section):
    """Config section as canonical JSON: a params value whose comparison ignores key order."""
    return json.dumps(section, sort_keys=True)


def twin_dir(twin="{twin}"):
    return f"{R}/twins/{twin}"


def all_outputs():
    import os

    out = [
        f"{R}/tables/action_space.csv",
        f"{R}/design/report.csv",
        f"{R}/tables/action_space_grid.csv",
        f"{R}/tables/action_space.tex",
        f"{R}/summary.md",
        f"{R}/summary.html",
    ]
    if config["source"]["kind"] == "synthetic":  # the truth is known only there
        out += [f"{R}/figures/confounding.{ext}" for ext in ("png", "pdf")]
    # the sensitivity sweep comes with the statistics module; include it once it is there
    has_sweep = os.path.exists(
        os.path.join(
            workflow.basedir, "src", "twinfalsify", "inference", "sensitivity.py"
        )
    )
    figures = ["pvalues", "longitudinal", "histograms", "sample_sizes", "propensity"]
    figures += ["sensitivity"] if has_sweep else []
    for twin in TWINS:
        out += [
            f"{twin_dir(twin)}/results.parquet",
            f"{twin_dir(twin)}/tables/rejections.csv",
            f"{twin_dir(twin)}/tables/rejections.tex",
        ]
        out += [
            f"{twin_dir(twin)}/figures/{f}.{ext}"
            for f in figures
            for ext in ("png", "pdf")
        ]
    return out
