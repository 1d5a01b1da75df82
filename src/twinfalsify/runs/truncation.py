"""Depth truncation over the twin protocol: which hours of a run are still needed.

A simulate request may carry ``continue_while``: a list of *box paths*, one per hypothesis
(or group of hypotheses) the run serves. Path p = [[feature, op, threshold], ...] holds the
box of hour 1, 2, ... (op ">" or "<=": a B-set bin "above / not above the D0 median at that
hour"; "any": the whole space), for the hours before the hypothesis' last one. After
completing hour s the run is still needed iff some path has at least s boxes and its first
s boxes all hold on hours 1..s; otherwise no hypothesis can be entered by it any more, and
a twin with the ``truncate`` capability may stop it and answer the hours it has, flagged
``truncated`` (docs/reference/twin-protocol.md). The caller checks the flag against the same rule.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from twinfalsify.schema import FEATURES, WHOLE_SPACE

OPS = (">", "<=", "any")  # "any": the bin is the whole space (always holds)
Box = tuple[str, str, float]  # (feature, op, threshold)


def parse_paths(value: Any) -> list[list[Box]]:
    """A request's ``continue_while`` field -> paths of (feature, op, threshold); ValueError
    naming the problem."""
    if not isinstance(value, list):
        raise ValueError(f"'continue_while' must be a list of box paths, got "
                         f"{type(value).__name__}")
    out = []
    for k, path in enumerate(value):
        if not isinstance(path, list):
            raise ValueError(f"'continue_while' path {k} must be a list of boxes")
        boxes = []
        for box in path:
            if (not isinstance(box, list) or len(box) != 3 or box[0] not in FEATURES
                    or box[1] not in OPS or not isinstance(box[2], int | float)):
                raise ValueError(f"'continue_while' path {k}: box {box!r} is not "
                                 f"[feature, '>' | '<=' | 'any', number]")
            boxes.append((box[0], box[1], float(box[2])))
        out.append(boxes)
    return out


def hours_needed(paths: Sequence[Sequence[Box]], values: np.ndarray | Sequence, hours: int,
                 columns: Sequence[str] = FEATURES) -> int:
    """Hours 1..n of a run that some path still needs, given its completed hours
    ``values`` ((s, len(columns)), ``columns`` order; or protocol hour objects
    {feature: value}): n = 1 + the longest run of leading boxes of any path that hold, at
    most ``hours``. An hour not completed yet counts as holding nothing, so the result never
    exceeds len(values) + 1."""
    col = {c: i for i, c in enumerate(columns)}
    best = 0
    for path in paths:
        k = 0
        while k < min(len(path), len(values)):
            name, op, thr = path[k]
            row = values[k]
            v = row[name] if isinstance(row, Mapping) else row[col[name]]
            if not (op == "any" or (v > thr if op == ">" else v <= thr)):
                break
            k += 1
        best = max(best, k)
    return min(hours, best + 1)


def box_paths(bins: Sequence[int], outcome: str, base: int, medians: Sequence[float]
              ) -> list[list[Any]] | None:
    """The box path of a hypothesis of depth t = len(bins) - 1 for a run whose X_0 has base
    code ``base`` (``design.StateBins``): boxes for hours 1..t-1 as protocol JSON, or None
    when some bin can never hold for this base (the run cannot enter)."""
    path = []
    for s in range(1, len(bins) - 1):
        b = int(bins[s])
        if b == WHOLE_SPACE:
            path.append([outcome, "any", 0.0])
        elif b == base + 1:
            path.append([outcome, ">", float(medians[s])])
        elif b == base:
            path.append([outcome, "<=", float(medians[s])])
        else:
            return None
    return path


class JobBoxes:
    """``continue_while`` of an adaptive shard's jobs: per run, the box paths of the running
    hypotheses whose own last node the job fills first for that run (``runs.adaptive``)."""

    def __init__(self, hyps, in_b0: np.ndarray, states, x0: np.ndarray) -> None:
        self.seqs = [tuple(int(a) for a in q) for q in hyps["actions"].tolist()]
        self.bins = hyps["bins"].tolist()
        self.outcome = hyps["outcome"].tolist()
        self.in_b0 = in_b0  # (len(hyps), m)
        self.base = states.base_codes(x0)
        self.medians = states.medians
        self._paths: dict[tuple[int, int], list | None] = {}
        self._served: dict[tuple[int, ...], list[int]] = {}  # leaf -> hypotheses on its path

    def _path(self, h: int, base: int) -> list | None:
        key = (h, base)
        if key not in self._paths:
            self._paths[key] = box_paths(self.bins[h], self.outcome[h], base,
                                         self.medians[self.outcome[h]])
        return self._paths[key]

    def for_job(self, leaf: tuple[int, ...], runs: np.ndarray, fresh: list[np.ndarray],
                active: np.ndarray) -> list[list]:
        """Per run of the job (X_0 positions ``runs``): its box paths. ``fresh[s-1]``: the
        runs for which this job fills node leaf[:s] first; ``active``: running hypotheses."""
        out: list[dict] = [{} for _ in runs]
        if leaf not in self._served:
            self._served[leaf] = [h for h, q in enumerate(self.seqs) if leaf[:len(q)] == q]
        for h in self._served[leaf]:
            if not active[h]:
                continue
            t = len(self.seqs[h])
            for r in np.flatnonzero(fresh[t - 1] & self.in_b0[h, runs]):
                path = self._path(h, int(self.base[runs[r]]))
                if path is not None:
                    out[r][repr(path)] = path
        return [list(d.values()) for d in out]
