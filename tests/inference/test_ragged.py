"""Ragged groups: the vectorised grouping and selection against a plain loop over groups,
on the layouts that break index arithmetic (empty groups, repeated and reversed picks, ids
absent from the order, ids not sorted, an empty pick)."""

from __future__ import annotations

import numpy as np
import pytest

from twinfalsify.inference.samples import Ragged


def _groups(r: Ragged) -> list[list[float]]:
    return [r.group(h).tolist() for h in range(len(r))]


@pytest.mark.parametrize("seed", range(20))
def test_from_grouped_equals_a_loop(seed):
    rng = np.random.default_rng(seed)
    order = rng.permutation(rng.choice(1000, size=rng.integers(1, 30), replace=False))
    present = order[rng.random(len(order)) < 0.7]  # some groups stay empty
    ids = rng.choice(present, size=rng.integers(0, 200)) if len(present) else np.zeros(0, int)
    values = rng.integers(0, 5, size=len(ids)).astype(float)  # ties among values
    got = Ragged.from_grouped(ids, values, order)
    want = [[v for i, v in zip(ids, values, strict=True) if i == h] for h in order]
    assert _groups(got) == want


def test_from_grouped_names_an_id_missing_from_the_order():
    with pytest.raises(KeyError, match=r"\[7\]"):
        Ragged.from_grouped(np.array([3, 7, 3]), np.ones(3), np.array([5, 3]))
    with pytest.raises(KeyError, match=r"\[99\]"):  # beyond every id of the order
        Ragged.from_grouped(np.array([99]), np.ones(1), np.array([5, 3]))


@pytest.mark.parametrize("seed", range(20))
def test_take_equals_a_loop(seed):
    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, 4, size=rng.integers(1, 12))  # empty groups among them
    r = Ragged.from_groups([rng.integers(0, 3, size=k).astype(float) for k in sizes])
    pick = rng.integers(0, len(r), size=rng.integers(0, 15))  # repeats, any order, or none
    assert _groups(r.take(pick)) == [r.group(int(h)).tolist() for h in pick]
    assert r.take(pick).values.dtype == np.float64
