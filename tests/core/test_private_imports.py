"""No module of the package reaches into another one's private names.

An underscore name is a module's own business: it may change or go without notice, so a
module that needs it from elsewhere means the name is in the wrong place or wants to be
public. Every module under ``src/twinfalsify`` is parsed (``ast``) for

- ``from twinfalsify.x import _y`` (also relative: ``from .x import _y``), and
- ``m._y`` where ``m`` is a twinfalsify module bound by an import
  (``from twinfalsify.runs import runner`` ... ``runner._y``; ``import twinfalsify.x as m``).

Dunder names (``__version__``, ``__file__``) are public. A hit fails the test listing every
offender as ``file:line: name``.
"""

from __future__ import annotations

import ast
from pathlib import Path

from helpers.paths import ROOT

SRC = ROOT / "src"
PACKAGE = "twinfalsify"


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_module(dotted: str) -> bool:
    """Whether ``dotted`` names a module or package of the source tree."""
    base = SRC.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _absolute(node: ast.ImportFrom, here: str, is_package: bool) -> str | None:
    """The absolute module an ImportFrom reads from (resolving relative imports)."""
    if not node.level:
        return node.module
    parts = here.split(".")
    base = parts if is_package else parts[:-1]
    if node.level > 1:
        base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _dotted(node: ast.expr) -> str | None:
    """``a.b.c`` of a Name/Attribute chain, else None."""
    names: list[str] = []
    while isinstance(node, ast.Attribute):
        names.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    names.append(node.id)
    return ".".join(reversed(names))


def private_imports(path: Path) -> list[str]:
    """Every private name of another twinfalsify module ``path`` uses, as ``file:line: name``."""
    here = _module_name(path)
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    rel = path.relative_to(ROOT).as_posix()
    hits: list[str] = []
    modules: dict[str, str] = {}  # local name -> twinfalsify module it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            source = _absolute(node, here, is_package)
            if not source or not (source == PACKAGE or source.startswith(PACKAGE + ".")):
                continue
            for alias in node.names:
                if _is_private(alias.name) and source != here:
                    hits.append(f"{rel}:{node.lineno}: from {source} import {alias.name}")
                elif _is_module(f"{source}.{alias.name}"):
                    modules[alias.asname or alias.name] = f"{source}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == PACKAGE or alias.name.startswith(PACKAGE + "."):
                    if alias.asname:
                        modules[alias.asname] = alias.name
                    else:  # ``import twinfalsify.x`` binds ``twinfalsify``
                        modules[PACKAGE] = PACKAGE
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and _is_private(node.attr)):
            continue
        dotted = _dotted(node.value)
        if dotted is None:
            continue
        head, _, rest = dotted.partition(".")
        if head not in modules:
            continue
        target = modules[head] + (f".{rest}" if rest else "")
        if _is_module(target) and target != here:
            hits.append(f"{rel}:{node.lineno}: {target}.{node.attr}")
    return hits


def test_no_module_imports_another_modules_private_names():
    offenders = sorted(h for p in (SRC / PACKAGE).rglob("*.py") for h in private_imports(p))
    assert not offenders, (
        "private names used from another module (make them public, or move them where "
        "they are used):\n" + "\n".join(offenders))


def test_the_check_finds_each_form(tmp_path, monkeypatch):
    """Each form is caught; a module's own private names, dunders and public names are not."""
    pkg = tmp_path / "src" / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    for f in ("__init__.py", "a.py", "sub/__init__.py", "sub/b.py"):
        (pkg / f).write_text("")
    (pkg / "sub" / "c.py").write_text(
        "from twinfalsify.a import _x, y\n"
        "from .b import _z\n"
        "from twinfalsify.sub import b\n"
        "import twinfalsify.a as a\n"
        "import twinfalsify.sub.b\n"
        "from twinfalsify import __version__\n"
        "_own = 1\n"
        "b._w, a._v, twinfalsify.sub.b._u, a.__name__, y._not_a_module, b.public\n"
    )
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    monkeypatch.setattr(__import__(__name__), "SRC", tmp_path / "src")
    hits = private_imports(pkg / "sub" / "c.py")
    assert [h.split(": ", 1)[1] for h in hits] == [
        "from twinfalsify.a import _x",
        "from twinfalsify.sub.b import _z",
        "twinfalsify.sub.b._w",
        "twinfalsify.a._v",
        "twinfalsify.sub.b._u",
    ], hits
