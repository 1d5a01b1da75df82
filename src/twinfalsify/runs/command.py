"""A ``kind: command`` twin's command: checked when the config is read, and fingerprinted.

Check (:func:`check_command`, called by ``runs.registry.check_spec`` at parse time): the
command is not blank; its program resolves (on PATH, or a file that exists and is
executable); a script named to an interpreter (``python twin.py``, ``Rscript twin.R``)
exists; the module of ``python -m module`` can be found with the PYTHONPATH the twin gets.
Each problem is one line naming ``twins.<name>.command``, before any job runs.

Fingerprint (:func:`command_fingerprint`, a param of the twin's shard jobs): SHA-256 over
the bytes of every file the command names that exists (its script, a model file passed as
an argument, the program itself when given as a path), of the module file of ``python -m
module``, and of every file under the paths listed in the spec's ``code:`` (files or
folders; hidden folders and compiled Python files skipped; a path holding the results
folder is refused at parse time, :func:`code_paths_error`). Editing any of them reruns
exactly that twin's shards and what follows; restoring
the same bytes (``git checkout``) reruns nothing, since only contents count, never times.
Not tracked: files the twin opens without naming them in its command or in ``code:``
(other modules of its package, its data, the libraries it imports), programs found on
PATH (their version is what the twin's hello reports, recorded with its runs), and the
paths of the spec's ``code_exclude:`` (files or folders).

Files the twin writes (a log or cache inside a ``code:`` folder, a file named on its
command line): the rules that run the twin compare the tracked files before and after
(:func:`watch_code`) and record the paths that changed in
``twins/<name>/code_written/<job>.json``; when the workflow next starts, such a path still
tracked stops it in one line naming the path and ``code_exclude``
(:func:`code_written_error`), instead of rerunning the twin at every start.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from twinfalsify.schema import ContractError

# interpreters whose first non-option argument is a script file
INTERPRETERS = ("python", "python3", "Rscript", "julia", "bash", "sh", "node", "ruby", "perl")
# options after which the interpreter runs no script file (code or a module instead)
NO_SCRIPT_OPTIONS = ("-c", "-m", "-e", "--eval", "-E")
SKIP_DIRS = {"__pycache__", ".git", ".snakemake", ".ipynb_checkpoints"}
SKIP_SUFFIXES = {".pyc", ".pyo"}
_CHUNK = 1 << 20


def words(spec: Mapping[str, Any]) -> list[str]:
    """The command as a list of words (a string is split as a shell would)."""
    command = spec.get("command")
    if isinstance(command, str):
        return shlex.split(command)
    return [str(w) for w in command or []]


def _is_python(program: str) -> bool:
    return re.fullmatch(r"python[0-9.]*", Path(program).name) is not None


def _interpreter(program: str) -> bool:
    name = Path(program).name
    return _is_python(program) or name in INTERPRETERS


def script_of(cmd: list[str]) -> str | None:
    """The script file an interpreter command names (first non-option argument), or None
    (not an interpreter, or ``-c`` / ``-m`` / ``-e``: code or a module, no script)."""
    if not cmd or not _interpreter(cmd[0]):
        return None
    for w in cmd[1:]:
        if w in NO_SCRIPT_OPTIONS or (_is_python(cmd[0]) and w[:2] in ("-c", "-m")):
            return None
        if not w.startswith("-"):
            return w
    return None


def module_of(cmd: list[str]) -> str | None:
    """The module of ``python -m module`` (``-mmodule`` too), or None."""
    if not cmd or not _is_python(cmd[0]):
        return None
    for k, w in enumerate(cmd[1:], start=1):
        if w == "-m":
            return cmd[k + 1] if k + 1 < len(cmd) else ""
        if w.startswith("-m") and len(w) > 2:
            return w[2:]
        if not w.startswith("-"):
            return None
    return None


def _twin_env(spec: Mapping[str, Any], src: Path | None) -> dict[str, str]:
    """The environment the twin gets (``runs.registry.make_twin``: plain ``python`` is the
    study's interpreter, with the library's src/ first on PYTHONPATH)."""
    env = {**os.environ, **{str(k): str(v) for k, v in (spec.get("env") or {}).items()}}
    cmd = words(spec)
    if src is not None and cmd and cmd[0] in ("python", "python3"):
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(src), env.get("PYTHONPATH")) if p)
    return env


def _program(cmd: list[str]) -> str:
    """The program that runs: plain ``python``/``python3`` is the study's interpreter."""
    return sys.executable if cmd[0] in ("python", "python3") else cmd[0]


def check_command(name: str, spec: Mapping[str, Any], src: Path | None = None) -> None:
    """Raise ContractError (``twins.<name>.command: ...``, one line) for a command that
    cannot start: blank, program not found or not executable, missing script, module of
    ``python -m`` not found. Relative paths are relative to the working directory (where
    the workflow runs the twin). ``src``: the library's src/ (on a python twin's path)."""
    key = f"twins.{name}.command"
    try:
        cmd = words(spec)
    except ValueError as exc:  # shlex: unbalanced quotes
        raise ContractError(f"{key}: cannot be split into words ({exc})") from None
    if not cmd or not "".join(cmd).strip() or not cmd[0].strip():
        raise ContractError(f"{key}: is blank; give the program and its arguments")
    shown = shlex.join(cmd)
    env = _twin_env(spec, src)
    program = _program(cmd)
    if os.sep in program or (os.altsep and os.altsep in program):
        if not Path(program).is_file():
            raise ContractError(f"{key}: program {program!r} does not exist (command: {shown})")
        if not os.access(program, os.X_OK):
            raise ContractError(f"{key}: program {program!r} is not executable "
                                f"(command: {shown})")
    elif shutil.which(program, path=env.get("PATH", os.defpath)) is None:
        raise ContractError(f"{key}: program {program!r} not found on PATH (command: {shown})")
    script = script_of(cmd)
    if script is not None and not Path(script).is_file():
        raise ContractError(f"{key}: script {script!r} does not exist (relative paths are "
                            f"relative to the working directory; command: {shown})")
    module = module_of(cmd)
    if module is not None:
        if not module:
            raise ContractError(f"{key}: '-m' names no module (command: {shown})")
        if not _module_found(program, module, env):
            raise ContractError(f"{key}: no module named {module!r} for {program!r} (with "
                                f"PYTHONPATH={env.get('PYTHONPATH', '')!r}; command: {shown})")
    for path in _code_paths(spec):
        if not Path(path).exists():
            raise ContractError(f"twins.{name}.code: {path!r} does not exist (relative paths "
                                "are relative to the working directory)")


_FIND = ("import importlib.util as u, sys\n"
         "try:\n    s = u.find_spec(sys.argv[1])\nexcept Exception:\n    s = None\n"
         "print(s.origin if s is not None and s.origin else '')\n"
         "sys.exit(0 if s is not None else 3)")


def _module_origin(program: str, module: str, env: Mapping[str, str]) -> str | None:
    """File of ``module`` as the twin's interpreter finds it ('' if not a file), None if
    not found (asked of that interpreter: it may not be this one)."""
    try:
        out = subprocess.run([program, "-c", _FIND, module], env=dict(env), capture_output=True,
                             text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _module_found(program: str, module: str, env: Mapping[str, str]) -> bool:
    return _module_origin(program, module, env) is not None


def _code_paths(spec: Mapping[str, Any]) -> list[str]:
    code = spec.get("code") or []
    return [code] if isinstance(code, str) else [str(c) for c in code]


def code_paths_error(name: str, spec: Mapping[str, Any], results: str | Path) -> str | None:
    """One line when a ``code:`` path of a command twin holds the results folder (or lies
    inside it), else None.

    What the study writes would then be part of the twin's fingerprint: every run would
    change it, and every start would rerun the twin.
    """
    if spec.get("kind") != "command":
        return None
    out = Path(results).resolve()
    for c in _code_paths(spec):
        here = Path(c).resolve()
        if out.is_relative_to(here) or here.is_relative_to(out):
            where = "holds" if out.is_relative_to(here) else "lies inside"
            return (f"twins.{name}.code: {c!r} {where} the results folder {results}: what the "
                    "study writes would change the twin's fingerprint and rerun it on every "
                    "start; list the twin's own files or folders instead")
    return None


def _files_under(path: Path) -> Iterable[Path]:
    if path.is_file():
        yield path
        return
    for root, dirs, files in os.walk(path):
        # hidden folders (.git, .snakemake, .venv, caches) are tools' state, not the twin
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.startswith("."))
        for f in sorted(files):
            p = Path(root) / f
            if p.suffix not in SKIP_SUFFIXES:
                yield p


def _excluded(spec: Mapping[str, Any]) -> list[Path]:
    raw = spec.get("code_exclude") or []
    return [Path(p).resolve() for p in ([raw] if isinstance(raw, str) else raw)]


def tracked_files(spec: Mapping[str, Any], src: Path | None = None) -> list[Path]:
    """The files :func:`command_fingerprint` reads, in a fixed order (without those under a
    ``code_exclude:`` path)."""
    cmd = words(spec)
    out: list[Path] = []
    for w in cmd:
        p = Path(w)
        if w and p.is_file():
            out.append(p)
    module = module_of(cmd) if cmd else None
    if module and not module.startswith("twinfalsify."):  # the library's own: its code param
        origin = _module_origin(_program(cmd), module, _twin_env(spec, src))
        if origin and Path(origin).is_file():
            out.append(Path(origin))
    for c in _code_paths(spec):
        if Path(c).exists():
            out.extend(_files_under(Path(c)))
    excluded = _excluded(spec)
    out = [p for p in out if not any(p.resolve().is_relative_to(x) for x in excluded)]
    seen: set[Path] = set()
    return [p for p in out if not (p.resolve() in seen or seen.add(p.resolve()))]


def command_fingerprint(spec: Mapping[str, Any], src: Path | None = None) -> str:
    """SHA-256 (16 hex digits) over the names and bytes of :func:`tracked_files`; '' for a
    twin that is not ``kind: command``. Contents only: a file rewritten with the same bytes
    (or restored by ``git checkout``) keeps its fingerprint."""
    if spec.get("kind") != "command":
        return ""
    h = hashlib.sha256()
    for p in tracked_files(spec, src):
        h.update(str(p).encode() + b"\0")
        with p.open("rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()[:16]


def _digests(spec: Mapping[str, Any], src: Path | None) -> dict[str, str]:
    """{path: SHA-256 of its bytes} of the tracked files, and '' for a path the command
    names that does not exist (a file the twin may create)."""
    out: dict[str, str] = {}
    for p in tracked_files(spec, src):
        h = hashlib.sha256()
        try:
            with p.open("rb") as fh:
                while chunk := fh.read(_CHUNK):
                    h.update(chunk)
        except OSError:
            continue
        out[str(p)] = h.hexdigest()
    excluded = _excluded(spec)
    for w in words(spec)[1:]:
        p = Path(w)
        if (w and w not in out and not w.startswith("-") and not p.exists()
                and not any(p.resolve().is_relative_to(x) for x in excluded)):
            out[w] = ""
    return out


@contextmanager
def watch_code(spec: Mapping[str, Any], src: Path | None, record: Path) -> Iterator[None]:
    """Around a job that runs the twin (``kind: command`` only): the tracked files the job
    changed, created or removed are written to ``record`` (JSON list of paths; nothing is
    written when none changed). Another job of the same twin may write at the same time:
    what a job sees is what changed while it ran."""
    if spec.get("kind") != "command":
        yield
        return
    before = _digests(spec, src)
    yield
    after = _digests(spec, src)
    changed = sorted(p for p in set(before) | set(after) if before.get(p) != after.get(p))
    if changed:
        record.parent.mkdir(parents=True, exist_ok=True)
        tmp = record.with_name(record.name + ".tmp")
        tmp.write_text(json.dumps(changed))
        tmp.replace(record)


def code_written_error(name: str, spec: Mapping[str, Any], twin_folder: str | Path,
                       src: Path | None = None) -> str | None:
    """One line when a path the twin wrote in an earlier job (``watch_code`` records under
    ``<twin_folder>/code_written/``) is still part of its fingerprint, else None: it would
    change the fingerprint at every start and rerun the twin."""
    if spec.get("kind") != "command":
        return None
    folder = Path(twin_folder) / "code_written"
    if not folder.is_dir():
        return None
    written: set[str] = set()
    for f in sorted(folder.glob("*.json")):
        try:
            written.update(str(p) for p in json.loads(f.read_text()))
        except (OSError, ValueError, TypeError):
            continue
    if not written:
        return None
    tracked = {p.resolve() for p in tracked_files(spec, src)}
    named = {w for w in words(spec)[1:] if w and not w.startswith("-")}
    excluded = _excluded(spec)
    still = sorted(p for p in written
                   if (Path(p).resolve() in tracked or p in named)
                   and not any(Path(p).resolve().is_relative_to(x) for x in excluded))
    if not still:
        return None
    return (f"twins.{name}: the twin wrote {still[0]!r} while it ran"
            + (f" (and {len(still) - 1} more)" if len(still) > 1 else "")
            + ", a file its code fingerprint reads (its command or code:): every start would "
            f"rerun it; add it (or its folder) to twins.{name}.code_exclude, or have the twin "
            "write outside its code")
