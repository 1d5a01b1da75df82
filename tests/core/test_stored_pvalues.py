"""The sweep's Delta = 0 p-values read from a results table: placed by hypothesis id in the
caller's order, whatever the table's row order, and refused when a row is missing or doubled."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify.schema import ContractError
from twinfalsify.twin_tests import stored_pvalues


def _results(ids, methods=("betting", "hoeffding")):
    rows = [{"hyp_id": h, "side": s, "method": m, "p_value": (h + 1) / 100 + (s == "up") / 1000
             + (m == "hoeffding") / 10}
            for h in ids for s in ("lo", "up") for m in methods]
    return pd.DataFrame(rows).sample(frac=1.0, random_state=0)  # rows in any order


def test_pvalues_follow_the_callers_hypothesis_order():
    ids = np.array([7, 2, 11, 0])
    got = stored_pvalues(_results([0, 2, 7, 11]), ids, ["betting", "hoeffding"])
    np.testing.assert_array_equal(got["betting"][0], (ids + 1) / 100)
    np.testing.assert_array_equal(got["betting"][1], (ids + 1) / 100 + 1e-3)
    np.testing.assert_array_equal(got["hoeffding"][0], (ids + 1) / 100 + 0.1)


def test_a_missing_or_doubled_row_is_refused():
    res = _results([0, 1, 2])
    with pytest.raises(ContractError, match="misses some hypotheses"):
        stored_pvalues(res, np.array([0, 1, 2, 3]), ["betting"])
    with pytest.raises(ContractError, match="no p-values of method 'bootstrap'"):
        stored_pvalues(res, np.array([0, 1, 2]), ["bootstrap"])
    with pytest.raises(ContractError, match="listed twice"):
        stored_pvalues(pd.concat([res, res.iloc[:1]]), np.array([0, 1, 2]), ["betting"])
