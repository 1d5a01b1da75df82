"""Sample splitting: a held-out design set D0 and the test set D (docs/explanation/method.md).

Every data-dependent choice (action bins, B-sets, y_lo/y_up, which hypotheses)
is made on D0 only, so that the hypotheses are fixed before D is looked at
and the tests on D stay valid.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from twinfalsify.schema import STAY_ID, ContractError


def split_stays(
    trajectories: pd.DataFrame, d0_fraction: float, seed: int
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Seeded split of whole stays: D0 gets floor(fraction * n_stays) stays.

    Paper: 583 of 11,677.
    """
    if not 0.0 < d0_fraction < 1.0:
        raise ContractError(f"split.d0_fraction must be in (0, 1), got {d0_fraction}")
    stays = np.sort(trajectories[STAY_ID].unique())
    n0 = int(np.floor(d0_fraction * len(stays)))
    if n0 < 1 or n0 >= len(stays):
        raise ContractError(
            f"split: {len(stays)} stay(s) with d0_fraction {d0_fraction} leave D0 with {n0} "
            "stay(s); need at least one stay in each of D0 and D"
        )
    perm = np.random.default_rng(seed).permutation(stays)
    in_d0 = trajectories[STAY_ID].isin(set(perm[:n0].tolist()))
    d0 = trajectories.loc[in_d0].reset_index(drop=True)
    d = trajectories.loc[~in_d0].reset_index(drop=True)
    return d0, d
