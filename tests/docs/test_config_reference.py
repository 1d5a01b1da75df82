"""The configuration reference: complete, committed in sync, and true to what a run does.

``docs/reference/config.md`` is generated from the config schema and the test methods' option
specs (``twinfalsify.config_reference``); these tests fail when the committed page is stale,
when a key lacks a meaning, a type or a default, when an example would be refused, and when
a documented option default or limit differs from the method's own signature and checks.
"""

from __future__ import annotations

import copy
import inspect
import math
import re
from html.parser import HTMLParser

import jsonschema
import markdown
import pytest
import yaml

from twinfalsify import config_reference as ref
from twinfalsify.inference import registry
from twinfalsify.inference.option_docs import METHOD_DOCS, OPTIONS
from twinfalsify.schema import ContractError

SCHEMA = ref.load_schema()
NOWRAP = '<code style="white-space: nowrap">{}</code>'


def _section(page: str, heading: str) -> str:
    start = page.index(heading + "\n")
    nxt = page.find("\n## ", start + len(heading))
    return page[start:] if nxt < 0 else page[start:nxt]


def test_committed_page_is_what_the_schema_gives():
    assert ref.PAGE.read_text() == ref.render(SCHEMA), "run: make config-reference"
    assert ref.main(["--check"]) == 0


def test_a_stale_page_is_detected(tmp_path, monkeypatch):
    stale = tmp_path / "config.md"
    stale.write_text(ref.render(SCHEMA).replace("D0 trajectories a parameter set", "D0 rows"))
    monkeypatch.setattr(ref, "PAGE", stale)
    assert ref.main(["--check"]) == 1


def test_every_key_has_meaning_type_default_and_example():
    assert ref.problems(SCHEMA) == []


@pytest.mark.parametrize("path, drop, expected", [
    (("properties", "seed"), "description", "seed: no description"),
    (("properties", "design", "properties", "horizon"), "x-default",
     "design.horizon: no default"),
    (("properties", "twins", "additionalProperties", "properties", "timeout_s"), "x-default",
     "twins.<name>.timeout_s: no default"),
    (("properties", "twin_runs", "properties", "n_shards"), "examples",
     "twin_runs.n_shards: no example"),
])
def test_a_key_missing_its_meaning_or_default_is_named(path, drop, expected):
    schema = copy.deepcopy(SCHEMA)
    node = schema
    for key in path:
        node = node[key]
    if drop == "x-default":
        node.pop("default", None)
    del node[drop]
    assert any(p.startswith(expected) for p in ref.problems(schema)), ref.problems(schema)


def _leaves(node: dict, path: str = ""):
    """(section heading path, key, node) of every leaf key of the schema."""
    inner = node if "properties" in node else node.get("additionalProperties", {})
    for key, sub in inner.get("properties", {}).items():
        if ref._is_group(sub):
            yield from _leaves(sub, (f"{path}.{key}" if path else key)
                               + ("" if "properties" in sub else ".<name>"))
        else:
            yield path, key, sub


def test_every_schema_key_is_on_the_page_in_its_section_unwrapped():
    page = ref.render(SCHEMA)
    leaves = list(_leaves(SCHEMA))
    assert len(leaves) > 80
    for path, key, _ in leaves:
        heading = f"## `{path}`" if path else "## Top level"
        assert NOWRAP.format(key) in _section(page, heading), f"{path}.{key} not on the page"
    row = next(line for line in _section(page, "## `design`").splitlines()
               if NOWRAP.format("min_support") in line)
    assert "*default* <code>10</code>" in row and "*limits* &gt;= 1" in row
    row = next(line for line in _section(page, "## `testing`").splitlines()
               if NOWRAP.format("correction") in line)
    assert "holm" in row and "bonferroni" in row and "*default* <code>holm</code>" in row
    # a doc path in a description becomes a link the strict site build checks
    assert "[explanation/sequential.md](../explanation/sequential.md)" in page


def test_every_example_passes_the_schema():
    """An example on the page is a value the workflow accepts for that key."""
    for path, key, sub in _leaves(SCHEMA):
        for example in sub.get("examples", []):
            assert not list(jsonschema.Draft202012Validator(sub).iter_errors(example)), \
                (path, key, example)


def test_every_method_option_is_documented_from_its_spec():
    page = ref.render(SCHEMA)
    assert set(OPTIONS) == set(registry.METHODS) == set(METHOD_DOCS)
    for method, (_, allowed, _) in registry.METHODS.items():
        assert set(OPTIONS[method]) == set(allowed), method
        section = page[page.index(f"### `{method}`"):]
        for name in allowed:
            assert NOWRAP.format(name) in section.split("\n### ")[0], (method, name)


def _method(name: str):
    target = registry.METHODS[name][0]
    module, func = target.split(":")
    mod = __import__(module, fromlist=[func])
    return mod, getattr(mod, func)


@pytest.mark.parametrize("method", [m for m in OPTIONS if OPTIONS[m]])
def test_documented_defaults_are_the_methods_defaults(method):
    _, fn = _method(method)
    params = inspect.signature(fn).parameters
    for name, doc in OPTIONS[method].items():
        assert params[name].default == doc.default, (method, name)


def _check(method: str, opts: dict) -> bool:
    try:
        registry.make(method, opts, seed=0)
    except ContractError:
        return False
    return True


@pytest.mark.parametrize("method", [m for m in OPTIONS if OPTIONS[m]])
def test_documented_limits_are_the_checks_limits(method):
    """The example is accepted (with the options it needs); a value just past a documented
    bound is refused; a closed bound itself is accepted; a choice outside the listed ones is
    refused."""
    for name, doc in OPTIONS[method].items():
        need = dict(doc.needs)
        assert _check(method, {**need, name: doc.example}), (method, name, doc.example)
        integer = doc.type.startswith("integer")
        step = 1 if integer else 1e-9
        for bound, sign, is_open in ((doc.lo, -1, doc.lo_open), (doc.hi, 1, doc.hi_open)):
            if bound is None:
                continue
            at = int(bound) if integer else bound
            assert not _check(method, {**need, name: at + sign * step}), (method, name,
                                                                          "past", bound)
            assert _check(method, {**need, name: at}) != is_open, (method, name, "at", bound)
        if doc.choices:
            assert not _check(method, {name: "no-such-choice"}), (method, name)
            for c in doc.choices:
                assert _check(method, {name: c}), (method, name, c)
        if doc.lo is None and doc.hi is None and not doc.choices and "boolean" in doc.type:
            assert not _check(method, {name: 1}), (method, name)


def test_the_bootstrap_floor_limit_tracks_n_resamples():
    """p_floor < 2 / n_resamples: the page's 0.02 is the bound at the default B = 100."""
    doc = OPTIONS["bootstrap"]["p_floor"]
    assert math.isclose(doc.hi, 2 / OPTIONS["bootstrap"]["n_resamples"].default)
    assert _check("bootstrap", {"n_resamples": 1000, "p_floor": 0.0019})
    assert not _check("bootstrap", {"n_resamples": 1000, "p_floor": 0.002})


def test_no_key_name_wraps_on_the_page():
    """Key names and values are in nowrap code: no bare backticked key in a table row."""
    for line in ref.render(SCHEMA).splitlines():
        if line.startswith("| <code"):
            first = line.split(" | ")[0]
            assert re.fullmatch(r"\| <code style=\"white-space: nowrap\">[^<]+</code>", first)


class _Tables(HTMLParser):
    """The cells of every HTML table, as text: tables -> rows -> cells."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.in_cell = False

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self.tables[-1][-1].append("")
            self.in_cell = True

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.in_cell = False

    def handle_data(self, data):
        if self.in_cell:
            self.tables[-1][-1][-1] += data


def _html(page: str) -> str:
    """The page as the site's Markdown renders it (the extensions of mkdocs.yml that make
    tables)."""
    site = yaml.safe_load((ref.ROOT / "mkdocs.yml").read_text())
    names = [e if isinstance(e, str) else next(iter(e)) for e in site["markdown_extensions"]]
    return markdown.markdown(page, extensions=[e for e in names if e in ("tables", "toc")])


def test_every_table_is_two_columns_a_short_key_and_its_meaning():
    """No table is wider than the page: each row is the key (one short word that never
    wraps) and one wide column with the meaning, then type, default, limits and example, so
    the meaning has most of the width in every section (the config's first keys too)."""
    page = ref.render(SCHEMA)
    for line in page.splitlines():
        if line.startswith("|"):
            assert len(re.split(r"(?<!\\)\|", line.strip())) == 4, line  # 2 cells
    parser = _Tables()
    parser.feed(_html(page))
    assert len(parser.tables) >= 19
    longest = 0
    for table in parser.tables:
        assert table[0] == ["key", "meaning"], table[0]
        for key, cell in table[1:]:
            longest = max(longest, len(key))
            assert " " not in key and "*type* " not in cell and "type " in cell, (key, cell)
    assert longest <= 24, longest
    # each leaf key's row holds its description, its type and its default as the page's
    # Markdown renders them
    rows = {(t, r[0]): r[1] for t, table in enumerate(parser.tables) for r in table[1:]}
    for _, key, sub in _leaves(SCHEMA):
        text = sub["description"]
        assert any(k == key and text.split(" (")[0][:40] in cell
                   for (_, k), cell in rows.items()), key
    design = next(t for t in parser.tables if any(r[0] == "quantiles" for r in t))
    cell = next(r[1] for r in design if r[0] == "quantiles")
    assert cell.startswith("y_lo, y_up = these quantiles")
    assert "default [0.2, 0.8]" in cell and "limits 2 items, each item >= 0 and <= 1" in cell
