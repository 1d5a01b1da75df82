"""The one interface every twin implements, in-process or behind the subprocess protocol."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import pandas as pd

from twinfalsify.schema import FEATURES


@dataclass
class SimResult:
    """Output of simulating n runs for t hours.

    features: (n, t, len(FEATURES)) values at the end of hours 1..t, in the
    trajectory contract's units and column order; NaN where a run failed.
    status: (n,) one of schema.TWIN_STATUSES. message: (n,) free text ('' if ok).
    clamped: (n,) JSON object text of X_0 features the twin had to clamp,
    {feature: [given, used]} ('{}' if none).
    """

    features: np.ndarray
    status: np.ndarray
    message: np.ndarray = field(default=None)  # type: ignore[assignment]
    clamped: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n = self.features.shape[0]
        if self.message is None:
            self.message = np.full(n, "", dtype=object)
        if self.clamped is None:
            self.clamped = np.full(n, "{}", dtype=object)


class Twin(Protocol):
    """A digital twin.

    ``simulate(x0, doses, seeds)``: x0 is a frame of n initial states with (at
    least) the columns of schema.FEATURES (a twin may use only some of them,
    e.g. Pulse only schema.INIT_FEATURES); doses is (n, t, 2) with IV fluid in
    mL/h and vasopressor in ug/kg/min applied during hours 1..t; seeds is (n,)
    uint64, one per run. Randomness of hour s must depend only on (seed, doses
    of hours 1..s), so that runs sharing an X_0 seed and a dose prefix share
    the simulated prefix (exact prefix reuse) and results do not depend on
    how runs are batched.
    """

    name: str

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult: ...


def empty_features(n: int, hours: int) -> np.ndarray:
    return np.full((n, hours, len(FEATURES)), np.nan)
