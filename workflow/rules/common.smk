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
    out = [f"{R}/tables/action_space.csv", f"{R}/design/report.csv"]
    for twin in TWINS:
        out += [
            f"{twin_dir(twin)}/results.parquet",
            f"{twin_dir(twin)}/tables/rejections.csv",
            f"{twin_dir(twin)}/figures/pvalues.png",
            f"{twin_dir(twin)}/figures/pvalues.pdf",
        ]
    return out
