"""The README's rejection table and headline figure are what ``twinfalsify.readme_table``
gives from a study.

The generator is checked on the tiny study the suite builds anyway (``test_study``): its counts
and the headline caption's numbers against the results and the figure's data read
independently, its unit sentence, and that the README's blocks have the generator's format.
Where the default study's results exist in the checkout (``results/synthetic`` after
``make reproduce``), the README's numbers, caption and image must equal the generator's
output on them (``make readme-table`` rewrites them).
"""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
from helpers.paths import ROOT

from twinfalsify import readme_table as rt
from twinfalsify.design import WHOLE_SPACE

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


def _rejected_hours(study, twin: str, frame: pd.DataFrame) -> dict[str, list[int]]:
    """Per method, the hours of the figure's path whose own hypothesis is rejected (either
    side): by a plain loop over the hypotheses table and the results."""
    hyps = pd.read_parquet(study / "design" / "hypotheses.parquet")
    res = pd.read_parquet(study / "twins" / twin / "results.parquet")
    out: dict[str, list[int]] = {m: [] for m in res["method"].unique()}
    for r in frame.itertuples(index=False):
        for h in hyps.itertuples(index=False):
            if (h.outcome == r.outcome and h.kind == r.kind and h.t == r.t
                    and list(h.actions) == json.loads(r.actions)
                    and list(h.bins) == json.loads(r.bins)):
                for m in out:
                    rows = res[(res["hyp_id"] == h.hyp_id) & (res["method"] == m)]
                    if rows["rejected"].any():
                        out[m].append(int(r.t))
    return out


def test_the_figure_caption_is_the_tiny_studys_figure(test_study, tmp_path):
    """The caption's outcome, hours, B-set, n, n-hat, rejected hours and correction are those
    of the figure's data and the results; the image is the study's figure, linked relative to
    each page it is written into."""
    work, config = test_study
    study = work / "results" / "test"
    twin = "biased"
    frame = pd.read_csv(study / "twins" / twin / "figures" / "longitudinal.csv")
    facts = rt.figure_facts(study, twin)
    want = _rejected_hours(study, twin, frame)
    assert facts["rejected"] == want and any(want.values())
    caption = rt.figure_caption(facts)
    assert caption.startswith(f"*Bounds over time (study `test`, twin `{twin}`): "
                              f"{frame['outcome'].iloc[0]} (")
    assert f"at hours {frame['t'].min()}-{frame['t'].max()} " in caption
    n, nhat = frame["n"].tolist(), frame["nhat"].tolist()
    got = re.search(r"n = ([\d,]+)(?: \(hour \d\) to ([\d,]+))? test-set", caption)
    assert int(got.group(1).replace(",", "")) == n[0]
    assert int((got.group(2) or got.group(1)).replace(",", "")) == n[-1]
    got = re.search(r"n-hat = ([\d,]+)(?: \(hour \d\) to ([\d,]+))? twin runs", caption)
    assert int(got.group(1).replace(",", "")) == nhat[0]
    assert int((got.group(2) or got.group(1)).replace(",", "")) == nhat[-1]
    bins = json.loads(frame["bins"].iloc[-1])
    if len(set(bins)) == 1 and bins[0] != WHOLE_SPACE:
        assert f"subgroup B = {bins[0]} " in caption
    res = pd.read_parquet(study / "twins" / twin / "results.parquet")
    assert f"{rt.CORRECTION_NAMES[res['correction'].iloc[0]]} at family-wise error" in caption
    for method, hours in want.items():
        if hours:
            name = rt.METHOD_NAMES[method]
            clause = re.search(rf"the ([\w ,]*?){name}([\w ,]*?) tests? (?:rejects? it )?at "
                               r"t = ([\d ,and-]+)", caption)  # fmt: skip
            assert clause and clause.group(3).rstrip(" ,") == rt._hours(hours), caption
    below = (frame["q_twin_hat"] < frame["q_lo_hat"]).all()
    above = (frame["q_twin_hat"] > frame["q_up_hat"]).all()
    if below or above:
        assert f"lies {'below' if below else 'above'} the " in caption
    # written into a README and a page in another folder: blocks, image and relative links
    readme, page = tmp_path / "README.md", tmp_path / "docs" / "reference" / "figures.md"
    page.parent.mkdir(parents=True)
    blocks = f"{rt.START}\nold\n{rt.END}\ntext\n{rt.FIG_START}\nold\n{rt.FIG_END}\nrest\n"
    readme.write_text(blocks)
    page.write_text("intro\n" + blocks.split(rt.END + "\ntext\n")[1])
    assert rt.main([str(study), "--config", str(config), "--readme", str(readme), "--page",
                    str(page), "--figure-twin", twin]) == 0  # fmt: skip
    image = tmp_path / "docs" / "img" / f"longitudinal_{twin}.png"
    assert image.read_bytes() == (study / "twins" / twin / "figures" /
                                  "longitudinal.png").read_bytes()  # fmt: skip
    got = rt.readme_block(readme.read_text(), rt.FIG_START, rt.FIG_END)
    assert got == rt.figure_block(facts, f"docs/img/longitudinal_{twin}.png")
    assert rt.readme_block(page.read_text(), rt.FIG_START, rt.FIG_END) == rt.figure_block(
        facts, f"../img/longitudinal_{twin}.png")
    assert rt.readme_block(readme.read_text()) == rt.markdown(rt.counts(study, config))


def test_the_readme_block_has_the_generators_format():
    block = rt.readme_block((ROOT / "README.md").read_text())
    lines = block.splitlines()
    assert lines[0].startswith("Each cell: rejected hypotheses / hypotheses (")
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


def test_the_readme_figure_block_has_the_generators_format():
    """The README and the figures page show the same committed image with the same alt text
    and caption, each linked relative to its page."""
    readme = rt.readme_block((ROOT / "README.md").read_text(), rt.FIG_START, rt.FIG_END)
    page = rt.readme_block((ROOT / "docs" / "reference" / "figures.md").read_text(),
                           rt.FIG_START, rt.FIG_END)  # fmt: skip
    m = re.fullmatch(r"!\[(Bounds over time for [^\]]+)\]\((docs/img/longitudinal_\w+\.png)\)"
                     r"\n\n(\*Bounds over time \(study `[\w.-]+`, twin `\w+`\): [^\n]+\*)\n",
                     readme)  # fmt: skip
    assert m, readme
    assert (ROOT / m.group(2)).is_file()
    assert page == readme.replace(f"({m.group(2)})", f"(../{m.group(2)[len('docs/'):]})")
    caption = m.group(3)
    assert re.search(r"n = [\d,]+.* test-set trajectories, the twin's mean on n-hat = [\d,]+",
                     caption), caption


def test_the_readme_numbers_are_the_default_studys():
    study = ROOT / "results" / "synthetic"
    if not (study / "twins").is_dir():
        pytest.skip("no results/synthetic: run make reproduce (then make readme-table)")
    want = rt.markdown(rt.counts(study, ROOT / "config" / "config.yaml"))
    text = (ROOT / "README.md").read_text()
    assert rt.readme_block(text) == want, "run make readme-table"
    facts = rt.figure_facts(study, rt.FIGURE_TWIN)
    assert rt.readme_block(text, rt.FIG_START, rt.FIG_END) == rt.figure_block(
        facts, f"docs/img/longitudinal_{rt.FIGURE_TWIN}.png"), "run make readme-table"
    image = ROOT / "docs" / "img" / f"longitudinal_{rt.FIGURE_TWIN}.png"
    assert image.read_bytes() == (rt.figure_dir(study, rt.FIGURE_TWIN) /
                                  "longitudinal.png").read_bytes(), "run make readme-table"
