"""Sample splitting: a held-out design set D0 and the test set D (docs/explanation/method.md).

Every data-dependent choice (action bins, B-sets, y_lo/y_up, which hypotheses)
is made on D0 only, so that the hypotheses are fixed before D is looked at
and the tests on D stay valid. By default whole patients are split (all stays of a
patient on one side): hypotheses chosen on one stay of a patient are not independent of
that patient's other stays.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from twinfalsify.schema import STAY_ID, SUBJECT_ID, ContractError

SPLIT_BY = ("subject", "stay")


def split_stays(
    trajectories: pd.DataFrame, d0_fraction: float, seed: int, by: str = "subject"
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Seeded split of whole stays (``by="stay"``, the paper's) or of whole patients
    (``by="subject"``, the default): D0 gets floor(fraction * n) of the n units, the first
    ones of a seeded permutation of the sorted unit ids. Patients are the trajectories'
    ``subject_id`` column; without it each stay is its own patient, and both give the same
    split. Paper (by stay): 583 of 11,677.
    """
    if not 0.0 < d0_fraction < 1.0:
        raise ContractError(f"split.d0_fraction must be in (0, 1), got {d0_fraction}")
    if by not in SPLIT_BY:
        raise ContractError(f"split.by must be one of {', '.join(SPLIT_BY)}, got {by!r}")
    col = SUBJECT_ID if by == "subject" and SUBJECT_ID in trajectories else STAY_ID
    units = np.sort(trajectories[col].unique())
    n0 = int(np.floor(d0_fraction * len(units)))
    what = "patient" if col == SUBJECT_ID else "stay"
    if n0 < 1 or n0 >= len(units):
        raise ContractError(
            f"split: {len(units)} {what}(s) with d0_fraction {d0_fraction} leave D0 with {n0} "
            f"{what}(s); need at least one {what} in each of D0 and D"
        )
    perm = np.random.default_rng(seed).permutation(units)
    in_d0 = trajectories[col].isin(set(perm[:n0].tolist()))
    d0 = trajectories.loc[in_d0].reset_index(drop=True)
    d = trajectories.loc[~in_d0].reset_index(drop=True)
    return d0, d
