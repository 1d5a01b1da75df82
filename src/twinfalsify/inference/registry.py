"""Test methods by name, as the config's ``testing.methods`` names them."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from twinfalsify.inference.options import OptionError
from twinfalsify.inference.samples import HypothesisSamples
from twinfalsify.schema import ContractError

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]

# name -> (import path, options accepted, whether the method takes a seed)
METHODS: dict[str, tuple[str, tuple[str, ...], bool]] = {
    "hoeffding": ("twinfalsify.inference.hoeffding:hoeffding_test", ("factor",), False),
    "bootstrap": (
        "twinfalsify.inference.bootstrap:bootstrap_test",
        ("n_resamples", "min_n", "kind", "variant", "p_floor"),
        True,
    ),
    "betting": (
        "twinfalsify.inference.betting:betting_test",
        ("tune_alpha", "bets", "order", "grid", "grid_ratio", "orders", "running_max", "c",
         "tol", "max_iter"),
        True,
    ),
    "bernstein": ("twinfalsify.inference.bernstein:bernstein_test", (), False),
}


# methods whose tuning reads the family's level (``testing.alpha``)
LEVELLED = ("betting",)


def make(name: str, opts: dict[str, Any] | None, seed: int, alpha: float = 0.05) -> Method:
    """The method ``name`` with its options bound; unknown names/options, and values of the
    wrong type or out of range (the method module's ``check_options``), are config errors.
    ``alpha``: the family's level (``testing.alpha``), bound for the methods that tune to it
    (``LEVELLED``)."""
    if name not in METHODS:
        raise ContractError(
            f"testing.methods: unknown method {name!r}; choose from {', '.join(METHODS)}"
        )
    target, allowed, seeded = METHODS[name]
    opts = dict(opts or {})
    unknown = set(opts) - set(allowed)
    if unknown:
        raise ContractError(
            f"testing.methods.{name}: unknown option(s) {sorted(unknown)}; "
            f"allowed: {', '.join(allowed) or 'none'}"
        )
    module, func = target.split(":")
    mod = __import__(module, fromlist=[func])
    check = getattr(mod, "check_options", None)  # the method's own types and ranges
    if check is not None:
        try:
            check(opts)
        except OptionError as e:
            raise ContractError(f"testing.methods.{name}.{e}") from None
        except (TypeError, ValueError) as e:  # options that only make sense together
            raise ContractError(f"testing.methods.{name}: {e}") from None
    fn = getattr(mod, func)
    if seeded:
        opts["seed"] = int(seed)
    if name in LEVELLED:
        opts["alpha"] = float(alpha)
    return partial(fn, **opts)


def floored(name: str, method: Method, p: np.ndarray) -> np.ndarray:
    """(len(p),) bool: p is a reporting floor, not a measurement (bootstrap: every resample
    separated, ``inference.bootstrap.at_floor``); False for the other methods."""
    if name != "bootstrap":
        return np.zeros(len(p), dtype=bool)
    from twinfalsify.inference.bootstrap import P_FLOOR, at_floor

    floor = method.keywords.get("p_floor", P_FLOOR) if isinstance(method, partial) else P_FLOOR
    return at_floor(p, floor)


def refused(name: str, method: Method, n: np.ndarray, nhat: np.ndarray) -> np.ndarray:
    """(H,) bool: the method does not test these hypotheses, its p = 1 is by rule, not by
    evidence: n = 0 or nhat = 0 for every method; for the bootstrap also n or nhat below
    its ``min_n`` (``inference.bootstrap.bootstrap_test``)."""
    n, nhat = np.asarray(n), np.asarray(nhat)
    out = (n == 0) | (nhat == 0)
    if name != "bootstrap":
        return out
    import inspect

    from twinfalsify.inference.bootstrap import bootstrap_test

    default = inspect.signature(bootstrap_test).parameters["min_n"].default
    min_n = method.keywords.get("min_n", default) if isinstance(method, partial) else default
    min_n = max(int(min_n), 1)
    return out | (n < min_n) | (nhat < min_n)
