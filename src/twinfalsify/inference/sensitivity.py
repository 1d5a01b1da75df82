r"""Sensitivity of the rejections to the outcome range [y_lo, y_up] (the paper's appendix).

For every :math:`\Delta` in a grid, rerun each test with

.. math::

    y_{lo} \to y_{lo} (1 - \Delta/2), \qquad y_{up} \to y_{up} (1 + \Delta/2)

and correct each family as the main analysis does (the same methods, failed-run handling,
level and correction, within each (method, family), both sides of every parameter set),
then count rejections per group (e.g. outcome). :math:`\Delta = 0` reproduces the main
analysis' decisions exactly. Widening moves both the bounds and the clipping of every
sample, so the counts need not fall monotonically with :math:`\Delta`: a twin output
clipped at y_lo moves down with y_lo, and a widened range can bring a twin mean that sat
inside the bounds outside them.

For a negative y_lo the map moves y_lo up (towards 0): a relative, not an absolute,
widening; the sweep refuses ranges that become empty.

Speed: the betting test's data order depends on the samples' sizes and keys only, never on
[y_lo, y_up], so the sweep computes it once and reuses it at every widening
(``betting.order_cache``); every p-value is the one a separate call gives, bit for bit. The
main analysis' own p-values can be given for :math:`\Delta = 0` (``at_zero``), which are
then not computed again. The bootstrap's resamples cannot be reused that way: it draws
how many values of a resample are clipped at y_lo, at y_up or interior, with the shares of
each at that widening (``bootstrap._side_draws``), so a widening that moves any value across
a bound changes the draws of every hypothesis after it in the stream.

Reference: Cornish et al. (2026), JMLR, appendix (sensitivity to y_lo, y_up).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from twinfalsify.inference.betting import order_cache
from twinfalsify.inference.failures import failure_pvalues
from twinfalsify.inference.multiple_testing import correct_within
from twinfalsify.inference.samples import HypothesisSamples

Method = Callable[[HypothesisSamples], tuple[np.ndarray, np.ndarray]]
COLUMNS = ["delta", "method", "family", "group", "n_hypotheses", "n_rejected"]


def widened(samples: HypothesisSamples, delta: float) -> HypothesisSamples:
    """The samples with [y_lo (1 - delta/2), y_up (1 + delta/2)]."""
    y_lo = samples.y_lo * (1 - delta / 2)
    y_up = samples.y_up * (1 + delta / 2)
    if np.any(~(y_up > y_lo)):
        bad = np.flatnonzero(~(y_up > y_lo))[:5].tolist()
        raise ValueError(f"sensitivity: Delta={delta} leaves an empty range for hypotheses {bad}")
    return samples.with_bounds(y_lo, y_up)


def sweep_pvalues(
    method: Method, samples: HypothesisSamples, n_failed: np.ndarray, deltas: Sequence[float],
    failed_runs: str = "conservative", progress: Callable[[int, float], None] | None = None,
    at_zero: tuple[np.ndarray, np.ndarray] | None = None, families: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(p_lo, p_up), each (len(deltas), H): the method's p-values at every widening, each
    the main analysis' own call on the widened samples (Delta = 0: the main analysis; its
    p-values ``at_zero`` when given; ``families`` as in ``failures.failure_pvalues``).
    ``progress(j, seconds)`` is called after widening j."""
    f = np.asarray(n_failed, np.int64)
    out = []
    with order_cache():
        for j, d in enumerate(deltas):
            t0 = time.perf_counter()
            if float(d) == 0.0 and at_zero is not None:
                out.append(tuple(np.asarray(p, float) for p in at_zero))
            else:
                out.append(failure_pvalues(method, widened(samples, float(d)), f, failed_runs,
                                           families=families))
            if progress is not None:
                progress(j, time.perf_counter() - t0)
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def sensitivity_sweep(
    samples: HypothesisSamples,
    deltas: Sequence[float],
    methods: Mapping[str, Method],
    alpha: float = 0.05,
    correction: str = "holm",
    group: np.ndarray | None = None,
    *,
    n_failed: np.ndarray | None = None,
    failed_runs: str = "conservative",
    family: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    at_zero: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> pd.DataFrame:
    """Long table (delta, method, family, group, n_hypotheses, n_rejected), both sides counted.

    ``family`` labels each parameter set's family (the kind: causal or Manski; default one
    family "all"); the correction runs over both sides of every parameter set of a family
    at each (delta, method), as ``falsify.run_tests`` does. ``group`` labels each
    parameter set for counting (default "all"). ``n_failed``/``failed_runs``: the failed
    twin runs and their handling, as in the main analysis. ``at_zero``: per method, the main
    analysis' (p_lo, p_up), used at Delta = 0 instead of testing again.
    """
    h = len(samples)
    labels = np.full(h, "all", dtype=object) if group is None else np.asarray(group, dtype=object)
    fam = np.full(h, "all", dtype=object) if family is None else np.asarray(family, dtype=object)
    for name, arr in (("group", labels), ("family", fam)):
        if arr.shape != (h,):
            raise ValueError(f"sensitivity: {name} has shape {arr.shape}, expected ({h},)")
    if not methods:
        raise ValueError("sensitivity: no methods given")
    f = np.zeros(h, np.int64) if n_failed is None else np.asarray(n_failed, np.int64)
    cells = pd.DataFrame({"family": fam, "group": labels})
    keys = list(cells.drop_duplicates().itertuples(index=False, name=None))
    sizes = cells.value_counts(sort=False)
    rows = []
    for name, fn in methods.items():
        def step(j: int, seconds: float, name: str = name) -> None:
            if progress is not None:
                progress(f"{name}: Delta = {deltas[j]:g} ({j + 1}/{len(deltas)}) in "
                         f"{seconds:.1f} s")

        known = None if at_zero is None else at_zero.get(name)
        if known is not None and any(np.shape(p) != (h,) for p in known):
            raise ValueError(f"sensitivity: at_zero[{name!r}] does not have {h} p-values a side")
        p_lo, p_up = sweep_pvalues(fn, samples, f, deltas, failed_runs, step, known,
                                   families=None if family is None else fam)
        for j, delta in enumerate(deltas):
            rej = correct_within(np.concatenate([p_lo[j], p_up[j]]), np.concatenate([fam, fam]),
                                 alpha, correction)
            per = rej[:h].astype(int) + rej[h:].astype(int)
            counts = pd.Series(per).groupby([fam, labels]).sum()
            rows += [(float(delta), name, fa, g, int(2 * sizes[(fa, g)]), int(counts[(fa, g)]))
                     for fa, g in keys]
    return pd.DataFrame(rows, columns=COLUMNS)
