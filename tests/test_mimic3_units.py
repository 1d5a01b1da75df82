"""Unit tests of the MIMIC-III building blocks: conversions, outliers, blood pressure,
sample-and-hold, 1-NN imputation, vasopressor equivalents, data tables."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify.sources.mimic3 import doses, hourly
from twinfalsify.sources.mimic3.tables import data_table, data_version

T0 = pd.Timestamp("2150-01-01 10:00")


def test_data_tables_have_meaning_and_version():
    for name in ("items.csv", "unit_conversions.csv", "outlier_limits.csv", "sample_and_hold.csv",
                 "vasopressors.csv", "fluids.csv", "antibiotics.csv"):
        t = data_table(name)
        assert t["meaning"].notna().all(), name
        assert data_version(name) == "1"
    items = data_table("items.csv")
    assert not items.duplicated(["itemid", "source"]).any()


def test_convert_values_temperature_weight_fio2():
    ev = pd.DataFrame({
        "icustay_id": 1, "time": T0, "source": "chartevents",
        "itemid": [223761, 223761, 223762, 226531, 3582, 223835, 190],
        "value": [212.0, 37.5, 98.6, 200.0, 32.0, 0.5, 0.4]})
    out = hourly.convert_values(ev)["value"].to_numpy()
    np.testing.assert_allclose(out, [
        100.0,  # (212 - 32) * 5/9
        37.5,  # F item holding a Celsius value (25 < v < 45): kept
        37.0,  # C item holding Fahrenheit (> 70): converted
        200 * 0.45359237, 32 * 0.028349523125,
        50.0,  # percent item < 1 is a fraction
        40.0])  # fraction item x 100


def test_delete_outliers_bounds_inclusive():
    ev = pd.DataFrame({"icustay_id": 1, "time": T0,
                       "feature": ["HR", "HR", "Sodium", "Sodium", "Sodium", "Calcium"],
                       "value": [250.0, 250.1, 95.0, 94.9, 178.1, 1.9]})
    kept = hourly.delete_outliers(ev)
    assert kept["value"].tolist() == [250.0, 95.0]


def test_complete_bp_formulas():
    b = pd.DataFrame({"SysBP": [120, 120, np.nan], "MeanBP": [np.nan, 90, 90],
                      "DiaBP": [60, np.nan, 75]}, dtype=float)
    c = hourly.complete_bp(b)
    np.testing.assert_allclose(c["MeanBP"], [80, 90, 90])  # (120 + 2*60) / 3
    np.testing.assert_allclose(c["DiaBP"], [60, 75, 75])  # (3*90 - 120) / 2
    np.testing.assert_allclose(c["SysBP"], [120, 120, 120])  # 3*90 - 2*75


def test_block_means_and_sample_and_hold_boundary():
    intime = pd.Series([T0], index=pd.Index([7], name="icustay_id"))
    h = pd.Timedelta(hours=1)
    ev = pd.DataFrame({"icustay_id": 7, "feature": "HR",
                       "time": [T0 + 0.25 * h, T0 + 0.75 * h, T0 + 1 * h],
                       "value": [80.0, 100.0, 70.0]})
    b = hourly.block_means(ev, intime, ("HR",), 4)
    assert b["HR"].tolist()[:2] == [90.0, 70.0]  # mean within [0, 1); 1:00 belongs to t = 1
    assert np.isnan(b["HR"].tolist()[2:]).all()
    held = hourly.sample_and_hold(b, ev, intime)
    # last value (1:00) held 2 h: block start 2:00 (1 h old) and 3:00 (2 h old) -> held;
    # 4:00 (3 h old) -> missing
    assert held["HR"].tolist()[:4] == [90.0, 70.0, 70.0, 70.0]
    assert np.isnan(held["HR"].iloc[4])


def test_knn_impute_matches_brute_force():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(40, 5)) * [1, 10, 100, 1, 5]
    mask = rng.random(x.shape) < 0.2
    mask[:, 0] = False
    xm = np.where(mask, np.nan, x)
    out = hourly.knn_impute(xm)
    sd = np.nanstd(xm, axis=0)
    for i, j in zip(*np.nonzero(mask), strict=True):
        best, bestd = None, np.inf
        for k in range(len(x)):
            if k == i or mask[k, j]:
                continue
            sh = ~mask[i] & ~mask[k]
            d = np.mean(((xm[i, sh] - xm[k, sh]) / sd[sh]) ** 2)
            if d < bestd:
                best, bestd = k, d
        assert out[i, j] == xm[best, j]
    assert np.array_equal(out[~mask], x[~mask])


@pytest.mark.parametrize("system,item,rate,uom,expected", [
    ("mv", 221906, 0.2, "mcg/kg/min", 0.2),
    ("mv", 221906, 16, "mcg/min", 0.2),  # / 80 kg
    ("mv", 222315, 0.04, "units/min", 0.2),  # x 5
    ("mv", 222315, 2.4, "units/min", 0.2),  # > 0.2 taken as U/h: x 5/60
    ("cv", 30051, 0.04, "Umin", 0.2),
    ("cv", 30127, 100, "mcgkgmin", 45.0),  # x 0.45
    ("cv", 30043, 10, "mcgkgmin", 0.1),  # x 0.01
    ("mv", 221662, 800, "mcg/min", 0.1),  # x 0.01 / 80
    ("mv", 221906, 1, "mg/hour", np.nan),  # no rule: not counted
])
def test_norepinephrine_equivalent(system, item, rate, uom, expected):
    ev = pd.DataFrame({"itemid": [item], "rate": [rate], "rateuom": [uom]})
    got = doses.norepinephrine_equivalent(ev, system).iloc[0]
    if np.isnan(expected):
        assert np.isnan(got)
    else:
        assert got == pytest.approx(expected, rel=1e-12)


def _held(rows: dict[int, list[bool]]) -> pd.DataFrame:
    """(icustay_id, t) frame of the six vitals: complete (1.0) or with HR missing (NaN)."""
    idx, vals = [], []
    for sid, complete in rows.items():
        for k, ok in enumerate(complete):
            idx.append((sid, k))
            vals.append([1.0 if ok else np.nan] + [1.0] * (len(hourly.VITALS) - 1))
    return pd.DataFrame(vals, index=pd.MultiIndex.from_tuples(idx, names=["icustay_id", "t"]),
                        columns=list(hourly.VITALS))


def test_first_complete_vitals_first_hour_within_window():
    from twinfalsify.sources.mimic3.cohort import first_complete_vitals
    held = _held({1: [True, False, True], 2: [False, False, True, True],
                  3: [False, False, False, True], 4: [False] * 4})
    got = first_complete_vitals(held, window_h=3)
    # 1: hour 0; 2: hour 2 (the last allowed); 3: hour 3 is outside hours 0..2; 4: never
    assert got.to_dict() == {1: 0, 2: 2}
    assert first_complete_vitals(held, window_h=4).to_dict() == {1: 0, 2: 2, 3: 3}


def test_realign_shifts_blocks_by_the_anchor():
    from twinfalsify.sources.mimic3.cohort import realign
    idx = pd.MultiIndex.from_product([[10, 20, 30], range(5)], names=["icustay_id", "t"])
    f = pd.DataFrame({"v": np.arange(15.0)}, index=idx)  # v = 5 * stay_index + k
    out = realign(f, pd.Series({10: 0, 20: 2}), t_max=2)
    # stay 10: blocks 0..2 -> t 0..2; stay 20: blocks 2..4 -> t 0..2; stay 30: no anchor
    assert out.index.tolist() == [(10, 0), (10, 1), (10, 2), (20, 0), (20, 1), (20, 2)]
    assert out["v"].tolist() == [0, 1, 2, 7, 8, 9]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_knn_impute_fast_equals_direct_with_ties_and_chunks(seed):
    rng = np.random.default_rng(seed)
    # integer-valued columns and duplicated rows make many exact distance ties
    x = rng.integers(0, 4, size=(300, 6)).astype(float) * [1, 10, 100, 1, 5, 0.1]
    x[150:200] = x[100:150]
    x[rng.random(x.shape) < 0.3] = np.nan
    x[7] = np.nan  # a row with nothing observed stays NaN
    for chunk, batch in ((10_000, 512), (120, 7)):
        fast = hourly.knn_impute(x, chunk=chunk, batch=batch)
        slow = hourly._knn_impute_direct(x, chunk=chunk)
        np.testing.assert_array_equal(fast, slow)
    assert np.isnan(fast[7]).all()
