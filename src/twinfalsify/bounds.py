"""Both sides of every hypothesis, vectorised over hypotheses and trajectories.

Observational side (test set D), for hypothesis h = (k, t, a_1:t, B_0:t):
N = max{s <= t : A_1:s = a_1:s} (0 when A_1 != a_1); a trajectory enters iff
X_0:N in B_0:N; it is a follower iff N = t. The followers' raw outcomes X_t[k]
are kept (methods clip them to [y_lo, y_up]); non-followers contribute y_lo to
Y_lo and y_up to Y_up (Cornish et al. 2026, Theorem: Q_lo <= E[Y(a) | X(a) in B]
<= Q_up, with (Q_up - Q_lo) / (y_up - y_lo) = 1 - P(A_1:t = a_1:t | X_0:N in B_0:N)).

Twin side: run i of sequence a_1:t enters iff the real X_0 of its initial stay
is in B_0 and Xtwin_s in B_s for s = 1..t; its outcome is Xtwin_t[k].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from twinfalsify.design import WHOLE_SPACE, StateBins, padded, state_codes
from twinfalsify.inference.order import content_keys
from twinfalsify.inference.samples import HypothesisSamples, ObservationalSide, Ragged, TwinRuns

# TwinNodes lives in schema (a data contract), so the twin stage does not depend on this
# module: a fix here reruns the tests, not the twin runs (code fingerprints)
from twinfalsify.schema import FEATURES, T_MAX, ContractError, TwinNodes

_CHUNK_CELLS = 40_000_000  # booleans per chunk (H_chunk x n x (T + 1)): bounded memory


def _scatter_rows(hs: np.ndarray, rows: np.ndarray,
                  *targets: tuple[list[np.ndarray], np.ndarray]) -> None:
    """For each (groups, values) pair: ``values`` (aligned with ``rows``, row-sorted indices
    into ``hs``) split by row, row j's part stored as ``groups[hs[j]]``."""
    cuts = np.searchsorted(rows, np.arange(1, len(hs)))
    for groups, values in targets:
        for j, part in enumerate(np.split(values, cuts)):
            groups[hs[j]] = part


def _chunks(size: int, n: int, width: int) -> list[slice]:
    step = max(1, _CHUNK_CELLS // max(1, n * width))
    return [slice(i, min(i + step, size)) for i in range(0, size, step)]


def _bmatch(bins: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """(H, T+1) hypothesis B codes vs (n, T+1) codes -> (H, n, T+1) membership."""
    b = bins[:, None, :]
    return (b == codes[None, :, :]) | (b == WHOLE_SPACE)


def observational_side(
    hyps: pd.DataFrame,
    x: np.ndarray,
    actions: np.ndarray,
    states: StateBins,
    t_max: int = T_MAX,
    order_seed: int = 0,
) -> ObservationalSide:
    """Counts and follower outcomes on D: x (n, T+1, F) features, actions (n, T) codes.

    ``order_seed`` (the study seed) keys the data order of the followers' positions
    (``inference.order.content_keys``): a hypothesis of hour t orders its entering
    trajectories by a keyed hash of their X_0:t, A_1:t, so no stay id and no row order enters.
    """
    h_total = len(hyps)
    n_enter = np.zeros(h_total, dtype=np.int64)
    groups: list[np.ndarray] = [np.zeros(0)] * h_total
    pos_groups: list[np.ndarray] = [np.zeros(0)] * h_total
    a_pad = padded(hyps, "actions", t_max)
    b_pad = padded(hyps, "bins", t_max + 1)
    t_h = hyps["t"].to_numpy(np.int64)
    s_idx = np.arange(t_max + 1)
    keys = content_keys(x[:, : t_max + 1], actions[:, :t_max], order_seed)
    # per hour t: the data order of D (stable: ties are identical contents, module doc) and
    # each row's rank in it
    order = {int(t): np.argsort(keys[:, t], kind="stable") for t in np.unique(t_h)}
    rank = {t: np.argsort(o, kind="stable") for t, o in order.items()}
    for outcome, idx in hyps.groupby("outcome", sort=False).indices.items():
        codes = state_codes(x, states, outcome)
        y = x[:, :, FEATURES.index(outcome)]
        for sl in _chunks(len(idx), len(x), t_max + 1):
            hs = idx[sl]
            eq = actions[None, :, :] == a_pad[hs][:, None, :]
            n_match = np.cumprod(eq, axis=2).sum(axis=2)  # (h, n): N
            allowed = (s_idx[None, None, :] > n_match[..., None]) | _bmatch(b_pad[hs], codes)
            enter = allowed.all(axis=2)
            follow = enter & (n_match == t_h[hs][:, None])
            n_enter[hs] = enter.sum(axis=1)
            hh, ii = np.nonzero(follow)
            vals = y[ii, t_h[hs][hh]]
            # rank among the entering ones in the content-keyed order of the hypothesis' hour
            cum = np.empty(enter.shape, dtype=np.int64)
            for t in np.unique(t_h[hs]):
                r = t_h[hs] == t
                cum[r] = (np.cumsum(enter[r][:, order[int(t)]], axis=1) - 1)[:, rank[int(t)]]
            pos = cum[hh, ii]
            _scatter_rows(hs, hh, (groups, vals), (pos_groups, pos))
    return ObservationalSide(n=n_enter, follow=Ragged.from_groups(groups),
                             follow_pos=Ragged.from_groups(pos_groups))


def observational_side_from_tables(
    hyps: pd.DataFrame, counts: pd.DataFrame, follow: pd.DataFrame
) -> ObservationalSide:
    """The observational_side rule's tables (counts: hyp_id, n; follow: hyp_id, value, pos)
    -> ObservationalSide aligned to ``hyps``' order."""
    ids = hyps["hyp_id"].to_numpy()
    n = counts.set_index("hyp_id")["n"].reindex(ids)
    if n.isna().any():
        raise ContractError(
            f"observational counts lack {int(n.isna().sum())} hypothesis id(s), "
            f"e.g. {int(ids[n.isna().to_numpy()][0])}: rerun the observational_side rule"
        )
    if "pos" not in follow.columns:
        raise ContractError(
            "follower outcomes lack column 'pos' (position among entering trajectories): "
            "rerun the observational_side rule"
        )
    hid = follow["hyp_id"].to_numpy()
    follow_side = Ragged.from_grouped(hid, follow["value"].to_numpy(), ids)
    pos = Ragged.from_grouped(hid, follow["pos"].to_numpy(), ids)  # same stable grouping
    return ObservationalSide(n=n.to_numpy(np.int64), follow=follow_side, follow_pos=pos)


def read_observational_side(
    hypotheses: str, counts: str, follow: str
) -> tuple[pd.DataFrame, ObservationalSide]:
    """Read the design's hypotheses and the observational_side rule's two tables."""
    from twinfalsify.io import read_parquet

    hyps = read_parquet(hypotheses, "hypotheses")
    obs = observational_side_from_tables(
        hyps,
        read_parquet(counts, "observational counts"),
        read_parquet(follow, "follower outcomes"),
    )
    return hyps, obs


@dataclass(frozen=True)
class TwinSide:
    """The twin side of every hypothesis: outcomes, failures and the runs they come from."""

    values: Ragged  # raw outcomes of the entering ok runs, in the plan's run order
    n_failed: np.ndarray  # (H,) failed runs that could have entered
    run: Ragged  # aligned with ``values``: each entering run's index in the plan
    failed_run: Ragged  # the failed runs' plan indices (group sizes = n_failed)


def hypothesis_paths(hyps: pd.DataFrame, index: dict, t_max: int = T_MAX) -> np.ndarray:
    """(H, T) node index of a_1:s for s = 1..t (-1 beyond t)."""
    paths = np.full((len(hyps), t_max), -1, dtype=np.int64)
    for i, seq in enumerate(hyps["actions"].tolist()):
        for s in range(1, len(seq) + 1):
            key = tuple(int(a) for a in seq[:s])
            if key not in index:
                raise KeyError(f"twin nodes: no node {key} for hypothesis row {i}")
            paths[i, s - 1] = index[key]
    return paths


@dataclass(frozen=True)
class PathBoxes:
    """One outcome's hypotheses against every run's path: the entry rule's ingredients.

    ``vals`` (h, T, m): run j's value at hour s of the path a_1:s (NaN off the path or
    failed); ``on_path`` (h, T); ``ok_s`` (h, T, m): that value lies in B_s (True off the
    path); ``in_b0`` (h, m): the real X_0 of run j lies in B_0.
    """

    idx: np.ndarray  # hypothesis rows
    vals: np.ndarray
    on_path: np.ndarray
    ok_s: np.ndarray
    in_b0: np.ndarray

    @property
    def failed(self) -> np.ndarray:
        """(h, m) a node of the run's path failed."""
        return (np.isnan(self.vals) & self.on_path[..., None]).any(axis=1)

    @property
    def enter(self) -> np.ndarray:
        """(h, m) the run enters: X_0 in B_0, Xtwin_s in B_s for s = 1..t, nothing failed."""
        return self.in_b0 & self.ok_s.all(axis=1) & ~self.failed

    @property
    def could_enter_failed(self) -> np.ndarray:
        """(h, m) failed runs that could have entered: X_0 in B_0 and no completed hour
        (before the failure) outside its B_s (such a run cannot enter whatever it did next)."""
        left_b = (self.on_path[..., None] & ~np.isnan(self.vals) & ~self.ok_s).any(axis=1)
        return self.failed & self.in_b0 & ~left_b

    def last(self, t: np.ndarray) -> np.ndarray:
        """(h, m) each run's value at the hypothesis' own hour t."""
        return self.vals[np.arange(len(self.idx)), t[self.idx] - 1, :]


def path_boxes(hyps: pd.DataFrame, nodes: TwinNodes, states: StateBins, t_max: int = T_MAX):
    """Per outcome, in chunks of bounded memory: :class:`PathBoxes`. The one place the entry
    rule of the twin side reads B-sets (fixed tests, sequential mode, depth truncation)."""
    paths = hypothesis_paths(hyps, nodes.index, t_max)
    b_pad = padded(hyps, "bins", t_max + 1)
    base0 = states.base_codes(nodes.x0)
    m = nodes.x0.shape[0]
    for outcome, o_idx in hyps.groupby("outcome", sort=False).indices.items():
        k = FEATURES.index(outcome)
        code0 = base0 + states.above(outcome, nodes.x0[:, k], 0)
        vk = nodes.values[:, :, k]  # (n_nodes, m)
        for sl in _chunks(len(o_idx), m, t_max + 1):
            idx = o_idx[sl]
            p = paths[idx]  # (h, T)
            vals = np.where(p[..., None] >= 0, vk[np.maximum(p, 0)], np.nan)  # (h, T, m)
            on_path = p >= 0
            codes = base0[None, None, :] + states.above(
                outcome, np.nan_to_num(vals, nan=-np.inf), np.arange(1, t_max + 1)[None, :, None]
            )
            bs = b_pad[idx][:, 1:, None]
            ok_s = ~on_path[..., None] | (bs == WHOLE_SPACE) | (codes == bs)
            b0 = b_pad[idx][:, 0][:, None]
            yield PathBoxes(idx, vals, on_path, ok_s,
                            (b0 == WHOLE_SPACE) | (code0[None, :] == b0))


def twin_runs(
    hyps: pd.DataFrame, nodes: TwinNodes, states: StateBins, t_max: int = T_MAX
) -> TwinSide:
    """Entering ok runs (outcome and plan index) and failed runs (plan index) per hypothesis.

    A run whose path a_1:1 .. a_1:t has a failed node cannot be evaluated; it is
    left out of the twin sample and counted in n_failed, unless it could not
    have entered whatever the twin did: X_0 outside B_0, or a completed hour
    s (before the failure) outside B_s (:class:`PathBoxes`). The plan indices place each
    failed run in the data order of the betting test (``inference.failures``).
    """
    h_total = len(hyps)
    groups: list[np.ndarray] = [np.zeros(0)] * h_total
    run_groups: list[np.ndarray] = [np.zeros(0)] * h_total
    fail_groups: list[np.ndarray] = [np.zeros(0)] * h_total
    n_failed = np.zeros(h_total, dtype=np.int64)
    t_h = hyps["t"].to_numpy(np.int64)
    for box in path_boxes(hyps, nodes, states, t_max):
        hs = box.idx
        could = box.could_enter_failed
        n_failed[hs] = could.sum(axis=1)
        fh, fi = np.nonzero(could)
        _scatter_rows(hs, fh, (fail_groups, fi))
        last = box.last(t_h)
        hh, ii = np.nonzero(box.enter)
        _scatter_rows(hs, hh, (groups, last[hh, ii]), (run_groups, ii))
    return TwinSide(Ragged.from_groups(groups), n_failed, Ragged.from_groups(run_groups),
                    Ragged.from_groups(fail_groups))


def twin_runs_indexed(
    hyps: pd.DataFrame, nodes: TwinNodes, states: StateBins, t_max: int = T_MAX
) -> TwinRuns:
    """:func:`twin_runs` as the sequential mode reads it: the entering runs' outcomes in
    X_0 order with their positions, and the (H, m) masks of X_0 in B_0 and failed runs."""
    h_total = len(hyps)
    m = nodes.x0.shape[0]
    t_h = hyps["t"].to_numpy(np.int64)
    in_b0 = np.zeros((h_total, m), dtype=bool)
    failed_all = np.zeros((h_total, m), dtype=bool)
    enter_all = np.zeros((h_total, m), dtype=bool)
    last_all = np.zeros((h_total, m))
    for box in path_boxes(hyps, nodes, states, t_max):
        in_b0[box.idx] = box.in_b0
        failed_all[box.idx] = box.could_enter_failed
        enter_all[box.idx] = box.enter
        last_all[box.idx] = box.last(t_h)
    hh, ii = np.nonzero(enter_all)  # row-major: X_0 order within each hypothesis
    sizes = np.bincount(hh, minlength=h_total)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return TwinRuns(Ragged(last_all[hh, ii], offsets), ii.astype(np.int64), in_b0, failed_all)


def reachable(hyps: pd.DataFrame, nodes: TwinNodes, states: StateBins, t_max: int = T_MAX
              ) -> np.ndarray:
    """(H, T, m) bool: run j can still enter hypothesis h when hour s of its path begins:
    X_0 in B_0 and every completed hour s' < s in B_s' (a failed, NaN hour counts as
    inside: it cannot be shown to have left). Hour s of run j is needed for h only then
    (*depth truncation*: a run that left B_s' never enters h, whatever it does next)."""
    out = np.zeros((len(hyps), t_max, nodes.x0.shape[0]), dtype=bool)
    for box in path_boxes(hyps, nodes, states, t_max):
        inside = box.ok_s | np.isnan(box.vals)
        before = np.concatenate([np.ones_like(inside[:, :1]),
                                 np.logical_and.accumulate(inside[:, :-1], axis=1)], axis=1)
        out[box.idx] = box.in_b0[:, None, :] & before
    return out


def hypothesis_samples(
    hyps: pd.DataFrame, obs: ObservationalSide, twin: Ragged | TwinSide
) -> HypothesisSamples:
    """Both sides as the tests read them; a :class:`TwinSide` also places the failed runs."""
    runs = twin if isinstance(twin, TwinSide) else None
    if runs is not None:
        twin = runs.values
    return HypothesisSamples(
        y_lo=hyps["y_lo"].to_numpy(float),
        y_up=hyps["y_up"].to_numpy(float),
        n=obs.n,
        follow=obs.follow,
        twin=twin,
        follow_pos=obs.follow_pos,
        twin_run=None if runs is None else runs.run,
        failed_run=None if runs is None else runs.failed_run,
    )
