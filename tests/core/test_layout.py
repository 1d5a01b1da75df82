"""The library's import graph: no cycle anywhere, and no module imports a layer above its own.

Every ``import`` is counted, including those inside functions (a lazy import is still a
dependency); the parser is ``twinfalsify.provenance``, which also gives the workflow's rules
their code fingerprints. The layers, bottom to top, are ``LAYERS`` below
(docs/reference/layout.md, "Where things live").
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from helpers.paths import SRC

from twinfalsify import provenance

PKG = SRC / "twinfalsify"

# A module may import its own layer and the layers below it, never one above.
LAYERS: list[tuple[str, ...]] = [
    ("twinfalsify", "schema", "io", "noise", "provenance", "unitscreen"),
    ("sources",),
    ("split", "design", "inference", "tables"),
    ("bounds", "stored_runs"),
    ("falsify", "twin_tests"),
    ("twins",),
    ("runs", "studyconfig"),
    ("pulse",),
    ("summary", "figures", "calibration", "explain", "readme_table", "config_reference",
     "diff", "release"),
]
LAYER_OF = {top: i for i, tops in enumerate(LAYERS) for top in tops}


def modules() -> dict[str, Path]:
    return provenance.modules(SRC)


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    return provenance.imports_of(name, path, known)


def graph() -> dict[str, set[str]]:
    return provenance.graph(SRC)


def layer(name: str) -> int:
    parts = name.split(".")
    top = parts[1] if len(parts) > 1 else parts[0]
    if top not in LAYER_OF:
        pytest.fail(f"{name}: top-level module {top!r} is in no layer of tests/core/test_layout.py")
    return LAYER_OF[top]


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(g.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(g):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_no_import_cycle():
    cycle = find_cycle(graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_upward_import():
    bad = [f"{a} (layer {layer(a)}) imports {b} (layer {layer(b)})"
           for a, deps in graph().items() for b in deps if layer(b) > layer(a)]
    assert not bad, "upward imports:\n" + "\n".join(sorted(bad))


def test_every_package_states_its_one_job():
    for init in PKG.rglob("__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 40, f"{init.relative_to(SRC)}: no docstring saying its job"


def test_checker_finds_a_cycle_and_an_upward_edge():
    """The checks above can fail: a hand-made graph with a cycle and an upward edge."""
    g = {"twinfalsify.runs.runner": {"twinfalsify.runs.protocol_twin"},
         "twinfalsify.runs.protocol_twin": {"twinfalsify.runs.runner"}}
    assert find_cycle(g) == ["twinfalsify.runs.protocol_twin", "twinfalsify.runs.runner",
                             "twinfalsify.runs.protocol_twin"]
    assert layer("twinfalsify.sources.synthetic") < layer("twinfalsify.twins.builtin")
    known = set(modules())
    # the old layout's edge, parsed from source text
    src = PKG / "sources" / "synthetic.py"
    assert "twinfalsify.noise" in imports_of("twinfalsify.sources.synthetic", src, known)


def _brute_force_imports(path: Path) -> list[tuple]:
    """Every import statement, found by visiting every node of the file's syntax tree."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.append((None, "", [a.name for a in node.names]))
        elif isinstance(node, ast.ImportFrom):
            out.append((node.level, node.module or "", [a.name for a in node.names]))
    return sorted(out, key=repr)


def test_cached_import_statements_are_every_import_of_every_file(tmp_path, monkeypatch):
    """The statement-only walk and its bytes-keyed cache give what a walk of every node of
    the syntax tree gives, for every library file and rule script; an edited file is parsed
    again (never a stale answer); an unwritable cache folder is no error."""
    monkeypatch.setattr(provenance, "_CACHE", provenance._ImportCache())
    monkeypatch.setenv(provenance.CACHE_ENV, str(tmp_path / "cache"))
    files = [*PKG.rglob("*.py"), *(SRC.parent / "scripts").glob("*.py")]
    for fresh in (True, False):  # parsed, then read back from the cache file
        provenance._CACHE = provenance._ImportCache()
        for f in files:
            assert sorted(provenance.import_statements(f), key=repr) == \
                _brute_force_imports(f), f
        provenance._CACHE.save()
        assert provenance._CACHE.path.is_file() and not provenance._CACHE.dirty
        assert fresh or len(provenance._CACHE.entries) == len({f.read_bytes() for f in files})
    edited = tmp_path / "m.py"
    edited.write_text("def f():\n    try:\n        import a.b\n    finally:\n        pass\n")
    assert provenance.import_statements(edited) == [(None, "", ["a.b"])]
    edited.write_text("class C:\n    if x:\n        from .. import y\n")
    assert provenance.import_statements(edited) == [(2, "", ["y"])]
    (tmp_path / "ro").write_text("a file where the cache folder should be")
    monkeypatch.setenv(provenance.CACHE_ENV, str(tmp_path / "ro"))
    cache = provenance._ImportCache()
    cache.get(edited)
    cache.save()  # cannot write: parsed again next time, no error
    assert cache.dirty


def test_the_report_layer_reads_stored_runs_without_the_executor():
    """What reports on a study (summary, figures, explain, diff) and the one path to its
    p-values (twin_tests) read stored twin runs through ``stored_runs``, never by importing
    the executor that made them (``runs``)."""
    g = graph()
    readers = [m for m in g if m.split(".")[1:2] and m.split(".")[1] in
               ("summary", "figures", "explain", "diff", "twin_tests")]
    assert readers
    seen = set()
    todo = list(readers)
    while todo:  # everything they import, transitively
        m = todo.pop()
        for dep in g.get(m, ()):
            if dep not in seen:
                seen.add(dep)
                todo.append(dep)
    executor = sorted(m for m in seen if m.startswith("twinfalsify.runs"))
    assert executor == [], executor
