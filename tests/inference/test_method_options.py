"""Every option of every test method is checked for type and range when the method is bound
(``inference.registry.make``: at parse time for a study, by the method's own code)."""

from __future__ import annotations

import pytest

from twinfalsify.inference import registry
from twinfalsify.schema import ContractError

CHOICES = {"kind", "variant", "bets"}  # options whose values are names


@pytest.mark.parametrize(("name", "key"), [(n, k) for n, (_, keys, _) in
                                           registry.METHODS.items() for k in keys])
def test_every_option_refuses_a_value_of_the_wrong_type(name, key):
    wrong = 7 if key in CHOICES else "7"  # a number as a string: must never slip through
    with pytest.raises(ContractError) as err:
        registry.make(name, {key: wrong}, seed=0)
    msg = str(err.value)
    assert msg.startswith(f"testing.methods.{name}.{key}: ") and "must be" in msg, msg
    assert "\n" not in msg


@pytest.mark.parametrize(("name", "opts"), [
    ("hoeffding", {"factor": 2}), ("hoeffding", {"factor": 4.0}),
    ("bootstrap", {"n_resamples": 50, "min_n": 1, "kind": "percentile", "p_floor": 1e-9}),
    ("betting", {"bets": "plugin", "orders": 1, "running_max": True, "c": 0.5, "tol": 1e-4,
                 "max_iter": 5, "tune_alpha": None}),
    ("betting", {"grid": 1, "grid_ratio": 1.5, "tune_alpha": 0.01}),
    ("bernstein", {}),
])
def test_values_at_the_edge_of_their_range_are_accepted(name, opts):
    registry.make(name, opts, seed=0)


@pytest.mark.parametrize(("name", "key", "bad", "good"), [
    ("hoeffding", "factor", 1.999, 2.0), ("bootstrap", "n_resamples", 49, 50),
    ("bootstrap", "min_n", 0, 1), ("betting", "grid", 0, 1), ("betting", "max_iter", 0, 1),
])
def test_range_boundaries(name, key, bad, good):
    with pytest.raises(ContractError, match=f"{key}: {bad!r} is not allowed"):
        registry.make(name, {key: bad}, seed=0)
    registry.make(name, {key: good}, seed=0)
