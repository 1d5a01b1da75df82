"""Unit tests of the MIMIC-III building blocks: conversions, outliers, blood pressure,
sample-and-hold, 1-NN imputation, vasopressor equivalents, data tables."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3 import cohort, doses, hourly
from twinfalsify.sources.mimic3.tables import data_table, data_version

T0 = pd.Timestamp("2150-01-01 10:00")


def test_data_tables_have_meaning_and_version():
    versions = {"items.csv": "3", "unit_conversions.csv": "1", "outlier_limits.csv": "3",
                "sample_and_hold.csv": "2", "vasopressors.csv": "5", "fluids.csv": "1",
                "antibiotics.csv": "2", "cultures.csv": "1", "urine.csv": "4",
                "withdrawal.csv": "1", "heights.csv": "1",
                "specimens.csv": "1", "screens.csv": "1", "bp_devices.csv": "1",
                "dose_limits.csv": "1"}
    for name, version in versions.items():
        t = data_table(name)
        assert t["meaning"].notna().all(), name
        assert data_version(name) == version, name
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


def _bp(rows):
    """BP events from (icustay_id, minutes after T0, feature, value)."""
    return pd.DataFrame([{"icustay_id": i, "time": T0 + pd.Timedelta(minutes=m),
                          "feature": f, "value": float(v)} for i, m, f, v in rows])


def _completed(ev):
    out = hourly.complete_bp(ev).iloc[len(ev):]
    return sorted((int(r.icustay_id), int((r.time - T0) / pd.Timedelta(minutes=1)),
                   r.feature, round(r.value, 6)) for r in out.itertuples())


def test_complete_bp_formulas():
    ev = _bp([(1, 0, "SysBP", 120), (1, 0, "DiaBP", 60),  # MAP = (120 + 2*60) / 3
              (2, 0, "SysBP", 120), (2, 0, "MeanBP", 90),  # Dia = (3*90 - 120) / 2
              (3, 0, "MeanBP", 90), (3, 0, "DiaBP", 75)])  # Sys = 3*90 - 2*75
    assert _completed(ev) == [(1, 0, "MeanBP", 80.0), (2, 0, "DiaBP", 75.0),
                              (3, 0, "SysBP", 120.0)]


def test_complete_bp_only_within_a_charting_time():
    # systolic at 0:10, mean at 0:40 of the same hour: two charting times, no completion
    # (an hourly-mean completion combined them); both charted at 0:10 -> completed at 0:10
    ev = _bp([(1, 10, "SysBP", 94), (1, 40, "MeanBP", 142),
              (2, 10, "SysBP", 120), (2, 10, "MeanBP", 90), (2, 40, "SysBP", 150)])
    assert _completed(ev) == [(2, 10, "DiaBP", 75.0)]


def test_complete_bp_keeps_impossible_values_missing():
    ev = _bp([(1, 0, "SysBP", 120), (1, 0, "MeanBP", 80),  # Dia (240 - 120) / 2 = 60
              (2, 0, "SysBP", 200), (2, 0, "MeanBP", 60),  # Dia -20: below the limits
              # MAP above systolic: Dia (3 x 100 - 94) / 2 = 103 > Sys, rejected
              (3, 0, "SysBP", 94), (3, 0, "MeanBP", 100),
              (4, 0, "MeanBP", 90), (4, 0, "DiaBP", 95)])  # Dia above MAP: no Sys
    assert _completed(ev) == [(1, 0, "DiaBP", 60.0)]


def test_completed_bp_is_held_forward():
    # MetaVision without a charted diastolic (bp_items = ai_clinician): Sys and MAP charted
    # together at 0:30, nothing in hour 1. The diastolic completed at 0:30 is held into
    # hour 1 like the charted pair (completion before sample-and-hold, AI-Clinician's order)
    intime = pd.Series([T0], index=pd.Index([1], name="icustay_id"))
    ev = hourly.complete_bp(_bp([(1, 30, "SysBP", 120), (1, 30, "MeanBP", 90)]))
    b = hourly.block_means(ev, intime, hourly.BP, 2)
    held = hourly.sample_and_hold(b, ev, intime)
    assert held["DiaBP"].tolist()[:2] == [75.0, 75.0]
    assert held["SysBP"].tolist()[:2] == [120.0, 120.0]


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


def _brute_knn(x, groups, times):
    """1-NN by the definition: donors of other groups at times <= t, scale = column sd
    (ddof 0) over exactly those donor-eligible rows, mean squared scaled difference over
    the shared columns, first row on ties."""
    out = x.copy()
    obs = np.isfinite(x)
    for i, j in zip(*np.nonzero(~obs), strict=True):
        elig = (groups != groups[i]) & (times <= times[i])
        sd = np.nanstd(np.where(elig[:, None], x, np.nan), axis=0)
        sd[~np.isfinite(sd) | (sd == 0)] = 1.0
        best, bestd = None, np.inf
        for k in np.flatnonzero(elig & obs[:, j]):
            sh = obs[i] & obs[k]
            if not sh.any():
                continue
            d = np.mean(((x[i, sh] - x[k, sh]) / sd[sh]) ** 2)
            if d < bestd:
                best, bestd = k, d
        if best is not None:
            out[i, j] = x[best, j]
    return out


def test_knn_impute_matches_brute_force():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(40, 5)) * [1, 10, 100, 1, 5]
    mask = rng.random(x.shape) < 0.2
    mask[:, 0] = False
    xm = np.where(mask, np.nan, x)
    groups, times = np.repeat(np.arange(8), 5), np.tile(np.arange(5), 8)
    out = hourly.knn_impute(xm, groups, times)
    np.testing.assert_array_equal(out, _brute_knn(xm, groups, times))
    assert np.array_equal(out[~mask], x[~mask])
    # without groups / times: every other row is a donor (leave-one-out scale)
    np.testing.assert_array_equal(hourly.knn_impute(xm),
                                  _brute_knn(xm, np.arange(40), np.zeros(40)))


def test_knn_impute_is_causal_and_never_uses_the_own_stay():
    """Perturbing every row of a later hour (any stay) or any other row of the same stay
    changes no imputed value of hour t of that stay."""
    rng = np.random.default_rng(5)
    n_stays, T = 30, 5
    groups, times = np.repeat(np.arange(n_stays), T), np.tile(np.arange(T), n_stays)
    x = rng.normal(size=(n_stays * T, 6)) * [1, 2, 3, 1, 5, 10]
    x[rng.random(x.shape) < 0.25] = np.nan
    out = hourly.knn_impute(x, groups, times)
    for t in range(T - 1):
        y = x.copy()
        later = times > t
        y[later] = y[later] * rng.uniform(0.5, 1.5, size=y[later].shape) + 1.0
        out2 = hourly.knn_impute(y, groups, times)
        np.testing.assert_array_equal(out2[~later], out[~later])
        assert not np.array_equal(out2[later], out[later], equal_nan=True)
    # a stay's own other rows: perturb all of stay 0 but its hour-2 row
    y = x.copy()
    own = (groups == 0) & (times != 2)
    y[own] = y[own] * 3.0 + 7.0
    out3 = hourly.knn_impute(y, groups, times)
    row = np.flatnonzero((groups == 0) & (times == 2))
    np.testing.assert_array_equal(out3[row], out[row])
    # the old definition (all rows are donors, one global scale) fails the first property
    old = hourly.knn_impute(x, np.arange(len(x)), np.zeros(len(x)))
    y = x.copy()
    y[times > 0] += 100.0
    old2 = hourly.knn_impute(y, np.arange(len(x)), np.zeros(len(x)))
    assert not np.array_equal(old2[times == 0], old[times == 0], equal_nan=True)


def test_sample_and_hold_last_hour_mean():
    intime = pd.Series({7: T0})
    h = pd.Timedelta(hours=1)
    # hour 0: 80 at 0:15 and 100 at 0:45; nothing after
    ev = pd.DataFrame({"icustay_id": 7, "feature": "HR",
                       "time": [T0 + 0.25 * h, T0 + 0.75 * h], "value": [80.0, 100.0]})
    b = hourly.block_means(ev, intime, ("HR",), 4)
    last = hourly.sample_and_hold(b, ev, intime, how="last_value")
    mean = hourly.sample_and_hold(b, ev, intime, how="last_hour_mean")
    # hold 2 h after the last value (0:45): blocks 1 (1:00) and 2 (2:00) held
    assert last["HR"].tolist()[:3] == [90.0, 100.0, 100.0]
    assert mean["HR"].tolist()[:3] == [90.0, 90.0, 90.0]
    assert np.isnan(last["HR"].iloc[3]) and np.isnan(mean["HR"].iloc[3])
    with pytest.raises(ContractError, match="how must be one of"):
        hourly.sample_and_hold(b, ev, intime, how="next_value")


def test_renal_sofa_from_urine_output():
    b = pd.DataFrame({c: [np.nan] * 4 for c in ("pf", "sofa_platelets", "sofa_bilirubin",
                                                 "MeanBP", "vaso", "sofa_gcs")})
    b["sofa_creatinine"] = [1.0, 1.0, 1.0, 6.0]
    b["uo"] = [np.nan, 50.0, 20.0, 500.0]  # not charted / < 84 / < 34 / plenty
    assert cohort.sofa_components(b)["renal"].tolist() == [0, 3, 4, 4]


def test_cardiovascular_sofa_reads_the_rate_to_3_decimals():
    """Demo 265505 (norepinephrine 0.100103647 ug/kg/min) and 298685 (dopamine
    10.0079767 ug/kg/min x 0.01) score 3 points, as the ordered 0.1 / 10 do (SOFA: dopamine
    5-15 is 3 points); 0.1006 reads 0.101: 4."""
    b = pd.DataFrame({c: [np.nan] * 4 for c in ("pf", "sofa_platelets", "sofa_bilirubin",
                                                 "MeanBP", "sofa_gcs", "sofa_creatinine")})
    b["vaso"] = [0.100103647, 10.0079767 * 0.01, 0.1006, 0.05]
    assert cohort.sofa_components(b)["cardiovascular"].tolist() == [3, 3, 4, 3]


def test_the_rate_is_rounded_as_postgresql_rounds_a_numeric():
    """AI-Clinician's queries round ``cast(rate as numeric)`` to 3 decimals: the double's 15
    significant digits, halves away from zero. Binary rounding gives 0.1 for 0.1005 (not
    above SOFA's 0.1 threshold); PostgreSQL gives 0.101 (above it)."""
    x = pd.Series([0.1005, 0.1015, 0.1004999, 0.2345, 0.0, 10.0079767 * 0.01, np.nan, 2.5e-4])
    got = cohort.round_half_up(x, 3)
    want = [0.101, 0.102, 0.1, 0.235, 0.0, 0.1, np.nan, 0.0]
    np.testing.assert_array_equal(got.to_numpy(), np.array(want))
    assert pd.Series([0.1005]).round(3).iloc[0] == 0.1  # what binary rounding would give
    b = pd.DataFrame({c: [np.nan] for c in ("pf", "sofa_platelets", "sofa_bilirubin",
                                            "MeanBP", "sofa_gcs", "sofa_creatinine")})
    b["vaso"] = [0.1005]
    assert cohort.sofa_components(b)["cardiovascular"].tolist() == [4]


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
    stays = (None, None), (np.repeat(np.arange(60), 5), np.tile(np.arange(5), 60))
    for (groups, times), (chunk, batch) in zip(stays * 2, ((10_000, 512), (10_000, 512),
                                                           (120, 7), (120, 7)), strict=True):
        fast = hourly.knn_impute(x, groups, times, chunk=chunk, batch=batch)
        slow = hourly._knn_impute_direct(x, groups, times, chunk=chunk)
        np.testing.assert_array_equal(fast, slow)
        assert np.isnan(fast[7]).all()


def test_norepinephrine_in_mg_per_kg_min_as_the_cited_source():
    # mimic-code norepinephrine.sql: mg/kg/min rows with patientweight = 1 are charted in the
    # wrong unit and kept as mcg/kg/min; other mg/kg/min rows are x 1000
    ev = pd.DataFrame({"itemid": [221906] * 5, "rate": [0.1, 0.0001, 5.0, 0.08, 0.08],
                       "rateuom": ["mcg/kg/min", "mg/kg/min", "mL/hr", "mg/kg/min",
                                   "mg/kg/min"],
                       "patientweight": [70.0, np.nan, 70.0, 1.0, 70.0]})
    ne = doses.norepinephrine_equivalent(ev, "mv").to_numpy()
    np.testing.assert_allclose(ne[[0, 1, 3, 4]], [0.1, 0.1, 0.08, 80.0])
    assert np.isnan(ne[2])  # no rule for mL/hr: counted in the audit table
    # without the column the weight-1 rule cannot match: x 1000
    no_w = doses.norepinephrine_equivalent(ev.drop(columns="patientweight"), "mv").to_numpy()
    assert no_w[3] == pytest.approx(80.0)
    # the 80 is not a dose: outside dose_limits.csv; the bounds themselves are doses
    ok = doses.dose_plausible(pd.Series([0.0, 5.0, 80.0, -0.1, np.nan]), "vasopressor")
    assert ok.tolist() == [True, True, False, False, True]
    ok = doses.dose_plausible(pd.Series([0, 10_000, 10_001, -1]), "iv_fluid")
    assert ok.tolist() == [True, True, False, False]


def test_map_outside_diastolic_systolic_is_deleted():
    t = pd.Timestamp("2150-01-01 10:00")
    m = pd.Timedelta(minutes=1)
    # arterial line (MetaVision 220050 / 220051 / 220052) and cuff (220179 / 220180 / 220181)
    refs = pd.DataFrame({"icustay_id": 1,
                         "time": [t, t, t, t, t + 60 * m, t + 90 * m, t + 90 * m],
                         "itemid": [220050, 220051, 220179, 220180, 220050, 220050, 220051],
                         "value": [104.0, 60.0, 140.0, 90.0, 100.0, 0.0, 0.0]})
    maps = pd.DataFrame({"icustay_id": 1,
                         "time": [t, t, t, t, t + 60 * m, t + 61 * m, t + 90 * m, t],
                         "itemid": [220052, 220052, 220181, 220052, 220052, 220052, 220052,
                                    224322],
                         "value": [75.0, 142.0, 95.0, 55.0, 100.0, 142.0, 95.0, 150.0]})
    bad = hourly.map_outside_range(maps, refs)
    # 75 within its line's 104 / 60; 142 above it; the cuff's 95 within 140 / 90; the
    # arterial 55 below its own 60 (and the cuff's 90); 100 = its systolic alone: kept; 142
    # a minute after the systolic 100: another time, kept; 95 beside a line at 0 / 0: kept;
    # the IABP mean 150 has no device pressures: kept
    assert bad.tolist() == [False, True, False, True, False, False, False, False]
    # never deleted for falling below another device's diastolic: the cuff's 90 judges only
    # the cuff's mean
    only_cuff = refs[refs["itemid"].isin([220179, 220180])]
    assert not hourly.map_outside_range(maps.iloc[[3]], only_cuff).any()


def test_map_check_agrees_with_a_brute_force_loop():
    """Random MAPs and references of two devices on a coarse time grid (many ties and
    duplicates, integer values, missing diastolics, zeros, contradictory pairs): the
    vectorised check equals a row-by-row reading of its definition."""
    rng = np.random.default_rng(48)
    n = 400
    t = pd.Timestamp("2150-01-01 10:00") + pd.to_timedelta(rng.integers(0, 6, n), "min")
    dev = {"a": (220050, 220051, 220052), "c": (220179, 220180, 220181)}
    kind = rng.choice(["a", "c"], n)
    role = rng.integers(0, 3, n)
    item = np.array([dev[k][r] for k, r in zip(kind, role, strict=True)])
    ev = pd.DataFrame({"icustay_id": rng.integers(1, 3, n), "time": t, "itemid": item,
                       "value": rng.integers(0, 160, n).astype(float)})
    maps, refs = ev[role == 2].reset_index(drop=True), ev[role < 2].reset_index(drop=True)
    fast = hourly.map_outside_range(maps, refs)
    slow = []
    for _, q in maps.iterrows():
        k = "a" if q["itemid"] == 220052 else "c"
        same = refs[(refs["icustay_id"] == q["icustay_id"]) & (refs["time"] == q["time"])
                    & (refs["value"] > 0)]
        s = same.loc[same["itemid"] == dev[k][0], "value"]
        d = same.loc[same["itemid"] == dev[k][1], "value"]
        s = s.mean() if len(s) else np.nan
        d = d.mean() if len(d) else np.nan
        if np.isfinite(s) and np.isfinite(d) and s <= d:
            slow.append(False)  # a contradictory pair judges nothing
            continue
        slow.append(bool((np.isfinite(s) and q["value"] > s)
                         or (np.isfinite(d) and q["value"] < d)))
    assert fast.tolist() == slow
    assert 10 < sum(slow) < len(slow) - 10  # the draw exercises both outcomes


def test_every_blood_pressure_item_has_a_device():
    """A MeanBP item without a device would never be checked: bp_devices.csv lists every
    SysBP, MeanBP and DiaBP item of items.csv, with the role of its feature."""
    items = hourly.item_map()
    bp = items[items["feature"].isin(hourly.BP)].set_index("itemid")["feature"]
    dev = hourly.bp_devices().set_index("itemid")["role"].map(hourly.BP_ROLES)
    assert bp.index.isin(dev.index).all(), sorted(set(bp.index) - set(dev.index))
    assert (dev.reindex(bp.index) == bp).all()


def test_urine_irrigant_subtracted_within_its_charting_time():
    """GU irrigant in (227488) comes back in the urine charted with it (227489): subtracted
    per charting time, never below 0 mL; a charting time with irrigant only is no urine."""
    import duckdb

    t = pd.Timestamp("2150-01-01 10:00")
    rows = [(0.5, 227489, 100), (0.5, 227488, 300),  # 100 out, 300 in: 0, not -200
            (1.0, 227489, 500), (1.0, 227488, 200),  # 300
            (5.0, 227488, 1000),  # irrigant alone, block 1: no urine row (before: -1000)
            (9.0, 40055, 50), (9.0, 40055, 50)]  # duplicates count (two rows): 100
    out = pd.DataFrame({"ICUSTAY_ID": "1", "ITEMID": [str(r[1]) for r in rows],
                        "CHARTTIME": [str(t + pd.Timedelta(hours=r[0])) for r in rows],
                        "VALUE": [str(r[2]) for r in rows]})
    con = duckdb.connect()
    con.register("OUTPUTEVENTS", out)
    u = cohort._urine(con, [1], pd.Series([t], index=[1]), 3)
    assert u.to_dict() == {(1, 0): 300.0, (1, 2): 100.0}
    assert (u >= 0).all()


def test_own_earlier_weight_lower_median_and_age_bound(monkeypatch):
    """The patient's own earlier weight: the lower median of the last three plausible ones
    charted before the hour, at most 90 days old; never the mean of two."""
    t = pd.Timestamp("2150-01-01 10:00")
    d = pd.Timedelta(days=1)
    w = pd.DataFrame({"subject_id": [1, 1, 2, 3, 3, 3, 4, 5, 5],
                      "time": [t - 10 * d, t - 5 * d, t - 91 * d, t - 3 * d, t - 2 * d,
                               t - d, t, t - 100 * d, t - 2 * d],
                      "weight": [70.0, 234.0, 60.0, 64.6, 263.2, 65.0, 80.0, 50.0, 55.0]})
    monkeypatch.setattr(cohort, "patient_weights", lambda con, stays, subjects: w)
    stays = pd.DataFrame({"subject_id": [1, 2, 3, 4, 5]}, index=[11, 12, 13, 14, 15])
    held = pd.DataFrame({"weight": np.nan},
                        index=pd.MultiIndex.from_product([[11, 12, 13, 14, 15], [0]],
                                                         names=["icustay_id", "t"]))
    t0 = pd.Series(t, index=stays.index)
    got = cohort.own_earlier_weight(None, stays, held, t0).droplevel(1).to_dict()
    # 11: 70 and 234 give 70 (before: their mean, 152); 12: 91 days old, none; 13: 65 (the
    # median of 64.6, 263.2, 65); 14: charted at the hour's start, not before it; 15: the
    # 50 kg of 100 days before is out of the bound, 55 alone
    assert got == {11: 70.0, 13: 65.0, 15: 55.0}
