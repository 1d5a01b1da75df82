"""Per-hypothesis samples of both sides of a test, vectorised over hypotheses."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Ragged:
    """H variable-length groups stored flat: group h is values[offsets[h]:offsets[h+1]]."""

    values: np.ndarray  # float64 (total,)
    offsets: np.ndarray  # int64 (H + 1,), offsets[0] == 0, non-decreasing

    @classmethod
    def from_groups(cls, groups: list[np.ndarray]) -> Ragged:
        sizes = np.array([len(g) for g in groups], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        values = (
            np.concatenate([np.asarray(g, dtype=np.float64) for g in groups])
            if len(groups) and offsets[-1]
            else np.zeros(0)
        )
        return cls(values=values, offsets=offsets)

    @classmethod
    def from_grouped(cls, ids: np.ndarray, values: np.ndarray, order: np.ndarray) -> Ragged:
        """Long (id, value) pairs -> one group per id in ``order`` (ids absent -> empty)."""
        ids, values, order = np.asarray(ids), np.asarray(values, float), np.asarray(order)
        by_id = np.argsort(order, kind="stable")
        at = np.searchsorted(order[by_id], ids)
        found = at < len(order)
        found[found] = order[by_id[at[found]]] == ids[found]
        if not found.all():
            raise KeyError(f"ids not in order: {np.unique(ids[~found])[:5].tolist()}")
        gi = by_id[at].astype(np.int64)
        sort = np.argsort(gi, kind="stable")
        sizes = np.bincount(gi, minlength=len(order))
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        return cls(values=values[sort], offsets=offsets)

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.offsets)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def group(self, h: int) -> np.ndarray:
        return self.values[self.offsets[h] : self.offsets[h + 1]]

    def sums(self) -> np.ndarray:
        """Per-group sums (0 for empty groups)."""
        csum = np.concatenate([[0.0], np.cumsum(self.values)])
        return csum[self.offsets[1:]] - csum[self.offsets[:-1]]

    def group_ids(self) -> np.ndarray:
        """Group index of every value."""
        return np.repeat(np.arange(len(self)), self.sizes)

    def take(self, index: np.ndarray) -> Ragged:
        """The groups listed in ``index``, in that order."""
        index = np.asarray(index, dtype=np.int64)
        sizes = self.sizes[index]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        # every element of the listed groups, group after group
        src = np.repeat(self.offsets[index] - offsets[:-1], sizes) + np.arange(offsets[-1])
        return Ragged(values=self.values[src].astype(np.float64, copy=False), offsets=offsets)


@dataclass(frozen=True)
class HypothesisSamples:
    """Everything a test needs about H hypotheses, paper notation.

    Observational side (test set D): ``n`` trajectories enter (X_0:N in B_0:N);
    of those, the followers (N = t, i.e. A_1:t = a_1:t) have their raw outcome
    X_t[k] in ``follow``; f = clip(., y_lo, y_up) is applied by the methods (so
    a sensitivity sweep can widen [y_lo, y_up] without losing information).
    Each of the n - n_follow others contributes y_lo to the Y_lo sample and
    y_up to the Y_up sample. Twin side: raw outcomes of the ``nhat`` runs that
    enter, in ``twin``.
    """

    y_lo: np.ndarray  # (H,)
    y_up: np.ndarray  # (H,)
    n: np.ndarray  # (H,) int64
    follow: Ragged  # (H groups) clipped outcomes of followers
    twin: Ragged  # (H groups) clipped twin outcomes
    # (H,) identity of each hypothesis for order-dependent methods (betting): a hypothesis
    # keeps its seeded sample order whatever other hypotheses are tested with it (subsets,
    # failed-run completions). None: 0..H-1.
    keys: np.ndarray | None = None
    # (H groups, aligned with ``follow``) each follower's position among its hypothesis'
    # n entering trajectories in the content-keyed data order (``bounds.observational_side``):
    # where the betting test's data order puts it. None: unknown (followers are then taken as listed
    # first; the data order is then only a fixed pseudo-random one, betting module doc).
    follow_pos: Ragged | None = None
    # Failed twin runs at their places (``inference.failures``, ``bounds.twin_runs``):
    # ``twin_run`` (aligned with ``twin``) is each entering run's index in the plan's run
    # order, ``failed_run`` the plan indices of the failed runs that could have entered. The
    # betting test then puts the worst case of each failed run at its own place in the data
    # order. None: unknown (failed runs are then only counted, ``n_failed``).
    twin_run: Ragged | None = None
    failed_run: Ragged | None = None

    def __post_init__(self) -> None:
        h = len(self.y_lo)
        if not (len(self.y_up) == len(self.n) == len(self.follow) == len(self.twin) == h):
            raise ValueError("HypothesisSamples: all parts must describe the same H hypotheses")
        if self.keys is not None and len(self.keys) != h:
            raise ValueError("HypothesisSamples: keys must have one entry per hypothesis")
        if np.any(self.follow.sizes > self.n):
            raise ValueError("HypothesisSamples: more followers than entering trajectories")
        if self.follow_pos is not None:
            fp = self.follow_pos
            if not np.array_equal(fp.sizes, self.follow.sizes) or np.any(
                    (fp.values < 0) | (fp.values >= np.repeat(self.n, fp.sizes))):
                raise ValueError("HypothesisSamples: follow_pos must give every follower a "
                                 "position in 0..n-1 of its hypothesis")
        if (self.twin_run is None) != (self.failed_run is None):
            raise ValueError("HypothesisSamples: twin_run and failed_run go together")
        if self.twin_run is not None and (
                not np.array_equal(self.twin_run.sizes, self.twin.sizes)
                or len(self.failed_run) != h):
            raise ValueError("HypothesisSamples: twin_run must give every twin outcome its run "
                             "and failed_run one group per hypothesis")

    def __len__(self) -> int:
        return len(self.y_lo)

    @property
    def hyp_keys(self) -> np.ndarray:
        """``keys`` as int64, defaulting to 0..H-1."""
        if self.keys is None:
            return np.arange(len(self), dtype=np.int64)
        return np.asarray(self.keys, dtype=np.int64)

    @property
    def has_failed_places(self) -> bool:
        """True when some failed run has a known place (``failed_run``)."""
        return self.failed_run is not None and self.failed_run.offsets[-1] > 0

    def without_failed(self) -> HypothesisSamples:
        """The same samples without the failed runs' places (what ``drop`` tests)."""
        if self.failed_run is None:
            return self
        return replace(self, twin_run=None, failed_run=None)

    @property
    def n_follow(self) -> np.ndarray:
        return self.follow.sizes

    @property
    def nhat(self) -> np.ndarray:
        return self.twin.sizes

    @property
    def width(self) -> np.ndarray:
        """R = y_up - y_lo."""
        return self.y_up - self.y_lo

    def _mean(self, total: np.ndarray, count: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, total / np.maximum(count, 1), np.nan)

    def clip(self, ragged: Ragged) -> Ragged:
        """f = clip(value, y_lo, y_up) of each value's own hypothesis."""
        gid = ragged.group_ids()
        return Ragged(np.clip(ragged.values, self.y_lo[gid], self.y_up[gid]), ragged.offsets)

    @cached_property
    def follow_f(self) -> Ragged:
        """Followers' f(X_0:t) = clipped outcomes."""
        return self.clip(self.follow)

    @cached_property
    def twin_f(self) -> Ragged:
        """Twin runs' f(X_0, Xtwin_1:t) = clipped outcomes."""
        return self.clip(self.twin)

    @cached_property
    def q_lo_hat(self) -> np.ndarray:
        """Qhat_lo = mean of Y_lo over entering trajectories (NaN when n = 0)."""
        return self._mean(self.follow_f.sums() + (self.n - self.n_follow) * self.y_lo, self.n)

    @cached_property
    def q_up_hat(self) -> np.ndarray:
        """Qhat_up = mean of Y_up over entering trajectories (NaN when n = 0)."""
        return self._mean(self.follow_f.sums() + (self.n - self.n_follow) * self.y_up, self.n)

    @cached_property
    def q_twin_hat(self) -> np.ndarray:
        """Qhat_twin = mean of f over entering twin runs (NaN when nhat = 0)."""
        return self._mean(self.twin_f.sums(), self.nhat)

    @cached_property
    def propensity(self) -> np.ndarray:
        """P(A_1:t = a_1:t | X_0:N in B_0:N) estimate = n_follow / n = 1 - width ratio."""
        return self._mean(self.n_follow.astype(float), self.n)

    @cached_property
    def q_obs_hat(self) -> np.ndarray:
        """Naive observational mean of f given A = a, X in B (followers only); not a bound."""
        return self._mean(self.follow_f.sums(), self.n_follow)

    def obs_side(self, side: str) -> Ragged:
        """The full observational Y_lo (side='lo') or Y_up sample, materialised (clipped)."""
        fill = self.y_lo if side == "lo" else self.y_up
        follow = self.follow_f
        groups = [
            np.concatenate([follow.group(h), np.full(self.n[h] - self.n_follow[h], fill[h])])
            for h in range(len(self))
        ]
        return Ragged.from_groups(groups)

    def with_bounds(self, y_lo: np.ndarray, y_up: np.ndarray) -> HypothesisSamples:
        """Same samples, other [y_lo, y_up] (e.g. the sensitivity sweep's widened range)."""
        return replace(self, y_lo=np.asarray(y_lo, float), y_up=np.asarray(y_up, float))

    def per_hypothesis(self, arrays: Callable[[np.ndarray], np.ndarray],
                       ragged: Callable[[Ragged], Ragged]) -> HypothesisSamples:
        """The samples with every per-hypothesis field mapped: ``arrays`` on y_lo, y_up, n
        and the keys, ``ragged`` on every ragged field (a selection, a tiling, ...)."""
        def opt(r: Ragged | None) -> Ragged | None:
            return None if r is None else ragged(r)

        return HypothesisSamples(
            y_lo=arrays(self.y_lo), y_up=arrays(self.y_up), n=arrays(self.n),
            follow=ragged(self.follow), twin=ragged(self.twin), keys=arrays(self.hyp_keys),
            follow_pos=opt(self.follow_pos), twin_run=opt(self.twin_run),
            failed_run=opt(self.failed_run),
        )

    def take(self, index: np.ndarray) -> HypothesisSamples:
        index = np.asarray(index, dtype=np.int64)
        return self.per_hypothesis(lambda a: a[index], lambda r: r.take(index))

    def tile(self, k: int) -> HypothesisSamples:
        """K copies of every hypothesis, copy-major, each keeping its hypothesis' key (so an
        order-dependent method orders every copy as the original)."""
        def tile_r(r: Ragged) -> Ragged:
            sizes = np.tile(r.sizes, k)
            return Ragged(np.tile(r.values, k),
                          np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64))

        return self.per_hypothesis(lambda a: np.tile(a, k), tile_r)


@dataclass(frozen=True)
class ObservationalSide:
    """The observational side of every hypothesis (``bounds.observational_side``)."""

    n: np.ndarray  # (H,) entering trajectories
    follow: Ragged  # raw outcomes of followers
    # aligned with ``follow``: each follower's position among the hypothesis' n entering
    # trajectories in the content-keyed order (``inference.order``: the betting test's data
    # order, independent of the stay numbering); None: unknown
    follow_pos: Ragged | None = None


@dataclass(frozen=True)
class TwinRuns:
    """Entering twin runs per hypothesis in X_0 order: raw outcome and run position
    (``bounds.twin_runs_indexed``; the sequential mode's input)."""

    values: Ragged  # raw outcomes, X_0 order within each hypothesis
    run: np.ndarray  # (total,) position of each value's run in the X_0 order
    in_b0: np.ndarray  # (H, m) real X_0 in B_0 (runs that can ever enter)
    failed: np.ndarray  # (H, m) run failed on the path (and X_0 in B_0)
