"""The single-hypothesis bounds figure draws the bounds also for a hypothesis of hour 1 only."""

from __future__ import annotations

import numpy as np
import pandas as pd

from twinfalsify import figures


def _frame(hours: int) -> pd.DataFrame:
    return pd.DataFrame({
        "t": np.arange(1, hours + 1), "outcome": "paCO2", "actions": [[0] * h for h in
                                                                      range(1, hours + 1)],
        "bins": [[1] * (h + 1) for h in range(1, hours + 1)],
        "q_lo_hat": 36.0, "q_up_hat": 44.0, "r_bound": 1.5, "q_twin_hat": 47.0, "r_twin": 1.0,
        "q_obs_hat": 40.0, "r_obs": 1.2, "n": 120, "nhat": 300})


def _band_extents(fig) -> list[tuple[float, float, float, float]]:
    """(x0, x1, y0, y1) of each filled band the figure draws."""
    ax = fig.axes[0]
    out = []
    for coll in ax.collections:
        for path in coll.get_paths():
            v = path.vertices
            if len(v):
                out.append((v[:, 0].min(), v[:, 0].max(), v[:, 1].min(), v[:, 1].max()))
    return out


def test_a_one_hour_hypothesis_has_its_bounds_drawn():
    bands = [b for b in _band_extents(figures.longitudinal(_frame(1))) if b[1] > b[0]]
    # both bands (bounds, and bounds with intervals) have area around hour 1
    assert len(bands) >= 2
    spans = sorted((round(y0, 6), round(y1, 6)) for _, _, y0, y1 in bands)
    assert (36.0, 44.0) in spans and (34.5, 45.5) in spans
    assert all(x0 < 1.0 < x1 for x0, x1, _, _ in bands)


def test_longer_hypotheses_keep_their_bands_over_the_hours():
    bands = [b for b in _band_extents(figures.longitudinal(_frame(3))) if b[1] > b[0]]
    assert any(x0 == 1.0 and x1 == 3.0 for x0, x1, _, _ in bands)
