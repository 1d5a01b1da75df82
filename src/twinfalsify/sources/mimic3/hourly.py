"""Charted/lab events -> hourly feature blocks: unit conversion, outlier deletion,
block means, blood-pressure completion, sample-and-hold, and 1-NN imputation of labs.

All rules follow AI-Clinician (Komorowski et al. 2018; AIClinician_mimic3_dataset_160219.m)
unless stated; the tables are in twinfalsify/data/mimic3/.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from twinfalsify.schema import ContractError

from .tables import data_table

HOUR = pd.Timedelta(hours=1)
VITALS = ("HR", "SysBP", "DiaBP", "MeanBP", "RR", "Temp_C")
LABS = ("Potassium", "Sodium", "Chloride", "Glucose", "Calcium", "HCO3", "paO2", "paCO2",
        "Arterial_pH")


def item_map() -> pd.DataFrame:
    """items.csv joined with unit_conversions.csv: itemid, source, feature, offset, scale."""
    items = data_table("items.csv")
    conv = data_table("unit_conversions.csv")
    bad = set(items["conversion"]) - set(conv["conversion"])
    if bad:
        raise ContractError(f"items.csv: unknown conversion(s) {sorted(bad)} "
                            f"(unit_conversions.csv defines {sorted(conv['conversion'])})")
    m = items.merge(conv[["conversion", "offset", "scale"]], on="conversion")
    dup = m.duplicated(["itemid", "source"])
    if dup.any():
        raise ContractError(f"items.csv: itemid listed twice: {m.loc[dup, 'itemid'].tolist()}")
    return m


def convert_values(ev: pd.DataFrame) -> pd.DataFrame:
    """Apply unit conversions and AI-Clinician's temperature / FiO2 fixes.

    ``ev`` has icustay_id, time, itemid, source, value (raw VALUENUM). Returns icustay_id,
    time, itemid, feature, value in contract units. Conversion:
    value_out = (value + offset) * scale.
    Temperature: a Celsius-item value > 70 is taken as Fahrenheit, a Fahrenheit-item value
    in (25, 45) as Celsius (AI-Clinician's 'recorded in the wrong column' fix).
    FiO2: percent-item values < 1 are fractions (x 100).
    """
    m = item_map()
    e = ev.merge(m[["itemid", "source", "feature", "conversion", "offset", "scale"]],
                 on=["itemid", "source"], how="inner")
    v = e["value"].astype(float)
    conv = e["conversion"].to_numpy(object).copy()
    temp = e["feature"] == "Temp_C"
    conv[(temp & (conv == "none") & (v > 70)).to_numpy()] = "F_to_C"
    conv[(temp & (conv == "F_to_C") & (v > 25) & (v < 45)).to_numpy()] = "none"
    cm = data_table("unit_conversions.csv").set_index("conversion")
    off = cm.loc[conv, "offset"].to_numpy(float)
    sc = cm.loc[conv, "scale"].to_numpy(float)
    out = (v.to_numpy() + off) * sc
    fio2_pct = ((e["feature"] == "sofa_fio2") & (e["conversion"] == "none") & (v < 1)).to_numpy()
    out[fio2_pct] = v.to_numpy()[fio2_pct] * 100
    return pd.DataFrame({"icustay_id": e["icustay_id"].to_numpy(), "time": e["time"].to_numpy(),
                         "itemid": e["itemid"].to_numpy(), "feature": e["feature"].to_numpy(),
                         "value": out})


def delete_outliers(ev: pd.DataFrame) -> pd.DataFrame:
    """Drop values outside outlier_limits.csv (all rows for a feature apply, in turn)."""
    lim = data_table("outlier_limits.csv")
    keep = np.isfinite(ev["value"].to_numpy(float))
    for _, r in lim.iterrows():
        f = (ev["feature"] == r["feature"]).to_numpy()
        v = ev["value"].to_numpy(float)
        if pd.notna(r["lo"]):
            keep &= ~(f & (v < float(r["lo"])))
        if pd.notna(r["hi"]):
            keep &= ~(f & (v > float(r["hi"])))
    return ev[keep].reset_index(drop=True)


def block_means(ev: pd.DataFrame, intime: pd.Series, features: tuple[str, ...], t_max: int
                ) -> pd.DataFrame:
    """Mean of each feature's values in block t = [INTIME + t h, INTIME + (t+1) h).

    Returns a frame indexed by (icustay_id, t) for every stay in ``intime`` and t = 0..t_max,
    one column per feature, NaN where nothing was measured (AI-Clinician averages all
    values inside a time block, nanmean).
    """
    idx = pd.MultiIndex.from_product([intime.index, range(t_max + 1)], names=["icustay_id", "t"])
    e = ev[ev["feature"].isin(features)]
    e = e.assign(h=(e["time"].to_numpy() - intime.reindex(e["icustay_id"]).to_numpy()) / HOUR)
    e = e[(e["h"] >= 0) & (e["h"] < t_max + 1)]
    e = e.assign(t=np.floor(e["h"]).astype("int64"))
    wide = e.pivot_table(index=["icustay_id", "t"], columns="feature", values="value",
                         aggfunc="mean")
    return wide.reindex(index=idx, columns=list(features))


def within_limits(feature: str, v: pd.Series) -> pd.Series:
    """True where ``v`` passes every outlier_limits.csv row of ``feature``."""
    lim = data_table("outlier_limits.csv")
    ok = pd.Series(True, index=v.index)
    for _, r in lim[lim["feature"] == feature].iterrows():
        if pd.notna(r["lo"]):
            ok &= ~(v < float(r["lo"]))
        if pd.notna(r["hi"]):
            ok &= ~(v > float(r["hi"]))
    return ok


BP = ("SysBP", "MeanBP", "DiaBP")
BP_ROLES = {"sys": "SysBP", "dia": "DiaBP", "mean": "MeanBP"}


def bp_devices() -> pd.DataFrame:
    """bp_devices.csv: itemid -> device and role (sys, dia, mean); ContractError for an
    unknown role or an item listed twice."""
    t = data_table("bp_devices.csv").astype({"itemid": "int64"})
    bad = set(t["role"]) - set(BP_ROLES)
    if bad:
        raise ContractError(f"bp_devices.csv: unknown role(s) {sorted(bad)} "
                            f"(allowed: {', '.join(BP_ROLES)})")
    if t["itemid"].duplicated().any():
        raise ContractError("bp_devices.csv: itemid listed twice: "
                            f"{t.loc[t['itemid'].duplicated(), 'itemid'].tolist()}")
    return t


def map_outside_range(maps: pd.DataFrame, refs: pd.DataFrame) -> np.ndarray:
    """True for each charted mean pressure of ``maps`` (icustay_id, time, itemid, value)
    above the systolic or below the diastolic of the *same device* charted at the *same
    time* (``refs``: icustay_id, time, itemid, value; devices and roles from
    bp_devices.csv; several values of one device, role and instant averaged).

    A mean pressure lies between the diastolic and the systolic of the same waveform by
    definition; one outside them is an artefact of that measurement (a transducer being
    zeroed, 3 mmHg, or flushed). A reading of another device (the cuff beside the arterial
    line) or of another moment is a different measurement, which a real low MAP may well
    fall below: it is never a reference. A reference must be a pressure: > 0 mmHg (a line
    charted at zero, 0 / 0, says nothing of the mean charted beside it), and with both
    present, systolic > diastolic (otherwise the three readings contradict one another and
    which one is wrong cannot be told). Equal values are kept (a fully damped trace charts
    the three equal). A MAP of an item without a device, or without a usable same-device
    systolic or diastolic at its instant, passes. Only the MAP's own instant is read
    (causal). A MAP deleted here is completed from the systolic and diastolic of its instant
    (``complete_bp``), so a low pressure stays low: 41 below its own 67 / 47 becomes 53.7."""
    out = np.zeros(len(maps), dtype=bool)
    if not len(maps) or not len(refs):
        return out
    dev = bp_devices().set_index("itemid")
    r = refs.assign(device=refs["itemid"].map(dev["device"]),
                    role=refs["itemid"].map(dev["role"]))
    r = r[r["role"].isin(["sys", "dia"])]
    if r.empty:
        return out
    r = r[r["value"] > 0]
    ref = (r.groupby(["icustay_id", "time", "device", "role"])["value"].mean()
           .unstack("role").reindex(columns=["sys", "dia"]))
    ref = ref[~(ref["sys"] <= ref["dia"])]  # contradictory pair (NaN compares False): unusable
    q = pd.DataFrame({"icustay_id": maps["icustay_id"].to_numpy(),
                      "time": maps["time"].to_numpy(),
                      "device": maps["itemid"].map(dev["device"]).to_numpy()})
    hit = ref.reindex(pd.MultiIndex.from_frame(q))
    v = maps["value"].to_numpy(float)
    s, d = hit["sys"].to_numpy(float), hit["dia"].to_numpy(float)
    with np.errstate(invalid="ignore"):
        out = (np.isfinite(s) & (v > s)) | (np.isfinite(d) & (v < d))
    return out


def complete_bp(ev: pd.DataFrame) -> pd.DataFrame:
    """Complete blood pressure within each charting time (AI-Clinician, dataset code section
    'ESTIMATE MISSING BLOOD PRESSURE', applied per charted row before sample-and-hold).

    ``ev``: icustay_id, time, feature, value (converted, outliers deleted). At each
    (icustay_id, time) where exactly one of SysBP, MeanBP, DiaBP is missing and the other
    two are charted (values of one feature at that instant averaged), the missing one is
    added as an event of that time: MAP = (Sys + 2 Dia) / 3, Dia = (3 MAP - Sys) / 2,
    Sys = 3 MAP - 2 Dia (the standard MAP approximation). Readings of different times are
    never combined. A completion is rejected (no event) when the two given values are not
    ordered Sys > MAP > Dia (then neither is the result: the formulas keep the order of
    their inputs) or when it falls outside the feature's outlier limits, as a charted value
    would be deleted. Returns ``ev`` with the completed events appended (they are held
    forward by ``sample_and_hold`` like charted ones)."""
    bp = ev[ev["feature"].isin(BP)]
    if bp.empty:
        return ev
    w = bp.pivot_table(index=["icustay_id", "time"], columns="feature", values="value",
                       aggfunc="mean").reindex(columns=list(BP))
    s, m, d = w["SysBP"], w["MeanBP"], w["DiaBP"]
    new = []
    for feat, need, v, ordered in (
            ("MeanBP", m.isna() & s.notna() & d.notna(), (s + 2 * d) / 3, s > d),
            ("DiaBP", d.isna() & s.notna() & m.notna(), (3 * m - s) / 2, s > m),
            ("SysBP", s.isna() & m.notna() & d.notna(), 3 * m - 2 * d, m > d)):
        ok = need & ordered & within_limits(feat, v)
        if ok.any():
            new.append(pd.DataFrame({"icustay_id": w.index.get_level_values(0)[ok],
                                     "time": w.index.get_level_values(1)[ok],
                                     "feature": feat, "value": v[ok].to_numpy()}))
    if not new:
        return ev
    return pd.concat([ev, *new], ignore_index=True)


HOLDS = ("last_value", "last_hour_mean")


def sample_and_hold(blocks: pd.DataFrame, ev: pd.DataFrame, intime: pd.Series,
                    how: str = "last_value") -> pd.DataFrame:
    """Fill a missing block value from measurements taken before the block start
    (INTIME + t h) if the last one is at most hold_hours old (sample_and_hold.csv).
    Measurements before ICU admission count (labs are drawn on the ward / in the ED).

    ``how="last_value"`` (AI-Clinician SAH.m: a value is carried forward for hold_hours
    after it was taken): the last value; several values taken at that same instant are
    averaged. ``how="last_hour_mean"``: the mean of the values of the last whole hour
    [INTIME + k h, INTIME + (k + 1) h) before the block that has any, held for hold_hours
    after the last of them. Either way only values charted before the block start are used.
    """
    if how not in HOLDS:
        raise ContractError(f"sample_and_hold: how must be one of {HOLDS}, got {how!r}")
    hold = data_table("sample_and_hold.csv").set_index("feature")["hold_hours"]
    out = blocks.copy()
    keys = out.index.to_frame(index=False)
    start = intime.reindex(keys["icustay_id"]).to_numpy() + keys["t"].to_numpy() * HOUR
    for feat in out.columns:
        if feat not in hold.index:
            continue
        miss = out[feat].isna().to_numpy()
        if not miss.any():
            continue
        e = ev[ev["feature"] == feat]
        if e.empty:
            continue
        if how == "last_hour_mean":
            # hour buckets on INTIME's grid (negative before admission); a bucket ending
            # after a block start never precedes it, since blocks share the grid
            k = np.floor((e["time"].to_numpy() - intime.reindex(e["icustay_id"]).to_numpy())
                         / HOUR).astype("int64")
            e = (e.assign(k=k).groupby(["icustay_id", "k"], as_index=False)
                 .agg(time=("time", "max"), value=("value", "mean")))
        else:
            # values charted at the same instant (e.g. a weight in kg and in lb) are
            # averaged, as within a block; otherwise the result would depend on row order
            e = e.groupby(["icustay_id", "time"], as_index=False)["value"].mean()
        e = e.sort_values("time", kind="stable")
        q = pd.DataFrame({"icustay_id": keys["icustay_id"].to_numpy()[miss],
                          "start": start[miss], "row": np.flatnonzero(miss)})
        q = q.sort_values("start")
        e = e.rename(columns={"time": "start"})[["icustay_id", "start", "value"]]
        # strictly before the block start: allow_exact_matches=False
        hit = pd.merge_asof(q, e.assign(taken=e["start"]), on="start", by="icustay_id",
                            allow_exact_matches=False, direction="backward")
        ok = hit["value"].notna() & ((hit["start"] - hit["taken"]) <= hold[feat] * HOUR)
        col = out[feat].to_numpy(copy=True)
        col[hit.loc[ok, "row"].to_numpy()] = hit.loc[ok, "value"].to_numpy()
        out[feat] = col
    return out


def knn_impute(x: np.ndarray, groups: np.ndarray | None = None,
               times: np.ndarray | None = None, chunk: int = 10_000,
               batch: int = 512) -> np.ndarray:
    """1-nearest-neighbour imputation (AI-Clinician: MATLAB knnimpute(., 1, 'seuclidean')
    on chunks of 10,000 records), causal: donors are rows of *other* groups at the same or
    an earlier hour.

    Row i belongs to group g = groups[i] (the extraction passes the patient, SUBJECT_ID, so
    no stay of the same patient is a donor) at hour t = times[i]. Its eligible donors for a
    missing column j are the rows k with groups[k] != g, times[k] <= t and column j
    observed; the donor minimises the mean over commonly observed columns of
    ((x_i - x_k) / sd_{g,t})^2 (standardised Euclidean distance; averaging over the shared
    columns keeps rows with different missingness comparable); ties go to the first row.
    sd_{g,t} is the column standard deviation over the eligible rows (other stays, hours
    <= t). So the imputed values of hour t depend only on row i and on rows of other stays
    at hours <= t, never on anything charted after the end of hour t, neither in the stay
    itself (AI-Clinician imputes over all records, so a stay's later hours are its usual
    donors) nor in the other stays. ``groups=None``: each row its own stay; ``times=None``:
    all rows at the same hour (plain 1-NN with a leave-one-out scale).
    Rows are processed in chunks of ``chunk`` rows, donors searched within the chunk.
    Cells without any eligible donor stay NaN.

    Cost: linear in the number of rows (chunk-bounded). Within a chunk, distances of a batch
    of rows to all rows come from matrix products, with x zero-filled, O the observed mask
    and w_i = 1 / sd_{g(i),t(i)}^2: sum_shared w (x_i - x_k)^2 = (w O_i x_i^2) . O_k
    - 2 (w O_i x_i) . x_k + (w O_i) . (O_k x_k^2), n_shared = O_i . O_k. The donor is then
    confirmed by the direct formula on every row within 1e-6 (1 + d_min) of the
    approximate minimum (the expansion's rounding error is ~1e-13 of the squares), so the
    result equals the direct definition, ties included (``_knn_impute_direct``).
    """
    x = np.asarray(x, dtype=float)
    out = x.copy()
    g, tt = _knn_keys(x, groups, times)
    inv_var = 1.0 / _knn_scale(x, g, tt) ** 2  # per row: 1 / sd_{g(i),t(i)}^2
    for c0 in range(0, len(x), chunk):
        xc = x[c0:c0 + chunk]
        gc, tc = g[c0:c0 + chunk], tt[c0:c0 + chunk]
        obs = np.isfinite(xc)
        z = np.where(obs, xc, 0.0)
        z2, of = z * z, obs.astype(float)
        rows = np.flatnonzero(~obs.all(axis=1))
        for b0 in range(0, len(rows), batch):
            r = rows[b0:b0 + batch]
            w = inv_var[c0 + r] * of[r]
            num = (w * z2[r]) @ of.T - 2.0 * ((w * z[r]) @ z.T) + w @ z2.T
            n = of[r] @ of.T
            approx = np.where(n > 0, num / np.maximum(n, 1.0), np.inf)
            # never a donor from its own stay or from a later hour
            approx[(gc[r][:, None] == gc[None, :]) | (tc[None, :] > tc[r][:, None])] = np.inf
            for j in np.flatnonzero(~obs[r].all(axis=0)):
                need = np.flatnonzero(~obs[r, j])
                cand = np.where(obs[:, j], approx[need], np.inf)
                dmin = cand.min(axis=1)
                near = cand <= (dmin + 1e-6 * (1.0 + dmin))[:, None]
                k = np.argmin(cand, axis=1)
                for p in np.flatnonzero(np.isfinite(dmin) & (near.sum(axis=1) > 1)):
                    c = np.flatnonzero(near[p])  # near-ties: decide by the direct formula
                    i = r[need[p]]
                    k[p] = c[int(np.argmin(_direct_dist(xc, obs, i, c, inv_var[c0 + i])))]
                ok = np.isfinite(dmin)
                out[c0 + r[need[ok]], j] = x[c0 + k[ok], j]
    return out


def _knn_keys(x: np.ndarray, groups, times) -> tuple[np.ndarray, np.ndarray]:
    g = np.arange(len(x)) if groups is None else np.asarray(groups)
    t = np.zeros(len(x), dtype="int64") if times is None else np.asarray(times)
    if len(g) != len(x) or len(t) != len(x):
        raise ValueError("knn_impute: groups and times need one entry per row")
    return g, t


def _knn_scale(x: np.ndarray, groups: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Per row i, the column standard deviations (ddof 0, observed values) over the rows
    of every group but groups[i] with times <= times[i]; 1 where undefined or 0.

    Sums per (group, hour) are accumulated over hours <= t, then summed over the other
    groups as a prefix sum over the groups before g plus a suffix sum over those after g,
    so not one rounding depends on group g's values or on any row of a later hour."""
    gu, gi = np.unique(groups, return_inverse=True)
    tu, ti = np.unique(times, return_inverse=True)
    obs = np.isfinite(x)
    z = np.where(obs, x, 0.0)
    shape = (len(gu), len(tu), x.shape[1])
    s = [np.zeros(shape) for _ in range(3)]
    for acc, v in zip(s, (obs.astype(float), z, z * z), strict=True):
        np.add.at(acc, (gi, ti), v)

    def others(a: np.ndarray) -> np.ndarray:
        a = np.cumsum(a, axis=1)  # hours <= t
        zero = np.zeros_like(a[:1])
        pre = np.concatenate([zero, np.cumsum(a, axis=0)[:-1]])
        suf = np.concatenate([np.cumsum(a[::-1], axis=0)[::-1][1:], zero])
        return pre + suf

    n, t1, t2 = (others(a) for a in s)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = t1 / n
        var = np.maximum(t2 / n - mean * mean, 0.0)
    sd = np.sqrt(var)
    sd[~np.isfinite(sd) | (sd <= 1e-12 * (1.0 + np.abs(np.nan_to_num(mean))))] = 1.0
    return sd[gi, ti]


def _direct_dist(xc: np.ndarray, obs: np.ndarray, i: int, rows: np.ndarray,
                 inv_var: np.ndarray) -> np.ndarray:
    """Mean of inv_var * (x_i - x_k)^2 of row i to ``rows`` over shared columns."""
    shared = obs[rows] & obs[i]
    diff = np.where(shared, xc[rows] - np.where(obs[i], xc[i], 0.0), 0.0)
    n = shared.sum(axis=1)
    return np.where(n > 0, (diff ** 2 * inv_var).sum(axis=1) / np.maximum(n, 1), np.inf)


def _knn_impute_direct(x: np.ndarray, groups: np.ndarray | None = None,
                       times: np.ndarray | None = None, chunk: int = 10_000) -> np.ndarray:
    """``knn_impute`` by the definition, one row at a time (O(chunk) numpy work per row)."""
    x = np.asarray(x, dtype=float)
    out = x.copy()
    g, tt = _knn_keys(x, groups, times)
    inv_var = 1.0 / _knn_scale(x, g, tt) ** 2
    for c0 in range(0, len(x), chunk):
        xc = x[c0:c0 + chunk]
        gc, tc = g[c0:c0 + chunk], tt[c0:c0 + chunk]
        obs = np.isfinite(xc)
        every = np.arange(len(xc))
        for i in np.flatnonzero(~obs.all(axis=1)):
            dist = _direct_dist(xc, obs, i, every, inv_var[c0 + i])
            dist[(gc == gc[i]) | (tc > tc[i])] = np.inf
            for j in np.flatnonzero(~obs[i]):
                cand = np.where(obs[:, j], dist, np.inf)
                k = int(np.argmin(cand))
                if np.isfinite(cand[k]):
                    out[c0 + i, j] = x[c0 + k, j]
    return out
