"""The library's import graph, and code fingerprints of what a rule script depends on.

One parser serves two uses: tests/core/test_layout.py checks the graph (no cycle, no upward
import), and the workflow (common.smk) gives every rule a ``code`` param = the fingerprint
of the library modules its script imports, directly or transitively. Snakemake reruns a
job whose params changed, so a fix in ``bounds.py`` reruns exactly the rules whose scripts
reach ``bounds.py`` and nothing else. The script's own bytes are in it too: Snakemake's own
"code" trigger compares a script's modification time with its outputs', so a script
restored with the same bytes (``git checkout``) reruns its rule under it; with
``--rerun-triggers mtime params input`` (the project's profile ``profiles/default``, read at
every start) this fingerprint alone decides, by content.

Every ``import`` counts, including those inside functions (a lazy import is still a
dependency). A module a script only starts as a subprocess by name (``python -m
twinfalsify.runs.serve``) is not an import: a rule names such modules as ``extra``.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import sys
from collections.abc import Iterable, Iterator
from functools import lru_cache
from pathlib import Path

PACKAGE = "twinfalsify"
# Parsed import statements of every file read, keyed by a hash of its bytes: a file's
# imports are a function of its text alone, so the cache is never stale, and a Snakemake
# start (which fingerprints every rule's code) parses only the files that changed.
CACHE_ENV = "TWINFALSIFY_CACHE_DIR"


def module_name(path: Path, src: Path) -> str:
    """Dotted module name of a file under ``src`` (a package's ``__init__`` = the package)."""
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules(src: Path) -> dict[str, Path]:
    """Every module of the library under ``src``: dotted name -> file."""
    return {module_name(p, src): p for p in sorted((src / PACKAGE).rglob("*.py"))}


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """Library modules that the file ``path`` (module ``name``) imports, at any depth.

    Absolute and relative imports; ``from pkg import mod`` counts as importing ``pkg.mod``
    when that is a module. ``name`` may be any label for a file outside the package (a rule
    script); it is only used to resolve relative imports and to drop self-imports.
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for level, base, names in import_statements(path):
        if level is None:  # import a, b.c
            targets = names
        else:
            if level:
                anchor = package.split(".")[: len(package.split(".")) - level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a}" if f"{base}.{a}" in known else base for a in names]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def _statements(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """Import statements at any depth of ``body`` (functions, classes, if/try/with blocks):
    imports are statements, so expressions are never visited."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
            continue
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            inner = getattr(node, field, None)
            if isinstance(inner, list):
                yield from _statements(inner)


def _parse_imports(text: str, path: Path) -> list[tuple[int | None, str, list[str]]]:
    out: list[tuple[int | None, str, list[str]]] = []
    for node in _statements(ast.parse(text, str(path)).body):
        if isinstance(node, ast.Import):
            out.append((None, "", [a.name for a in node.names]))
        else:
            out.append((node.level, node.module or "", [a.name for a in node.names]))
    return out


class _ImportCache:
    """{blake2b of a file's bytes: its import statements}, kept in one JSON file in the
    user's cache folder ($TWINFALSIFY_CACHE_DIR, else $XDG_CACHE_HOME/twinfalsify, else
    ~/.cache/twinfalsify). Unwritable or corrupt: parsed every time, never an error."""

    def __init__(self) -> None:
        base = os.environ.get(CACHE_ENV) or Path(
            os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / PACKAGE
        # the grammar is Python's: one file per Python version
        self.path = Path(base) / f"imports-py{sys.version_info[0]}{sys.version_info[1]}.json"
        self.entries: dict[str, list] | None = None
        self.dirty = False

    def get(self, path: Path) -> list[tuple[int | None, str, list[str]]]:
        data = path.read_bytes()
        key = hashlib.blake2b(data, digest_size=16).hexdigest()
        if self.entries is None:
            try:
                self.entries = json.loads(self.path.read_text())
            except (OSError, ValueError):
                self.entries = {}
        hit = self.entries.get(key)
        if hit is None:
            hit = self.entries[key] = _parse_imports(data.decode(), path)
            self.dirty = True
        return [(lvl, base, list(names)) for lvl, base, names in hit]

    def save(self) -> None:
        if not self.dirty or self.entries is None:
            return
        import tempfile

        tmp = None
        try:  # a temporary file renamed into place: concurrent Snakemake starts never clash
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=".imports-")
            with os.fdopen(fd, "w") as f:
                json.dump(self.entries, f)
            os.chmod(tmp, 0o644)
            os.replace(tmp, self.path)
            self.dirty = False
        except OSError:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)


_CACHE = _ImportCache()


def import_statements(path: Path) -> list[tuple[int | None, str, list[str]]]:
    """(level, module, names) of every import statement in the file, at any depth; level
    None for ``import a, b``. Cached by the file's bytes."""
    return _CACHE.get(path)


def graph(src: Path) -> dict[str, set[str]]:
    """Import graph of the library: module -> library modules it imports."""
    mods = modules(src)
    known = set(mods)
    out = {name: imports_of(name, path, known) for name, path in mods.items()}
    _CACHE.save()
    return out


def closure(starts: Iterable[str], g: dict[str, set[str]]) -> set[str]:
    """Every module reachable from ``starts`` (included), plus the packages they live in
    (importing ``a.b.c`` runs ``a/__init__`` and ``a/b/__init__`` first)."""
    seen: set[str] = set()
    todo = list(starts)
    while todo:
        m = todo.pop()
        if m in seen or m not in g:
            continue
        seen.add(m)
        parts = m.split(".")
        todo.extend(".".join(parts[:k]) for k in range(1, len(parts)))
        todo.extend(g[m])
    return seen


@lru_cache(maxsize=8)
def _graph_cached(src: str) -> dict[str, set[str]]:
    return graph(Path(src))


@lru_cache(maxsize=8)
def _modules_cached(src: str) -> dict[str, Path]:
    """:func:`modules`, listed once per process, as the import graph is (a workflow start
    fingerprints every rule's code; the files' bytes are read each time)."""
    return modules(Path(src))


def _excluded(name: str, exclude: Iterable[str]) -> bool:
    return any(name == e or name.startswith(e + ".") for e in exclude)


def script_modules(script: str | Path, src: str | Path, extra: Iterable[str] = (),
                   exclude: Iterable[str] = ()) -> set[str]:
    """Library modules a rule script depends on: its imports' closure, and ``extra``'s.

    ``exclude``: modules (and their submodules) this config never runs although they are
    imported, e.g. the MIMIC-III source in a synthetic study, or a test method it does not
    use; the caller states why each is safe to leave out (workflow/rules/common.smk).
    """
    g = _graph_cached(str(Path(src).resolve()))
    direct = imports_of("__script__", Path(script), set(g))
    _CACHE.save()
    exclude = tuple(exclude)
    return {m for m in closure([*direct, *extra], g) if not _excluded(m, exclude)}


def code_fingerprint(script: str | Path, src: str | Path, extra: Iterable[str] = (),
                     exclude: Iterable[str] = ()) -> str:
    """SHA-256 (16 hex digits) over the script's bytes and the names and bytes of
    :func:`script_modules`.

    Only what Python executes counts: the fingerprint is of source text, so an edit to a
    comment also changes it (cheap to compute, never misses a change), and a file restored
    to the same bytes (``git checkout``) keeps it: times are never compared.
    """
    src = Path(src).resolve()
    mods = _modules_cached(str(src))
    h = hashlib.sha256()
    h.update(b"__script__\0" + Path(script).read_bytes() + b"\0")  # the script itself
    for name in sorted(script_modules(script, src, extra, exclude)):
        h.update(name.encode() + b"\0" + mods[name].read_bytes() + b"\0")
    return h.hexdigest()[:16]


# Modules a study never runs unless its config asks for them, although rule scripts import
# them. A source's package and rule helper run only in the trajectories rule's branch for
# that source kind (the synthetic source is also the oracle/biased twins' world: never left
# out). A test method's module runs only when the method is in use: the registry binds
# methods by name, and the other modules that import one (inference.failures) only compare
# a bound method with it. The sequential (adaptive) test bets whatever the methods are.
SOURCE_MODULES: dict[str, tuple[str, ...]] = {
    "mimic3": ("twinfalsify.sources.mimic3", "twinfalsify.sources.mimic_rule",
               "twinfalsify.sources.checksums"),
    # MIMIC-IV runs the MIMIC-III cohort code on its own table layout
    "mimic4": ("twinfalsify.sources.mimic4", "twinfalsify.sources.mimic3",
               "twinfalsify.sources.mimic_rule", "twinfalsify.sources.checksums"),
    "table": ("twinfalsify.sources.table",),
    # the meds source reads the MIMIC item tables (its preset) and the MIMIC value rules
    "meds": ("twinfalsify.sources.meds", "twinfalsify.sources.mimic3"),
}
METHOD_MODULES: dict[str, str] = {
    "bootstrap": "twinfalsify.inference.bootstrap",
    "betting": "twinfalsify.inference.betting",
    "bernstein": "twinfalsify.inference.bernstein",
    "hoeffding": "twinfalsify.inference.hoeffding",
}
NEVER_LEFT_OUT = {"twinfalsify.inference.hoeffding"}  # its radius draws the figures' bounds
# The protocol client: a builtin twin simulated in the shard's own process (kind oracle,
# biased or fitted without ``protocol``) never runs it, although the shard script imports
# it (the registry reads the runner's default breaker settings, which apply to protocol
# twins only, and checks a command twin's command; the plan tells a protocol twin apart by
# type); no other rule script starts a twin. Left out of every rule but the shards of twins
# that run through it (workflow/rules/common.smk), so an edit of the client reruns only those.
PROTOCOL_CLIENT_MODULES = ("twinfalsify.runs.runner", "twinfalsify.runs.worker",
                           "twinfalsify.runs.command", "twinfalsify.runs.protocol_twin",
                           "twinfalsify.runs.protocol")


def code_scope(config: dict, all_methods: bool = False) -> tuple[list[str], list[str]]:
    """(methods in use, modules to leave out) of a study config, for :func:`code_fingerprint`.

    The first are the modules of ``testing.methods`` (bound by name, so not seen as imports:
    a rule that tests gives them as ``extra``); ``all_methods``: every method counts as in
    use (the calibration stage has its own list of methods). The second: the source packages
    of other source kinds, and the modules of methods not in use (fixed mode only).
    """
    kind = (config.get("source") or {}).get("kind")
    used_here = set(SOURCE_MODULES.get(kind, ()))
    leave = sorted({m for k, mods in SOURCE_MODULES.items() if k != kind for m in mods}
                   - used_here)
    names = set(METHOD_MODULES) if all_methods else set(
        (config.get("testing") or {}).get("methods") or {})
    used = sorted(METHOD_MODULES[n] for n in names if n in METHOD_MODULES)
    adaptive = (config.get("twin_runs") or {}).get("mode", "fixed") == "adaptive"
    for name, mod in METHOD_MODULES.items():
        if name in names or mod in NEVER_LEFT_OUT or (adaptive and name == "betting"):
            continue
        leave.append(mod)
    return used, leave


#: the packages whose versions a study's summary lists (its "Software" table)
SOFTWARE = ("twinfalsify", "snakemake", "numpy", "numba", "pandas", "scipy", "pyarrow", "duckdb",
            "matplotlib", "seaborn")


def software_versions() -> list[tuple[str, str]]:
    """(name, version) of Python and of each package of :data:`SOFTWARE` in this process's
    environment ("not installed" for one that is missing)."""
    from importlib.metadata import PackageNotFoundError, version

    out = [("python", sys.version.split()[0])]
    for name in SOFTWARE:
        try:
            out.append((name, version(name)))
        except PackageNotFoundError:
            out.append((name, "not installed"))
    return out
