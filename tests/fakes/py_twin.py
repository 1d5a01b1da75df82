"""A ``kind: python`` twin for tests: ``factory: py_twin:make`` (with ``path: tests/fakes``).

Each hour, fluids raise blood pressure and lower heart rate, a vasopressor raises both,
plus noise drawn from the run's seed and the doses so far (so runs sharing a dose prefix
share it, as the Twin interface asks). ``hr_step`` adds a fixed drift to HR per hour.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import pandas as pd

from twinfalsify.schema import FEATURES
from twinfalsify.twins.base import SimResult

_HR, _SYS, _DIA, _MAP = (FEATURES.index(f) for f in ("HR", "SysBP", "DiaBP", "MeanBP"))


@dataclass
class PyTwin:
    """Vectorised over runs; hour h depends on X_0, the seed and the doses of hours 1..h."""

    hr_step: float = 0.0
    name: str = "py"

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        x = x0[list(FEATURES)].to_numpy(float).copy()
        n, hours = doses.shape[0], doses.shape[1]
        out = np.empty((n, hours, len(FEATURES)))
        for h in range(hours):
            noise = np.array([np.random.default_rng(
                [int(seeds[i]), zlib.crc32(np.ascontiguousarray(doses[i, :h + 1]).tobytes())]
            ).normal(size=2) for i in range(n)])
            iv, vaso = doses[:, h, 0], doses[:, h, 1]
            x[:, _SYS] += 0.02 * iv + 25 * vaso + 2 * noise[:, 0]
            x[:, _DIA] += 0.01 * iv + 12 * vaso + noise[:, 1]
            x[:, _MAP] = (x[:, _SYS] + 2 * x[:, _DIA]) / 3
            x[:, _HR] += -0.01 * iv + 8 * vaso + self.hr_step
            out[:, h] = x
        return SimResult(features=out, status=np.full(n, "ok", dtype=object))


def make(hr_step: float = 0.0) -> PyTwin:
    """The factory a config names: ``factory: py_twin:make``."""
    return PyTwin(hr_step=hr_step)
