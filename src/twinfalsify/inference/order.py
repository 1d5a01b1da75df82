"""The data order of the betting test: a keyed hash of each sample's own content.

The betting interval (``inference.betting``) depends on the order of its sample; its validity
needs only that the order be a uniformly random permutation independent of the values. An
order taken from the stay numbering is not: ids assigned by a sorted extract or by admission
date under a drifting case mix carry information on the outcome, and the level is lost
(docs/explanation/statistics.md, measured). Here each trajectory's sort key is

    key_t(i) = blake2b(X_0:t(i), A_1:t(i); key = study seed)       (64 bits)

over its canonicalised bytes (float64, every NaN the same bytes, -0.0 as 0.0), for the hour
t of the hypothesis (never a value charted after t). The twin's X_0 are selected and listed by
key_0 of their X_0 (``runs.plan``), the same construction.

Why it is valid. Treat blake2b keyed with a seed chosen without looking at the data (it is
recorded in the config) as a random function: distinct contents get i.i.d. uniform keys,
independent of the contents. Sorting by them is then a uniformly random permutation of the
distinct contents, independent of the data, so a sample that is i.i.d. stays i.i.d. in that
order (and exchangeable sequences stay exchangeable): WSR's argument for a fixed order
applies.

Identical contents. Records with identical contents would get identical keys and sit next to
each other, so with few distinct contents (integer-charted vitals, rounded exports, binary
outcomes, duplicated rows) the sample would be sorted into blocks of equal values and the
running maximum of the capital would lose its level. Each record is therefore keyed on its
content *and* its copy index j among the records of identical content:

    key_t(i) = blake2b(key_t(content) || j; key = study seed)    for j >= 1 (j = 0: unchanged)

Distinct (content, j) pairs get i.i.d. uniform keys, so the order is a uniformly random
permutation of the records, ties included. Which of two identical records gets which copy
index cannot change anything: their values, entries and outcomes are identical (functions of
X_0:t, A_1:t), so no stay id or row order enters. Data without ties keep their keys
(j = 0) bit for bit. The key must hold the covariates and actions, not the outcome alone: a
hash of a Bernoulli outcome has two values, and sorting by it would sort the sample.

Assumption stated: the seed is not chosen after seeing the results (a recorded seed,
like any pre-registered randomisation). No stay id enters, so renumbering the stays or
reordering the rows of the input cannot change a key, an order or a decision.
"""

from __future__ import annotations

import hashlib

import numpy as np

_PERSON = b"twinfalsify-ord"  # blake2b personalisation: this use only
_PERSON_COPY = b"twinfalsify-cpy"  # ... and for the copy index of identical contents
_PERSON_HYP = b"twinfalsify-hyp"  # ... and for the hypotheses' keys under an order seed


def _canonical(a: np.ndarray) -> np.ndarray:
    """float64 copy with one NaN bit pattern and -0.0 as 0.0 (equal values, equal bytes)."""
    a = np.array(a, dtype=np.float64, copy=True)
    a[np.isnan(a)] = np.nan
    a[a == 0] = 0.0
    return np.ascontiguousarray(a)


def _key_bytes(seed: int) -> bytes:
    return int(seed).to_bytes(16, "little", signed=True)


def content_keys(x: np.ndarray, actions: np.ndarray, seed: int,
                 copies: bool = True) -> np.ndarray:
    """(n, T+1) uint64: column t keys each trajectory by its X_0:t and A_1:t (module doc).

    ``x``: (n, T+1, F) features; ``actions``: (n, T) action codes; ``seed``: the study seed.
    Column 0 equals :func:`x0_keys` of the X_0 rows. ``copies`` False: identical contents
    keep identical keys (to count ties, :func:`tied_share`).
    """
    x = _canonical(x)
    a = np.ascontiguousarray(np.asarray(actions, dtype=np.int64))
    n, width = x.shape[0], x.shape[1]
    out = np.empty((n, width), dtype=np.uint64)
    key = _key_bytes(seed)
    for i in range(n):
        h = hashlib.blake2b(key=key, digest_size=8, person=_PERSON)
        h.update(x[i, 0].tobytes())
        out[i, 0] = int.from_bytes(h.copy().digest(), "little")
        for t in range(1, width):  # X_0:t and A_1:t, incrementally (never later hours)
            h.update(a[i, t - 1].tobytes())
            h.update(x[i, t].tobytes())
            out[i, t] = int.from_bytes(h.copy().digest(), "little")
    if copies:
        for t in range(width):
            out[:, t] = break_ties(out[:, t], seed)
    return out


def hypothesis_keys(h: int, order_seed: int | None) -> np.ndarray | None:
    """(h,) int64 keys of the hypotheses' final permutations under an order seed (None: the
    default keys 0..h-1). A keyed hash of (order seed, hypothesis row): another value-free
    permutation of every hypothesis' data order, so each order seed is another valid
    randomisation (``testing.order_seed``)."""
    if order_seed is None:
        return None
    key = _key_bytes(order_seed)
    return np.array([int.from_bytes(hashlib.blake2b(int(i).to_bytes(8, "little"), key=key,
                                                    digest_size=8, person=_PERSON_HYP).digest(),
                                    "little") >> 1 for i in range(h)], dtype=np.int64)


def break_ties(keys: np.ndarray, seed: int) -> np.ndarray:
    """Keys of records with identical content made distinct by their copy index (module
    doc): the j-th copy (j >= 1, in any order: the copies are identical) gets
    blake2b(key || j) under the seed; a key without copies is returned unchanged."""
    keys = np.asarray(keys, dtype=np.uint64)
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    start = np.r_[True, sk[1:] != sk[:-1]]
    first = np.maximum.accumulate(np.where(start, np.arange(len(sk)), 0))
    j = np.arange(len(sk)) - first
    if not (j > 0).any():
        return keys
    out = keys.copy()
    key = _key_bytes(seed)
    for i in np.flatnonzero(j > 0):
        h = hashlib.blake2b(int(sk[i]).to_bytes(8, "little") + int(j[i]).to_bytes(8, "little"),
                            key=key, digest_size=8, person=_PERSON_COPY)
        out[order[i]] = int.from_bytes(h.digest(), "little")
    return out


def tied_share(keys: np.ndarray) -> float:
    """Share of records whose content key another record shares (before :func:`break_ties`)."""
    keys = np.asarray(keys, dtype=np.uint64)
    if len(keys) == 0:
        return 0.0
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    return float((counts[inverse] > 1).mean())


def x0_keys(x0: np.ndarray, seed: int) -> np.ndarray:
    """(m,) uint64: each X_0 row (``(m, F)`` features) keyed as :func:`content_keys` column 0."""
    return break_ties(x0_content_keys(x0, seed), seed)


def x0_content_keys(x0: np.ndarray, seed: int) -> np.ndarray:
    """(m,) uint64: the content key of each X_0 row, identical rows tied (no copy index)."""
    x0 = _canonical(np.atleast_2d(x0))
    key = _key_bytes(seed)
    return np.array([int.from_bytes(hashlib.blake2b(row.tobytes(), key=key, digest_size=8,
                                                    person=_PERSON).digest(), "little")
                     for row in x0], dtype=np.uint64)
