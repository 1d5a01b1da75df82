"""Small I/O helpers for the rule scripts: atomic writes, logs, one-line errors, and the end
of a job's process."""

from __future__ import annotations

import errno
import gc
import glob
import json
import logging
import math
import os
import re
import shutil
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.schema import ContractError

log = logging.getLogger("twinfalsify")


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


# errors that mean "no room": a full disk, a file size limit (ulimit -f), a disk quota
_NO_ROOM = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}


def _no_room(exc: BaseException) -> str | None:
    """The reason, when ``exc`` says the disk (or a size limit) has no room, else None.

    pyarrow raises OSError without an errno, only the C library's text, so that is
    matched too."""
    if isinstance(exc, OSError) and exc.errno in _NO_ROOM:
        return os.strerror(exc.errno)
    text = str(exc)
    return next((os.strerror(code) for code in sorted(_NO_ROOM)
                 if os.strerror(code) in text), None)


def _size(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


def _remove_stale_tmps(path: Path) -> None:
    """Remove hidden temporary files of ``path`` left by writers that no longer run (a job
    killed with -9 cannot clean up after itself)."""
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.tmp")
    for old in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        m = pattern.fullmatch(old.name)
        if m is None:
            continue
        pid = int(m.group(1))
        if pid != os.getpid():
            try:
                os.kill(pid, 0)
                continue  # its writer still runs
            except ProcessLookupError:
                pass
            except PermissionError:
                continue  # another user's process
        old.unlink(missing_ok=True)


def write_atomic(path: str | Path, write: Callable[[Path], object]) -> None:
    """Write ``path`` atomically: ``write(tmp)`` fills a hidden temporary file next to it,
    which then replaces ``path``, so a killed job leaves no half file.

    The temporary file is removed on any failure; a full disk (or ``ulimit -f``) is one
    ContractError naming the file and the free space of its folder. After a successful
    write, temporary files of earlier writers of ``path`` that are gone are removed too.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    try:
        write(tmp)
        tmp.replace(path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        reason = _no_room(exc) if isinstance(exc, Exception) else None
        if reason is None:
            raise
        try:
            free = f"{_size(shutil.disk_usage(path.parent).free)} free in {path.parent}"
        except OSError:
            free = f"free space of {path.parent} unknown"
        raise ContractError(f"{path}: cannot write: {reason} ({free})") from None
    _remove_stale_tmps(path)


def write_parquet(df: pd.DataFrame, path: str | Path) -> None:
    """Write atomically (temp file + rename) so a killed job leaves no half file."""
    write_atomic(path, lambda tmp: df.to_parquet(tmp, index=False))


def write_csv(df: pd.DataFrame, path: str | Path, **kwargs: Any) -> None:
    write_atomic(path, lambda tmp: df.to_csv(tmp, index=False, **kwargs))


def write_text(text: str, path: str | Path) -> None:
    write_atomic(path, lambda tmp: tmp.write_text(text))


def write_json(data: Any, path: str | Path) -> None:
    write_text(json.dumps(data, indent=1, sort_keys=True) + "\n", path)


def read_json(path: str | Path) -> Any:
    return json.loads(Path(path).read_text())


def read_parquet(path: str | Path, what: str = "table") -> pd.DataFrame:
    """A file the workflow wrote, read; a missing or damaged one is one line naming it.

    A damaged file (truncated by a full disk or a kill outside Snakemake's watch) looks
    finished to Snakemake, so every start that needs it would fail on it: the line says to
    delete it, after which the same command reruns the rule that writes it.
    """
    path = Path(path)
    if not path.exists():
        raise ContractError(f"{path}: {what} not found")
    try:
        return pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        detail = " ".join(str(exc).split())[:200]
        raise ContractError(
            f"{path}: cannot read {what} as Parquet, the file is damaged or truncated "
            f"({detail}); delete it and run the same command again: the rule that writes it "
            "reruns"
        ) from None


def freeze_heap() -> None:
    """Leave every object alive now out of the garbage collector's later passes
    (:func:`gc.freeze`), the one at interpreter exit included.

    For objects that live as long as their process: a rule script's, once its work is done;
    the parsed workflow's; a served twin's, once built. Python's last collection at exit would
    otherwise walk the whole heap of pandas, matplotlib and numba, a fixed cost of every
    job's process (``benchmarks/bench_process_exit.py``). Objects stay reference-counted:
    only cycles among them are no longer collected, and files and logs are closed as before
    (by ``with`` blocks, and by ``logging``'s exit hook).
    """
    gc.freeze()


def run_rule(snakemake: Any, main: Callable[[Any], None]) -> None:
    """Run a rule script body with logging to the rule's log and one-line data errors.

    A ContractError (bad input, bad config) ends the job with its message as
    the last line of the log and of stderr, not with a traceback. Whatever the end, the
    heap is frozen (:func:`freeze_heap`): the process exits without walking it.
    """
    log_path = snakemake.log[0] if len(snakemake.log) else None
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(log_path, mode="w"))
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(message)s", handlers=handlers, force=True
    )
    try:
        main(snakemake)
    except ContractError as exc:
        log.error("ERROR: %s", exc)
        sys.exit(1)
    except Exception as exc:
        what = _file_error(exc) if isinstance(exc, OSError) else None
        if what:
            log.error("ERROR: %s", what)
        else:  # a bug: keep the traceback
            log.error("ERROR: unexpected failure in rule %s:\n%s", snakemake.rule,
                      traceback.format_exc())
        sys.exit(1)
    finally:
        freeze_heap()


def job_errors(*snakemake_logs: str | Path) -> list[str]:
    """The one-line errors of the jobs a Snakemake run saw fail, in the order they failed.

    Snakemake's log names each failed job's logs ("Error in rule R:" ... "log: a.log, b.log
    (check log file(s) ...)"); the last "ERROR: " line ``run_rule`` wrote to each is its
    error. Printed at the very end of a failed run (the Snakefile's ``onerror``), the error
    is the run's last line instead of one in the middle of Snakemake's closing lines. A job
    whose log holds no such line (killed, out of memory) adds nothing. Never raises.
    """
    out: list[str] = []
    lines: list[str] = []
    for path in snakemake_logs:
        try:
            lines += Path(path).read_text(errors="replace").splitlines()
        except (OSError, TypeError):
            continue
    rule = None
    for line in lines:
        if line.startswith("Error in rule "):
            rule = line.removeprefix("Error in rule ").rstrip(":")
        elif rule and line.strip().startswith("log: "):
            paths = line.strip().removeprefix("log: ").split(" (check log")[0]
            for path in paths.split(", "):
                try:
                    errs = [ln for ln in Path(path).read_text(errors="replace").splitlines()
                            if "ERROR: " in ln]
                except OSError:
                    continue
                if errs:
                    msg = "ERROR: " + errs[-1].split("ERROR: ", 1)[1]
                    if msg not in out:
                        out.append(msg)
            rule = None
    return out


def _file_error(exc: OSError) -> str | None:
    """One line for an OSError about a file (read-only or full results folder, a file where
    a folder should be, a missing input), or None when it names no file (then it is a bug)."""
    return None if exc.filename is None else f"{exc.filename}: {exc.strerror or exc}"


def cli_main(main: Callable[[], int | None], prog: str) -> int:
    """Run a command-line entry point; bad input ends in one line on stderr, exit code 2.

    Bad input here: a ContractError (bad data, config or context), a file that cannot be
    read or written, an engine module that cannot be imported. Anything else is a bug and
    keeps its traceback. For a program's ``__main__`` only: whatever the end, the heap is
    frozen (:func:`freeze_heap`), as the process exits next.
    """
    try:
        return int(main() or 0)
    except ContractError as exc:
        what = str(exc)
    except ImportError as exc:
        what = f"cannot import {exc.name or ''}: {exc}".replace(":  ", ": ")
    except OSError as exc:
        what = _file_error(exc)
        if what is None:
            raise
    finally:
        freeze_heap()
    print(f"{prog}: error: {what}", file=sys.stderr, flush=True)
    return 2


def unwritable(folder: str | Path) -> str | None:
    """Why results cannot be written under ``folder`` (one line), or None.

    The folder may not exist yet: its nearest existing ancestor must be a writable folder.
    Checked when the workflow is parsed, so a read-only results folder stops the run before
    the first rule rather than as an error after it computed.
    """
    here = Path(folder).absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        return f"cannot write results under {folder}: {here} is a file, not a folder"
    if not os.access(here, os.W_OK | os.X_OK):
        return (f"cannot write results under {folder}: {here} is not writable "
                "(run from a writable copy of the study folder)")
    return None


def config_error(config: dict, schema_path: str | Path) -> str | None:
    """The first violation of the config schema as one line naming the key, or None.

    Snakemake's own ``validate`` prints the whole schema after the message; a person needs
    the dotted key path, the offending value and the rule, e.g.
    ``config key twin_runs.n_shards: 'four' is not of type 'integer'``.
    """
    import jsonschema
    import yaml

    # JSON Schema's "number" admits NaN and infinity (YAML .nan, .inf), and every range
    # check passes or fails silently on them: alpha .nan rejected every hypothesis.
    bad = _non_finite(config)
    if bad is not None:
        key, value = bad
        return f"config key {key}: {value} is not a finite number"
    schema = yaml.load(Path(schema_path).read_text(), Loader=_safe_loader())  # noqa: S506
    base = jsonschema.validators.validator_for(schema)
    # JSON Schema's "integer" admits 7.0; Snakemake would then compare the params 7.0 and
    # 7 as different and rerun a finished study: an integer key takes an integer only
    strict = base.TYPE_CHECKER.redefine(
        "integer", lambda _, v: isinstance(v, int) and not isinstance(v, bool))
    validator = jsonschema.validators.extend(base, type_checker=strict)(schema)
    error = jsonschema.exceptions.best_match(validator.iter_errors(config))
    if error is None:
        return None
    key = ".".join(str(p) for p in error.absolute_path) or "(top level)"
    return f"config key {key}: {error.message}"


def _non_finite(node: Any, path: str = "") -> tuple[str, float] | None:
    """(dotted key, value) of the first NaN or infinite float in a config tree, or None."""
    if isinstance(node, float) and not math.isfinite(node):
        return path or "(top level)", node
    items = node.items() if isinstance(node, dict) else (
        enumerate(node) if isinstance(node, list) else ())
    for k, v in items:
        found = _non_finite(v, f"{path}.{k}" if path else str(k))
        if found:
            return found
    return None


def _safe_loader() -> type:
    """PyYAML's safe loader, its C parser when libyaml is there (a tenth of the time)."""
    import yaml

    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_yaml_strict(path: str | Path) -> Any:
    """Load a YAML file, refusing a key written twice in one mapping.

    PyYAML keeps the last value silently; a study config with ``alpha`` twice would then
    run with whichever came last. ContractError names the file, the key and both lines.
    Merge keys (``<<: *anchor``) are allowed: a key of the merged mapping that the mapping
    itself sets again is an override, as YAML defines it, not a duplicate.
    """
    import yaml

    class Strict(_safe_loader()):  # type: ignore[misc,valid-type]
        pass

    def mapping(loader: Strict, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                # ``<<: *anchor``: its keys are defaults the mapping's own keys may
                # override (YAML's merge rule), not duplicates; PyYAML merges them below
                continue
            key = loader.construct_object(key_node, deep=deep)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise ContractError(
                    f"{path}: key {key!r} is written twice (lines {seen[key]} and {line}); "
                    "YAML would keep only the last"
                )
            seen[key] = line
        return loader.construct_mapping(node, deep=deep)

    Strict.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    try:
        return yaml.load(Path(path).read_text(), Loader=Strict)  # noqa: S506 - SafeLoader
    except yaml.YAMLError as exc:
        raise ContractError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
