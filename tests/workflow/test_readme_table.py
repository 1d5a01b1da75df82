"""The README's rejection table is what ``twinfalsify.readme_table`` gives from a study.

The generator is checked on the tiny study the suite builds anyway (``test_study``): its counts
against the results read independently, its unit sentence, and that the README's block has the
generator's format. Where the default study's results exist in the checkout
(``results/synthetic`` after ``make reproduce``), the README's numbers must equal the
generator's output on them (``make readme-table`` rewrites them).
"""

from __future__ import annotations

import re

import pandas as pd
import pytest
from helpers.paths import ROOT

from twinfalsify import readme_table as rt

ROW = re.compile(r"\| [A-Za-z0-9._-]+ \|( (\d+ / \d+|-) \|)+")


def test_generator_counts_the_tiny_studys_hypotheses(test_study):
    work, config = test_study
    study = work / "results" / "test"
    c = rt.counts(study, config)
    assert list(pd.unique(c["twin"])) == ["oracle", "biased"]  # the config's order
    for twin in ("oracle", "biased"):
        res = pd.read_parquet(study / "twins" / twin / "results.parquet")
        for (m, k), part in res.groupby(["method", "kind"]):
            row = c[(c["twin"] == twin) & (c["method"] == m) & (c["kind"] == k)].iloc[0]
            assert row["rejected"] == part["rejected"].sum()
            assert row["hypotheses"] == len(part) == 2 * part["hyp_id"].nunique()
    text = rt.markdown(c)
    sets = c.drop_duplicates("kind").set_index("kind")["parameter_sets"]
    assert (f"{sets['causal']} causal parameter sets and {sets['manski']} Manski parameter "
            "sets, two one-sided hypotheses") in text
    assert "Holm at family-wise error 0.05" in text
    lines = text.splitlines()
    assert lines[2] == "| twin | Hoeffding causal | Hoeffding Manski |"
    biased = c[c["twin"] == "biased"].set_index("kind")
    assert lines[-1] == (f"| biased | {biased.loc['causal', 'rejected']} / "
                         f"{biased.loc['causal', 'hypotheses']} | "
                         f"{biased.loc['manski', 'rejected']} / "
                         f"{biased.loc['manski', 'hypotheses']} |")
    # rewriting a README block and reading it back gives the table
    readme = f"intro\n{rt.START}\nold\n{rt.END}\nrest\n"
    assert rt.readme_block(rt.replace_block(readme, text)) == text
    assert rt.main([str(work / "results" / "missing")]) == 1


def test_the_readme_block_has_the_generators_format():
    block = rt.readme_block((ROOT / "README.md").read_text())
    lines = block.splitlines()
    assert lines[0].startswith("Each cell: rejected hypotheses / hypotheses tested (")
    m = re.search(r"(\d+) causal parameter sets and (\d+) Manski parameter sets", lines[0])
    assert m, lines[0]
    header = [h.strip() for h in lines[2].strip("|").split("|")]
    assert header[0] == "twin" and all(re.fullmatch(r"\w+ (causal|Manski)", h)
                                       for h in header[1:])
    rows = lines[4:]
    assert rows and all(ROW.fullmatch(r) for r in rows), rows
    # the unit: a column's denominator is twice its kind's parameter sets
    for r in rows:
        cells = [x.strip() for x in r.strip("|").split("|")][1:]
        for h, cell in zip(header[1:], cells, strict=True):
            want = 2 * int(m.group(1) if h.endswith("causal") else m.group(2))
            assert cell == "-" or int(cell.split(" / ")[1]) == want, (h, cell)


def test_the_readme_numbers_are_the_default_studys():
    study = ROOT / "results" / "synthetic"
    if not (study / "twins").is_dir():
        pytest.skip("no results/synthetic: run make reproduce (then make readme-table)")
    want = rt.markdown(rt.counts(study, ROOT / "config" / "config.yaml"))
    assert rt.readme_block((ROOT / "README.md").read_text()) == want, "run make readme-table"
