"""Sensitivity sweep over Delta: agreement with a direct run, monotonicity, table shape, figure."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify.inference.hoeffding import hoeffding_test
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.sensitivity import plot_sensitivity, sensitivity_sweep, widened


def _case(seed=0, h=120):
    rng = np.random.default_rng(seed)
    n = rng.integers(200, 2000, h)
    nf = (n * rng.uniform(0.6, 1, h)).astype(int)
    nh = rng.integers(200, 1000, h)
    shift = rng.uniform(-3, 3, h)
    # outcomes inside [y_lo, y_up] = [60, 100] so widening never changes the clipping
    follow = Ragged.from_groups([rng.uniform(65, 95, k) for k in nf])
    twin = Ragged.from_groups([np.clip(rng.uniform(65, 95, k) + 8 * shift[i], 60, 100)
                               for i, k in enumerate(nh)])
    s = HypothesisSamples(np.full(h, 60.0), np.full(h, 100.0), n.astype(np.int64), follow, twin)
    return s, np.array(["hr", "map", "rr"])[np.arange(h) % 3]


def test_delta_zero_matches_direct_run_and_counts_per_group():
    s, g = _case()
    t = sensitivity_sweep(s, [0.0], {"hoeffding": hoeffding_test}, group=g)
    p_lo, p_up = hoeffding_test(s)
    rej = correct(np.concatenate([p_lo, p_up]), 0.05, "holm")
    per = rej[: len(s)].astype(int) + rej[len(s):]
    for grp in ("hr", "map", "rr"):
        row = t[t.group == grp].iloc[0]
        assert row.n_rejected == per[g == grp].sum()
        assert row.n_hypotheses == 2 * (g == grp).sum()
    assert t.n_rejected.sum() > 0


def test_rejections_fall_as_the_range_widens():
    s, g = _case(seed=1)
    deltas = [0.0, 0.1, 0.2, 0.4, 0.8]
    t = sensitivity_sweep(s, deltas, {"hoeffding": hoeffding_test}, correction="by")
    counts = t.sort_values("delta").n_rejected.to_numpy()
    assert counts[0] > counts[-1] and np.all(np.diff(counts) <= 0)
    w = widened(s, 0.2)
    np.testing.assert_allclose(w.y_lo, 60 * 0.9)
    np.testing.assert_allclose(w.y_up, 100 * 1.1)


def test_bad_input_and_figure(tmp_path):
    s, g = _case(h=9)
    with pytest.raises(ValueError, match="group"):
        sensitivity_sweep(s, [0.0], {"h": hoeffding_test}, group=g[:3])
    with pytest.raises(ValueError, match="empty range"):
        widened(s, -3.0)
    t = sensitivity_sweep(s, [0.0, 0.5], {"h": hoeffding_test, "h4": lambda x: hoeffding_test(
        x, factor=4)}, group=g)
    assert list(t.columns) == ["delta", "method", "group", "n_hypotheses", "n_rejected"]
    assert len(t) == 2 * 2 * 3
    out = plot_sensitivity(t, tmp_path / "fig" / "sens.png")
    assert out.exists() and out.stat().st_size > 1000
    with pytest.raises(ValueError, match="lacks columns"):
        plot_sensitivity(pd.DataFrame({"delta": [0]}), tmp_path / "x.png")
