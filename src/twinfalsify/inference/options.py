"""Type and range checks for a test method's options, with the accepted range in the message.

Each method module states its own options in one function, ``check_options(opts)``, built
from these checks; ``inference.registry.make`` calls it whenever a method is bound, so the
config check at parse time (``studyconfig``) and a run use the same rules. A bool is not a
number here (YAML ``yes`` must not become 1), nor is a numeric string ("2").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any


class OptionError(ValueError):
    """One option's value is unusable; ``key`` names the option."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key


def _shown(value: Any) -> str:
    return f"{value!r} (a {type(value).__name__})" if isinstance(value, str | bool) \
        else repr(value)


def number(opts: Mapping[str, Any], key: str, *, lo: float | None = None,
           hi: float | None = None, lo_open: bool = False, hi_open: bool = False,
           allow_none: bool = False, note: str = "") -> None:
    """``opts[key]``, if given, is a finite real number within the stated bounds."""
    if key not in opts or (allow_none and opts[key] is None):
        return
    value = opts[key]
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    want = "a number" + (f" {' and '.join(parts)}" if parts else "") + (
        " or null" if allow_none else "") + (f" ({note})" if note else "")
    ok = isinstance(value, int | float) and not isinstance(value, bool) \
        and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if not ok:
        raise OptionError(key, f"{_shown(value)} is not allowed: must be {want}")


def integer(opts: Mapping[str, Any], key: str, *, lo: int, allow_none: bool = False,
            note: str = "") -> None:
    """``opts[key]``, if given, is an integer >= ``lo`` (1.0 is not an integer here)."""
    if key not in opts or (allow_none and opts[key] is None):
        return
    value = opts[key]
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= lo):
        want = f"an integer >= {lo}" + (" or null" if allow_none else "") + (
            f" ({note})" if note else "")
        raise OptionError(key, f"{_shown(value)} is not allowed: must be {want}")


def choice(opts: Mapping[str, Any], key: str, choices: Sequence[str]) -> None:
    """``opts[key]``, if given, is one of ``choices``."""
    if key in opts and opts[key] not in choices:
        raise OptionError(key, f"{_shown(opts[key])} is not allowed: must be one of "
                               f"{', '.join(choices)}")


def boolean(opts: Mapping[str, Any], key: str, *, allow_none: bool = False) -> None:
    """``opts[key]``, if given, is true or false (or null when allowed)."""
    if key not in opts or (allow_none and opts[key] is None):
        return
    if not isinstance(opts[key], bool):
        raise OptionError(key, f"{_shown(opts[key])} is not allowed: must be true or false"
                               + (" or null" if allow_none else ""))
