"""The library's import graph: no cycle anywhere, and no module imports a layer above its own.

Every ``import`` is counted, including those inside functions (a lazy import is still a
dependency). The layers, bottom to top, are ``LAYERS`` below (README, "Where things live").
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PKG = SRC / "twinfalsify"

# A module may import its own layer and the layers below it, never one above.
LAYERS: list[tuple[str, ...]] = [
    ("twinfalsify", "schema", "io", "noise"),
    ("sources",),
    ("split", "design", "bounds", "inference", "falsify", "tables"),
    ("twins",),
    ("runs",),
    ("pulse",),
    ("summary", "figures", "calibration"),
]
LAYER_OF = {top: i for i, tops in enumerate(LAYERS) for top in tops}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """Library modules that ``name`` imports (absolute or relative, at any depth)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            # "from pkg import mod" imports the module pkg.mod when there is one
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                       for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    return {name: imports_of(name, path, known) for name, path in mods.items()}


def layer(name: str) -> int:
    parts = name.split(".")
    top = parts[1] if len(parts) > 1 else parts[0]
    if top not in LAYER_OF:
        pytest.fail(f"{name}: top-level module {top!r} is in no layer of tests/test_layout.py")
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
