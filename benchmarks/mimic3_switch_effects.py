"""What each switch of ``Mimic3Options`` changes on a MIMIC-III folder, flipped alone.

For every switch, extracts the cohort with the project's defaults and with that one switch at
its alternative (``options.CHOICES``), and prints one Markdown table row per switch: the
CONSORT steps whose exclusions change (``n_stays`` after the step, change in brackets), the
final count with the stays that enter and leave, and on the stays in both cohorts the
trajectory cells that change, per column (values equal to 1e-9, missing equal to missing),
charted or held cells apart from 1-NN imputed ones (whose donors are the cohort's stays, so
they move whenever the cohort does).
This is the "demo effect" column of docs/how-to/mimic3.md's switch table.

``--preset-sofa``: instead, under the ``ai_clinician`` preset, the max SOFA of every stay with
an onset with each switch in ``--keys`` turned to the project's value alone, and with all of
them at once: the stays whose max SOFA changes, per switch (docs/how-to/mimic3.md, "The
rules as switches under the preset").

Run:  PYTHONPATH=src python benchmarks/mimic3_switch_effects.py MIMIC3_DIR
      [--anchor first_vitals] [--threads 2]
      [--preset-sofa [--keys venous_gas screens urine_irrigant tf_residual fio2_lab]]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify import schema
from twinfalsify.sources.mimic3 import extract_mimic3
from twinfalsify.sources.mimic3.options import CHOICES, PRESETS, Mimic3Options

RULE_KEYS = ("venous_gas", "screens", "urine_irrigant", "tf_residual", "fio2_lab")


def _imputed_flags(res) -> pd.DataFrame:
    """The trajectories' rows with True where the cell was imputed (1-NN), else False."""
    key = [schema.STAY_ID, "t"]
    flags = res.trajectories[key].copy()
    if res.imputed is not None:
        flags = flags.merge(res.imputed, on=key, how="left")
    return flags.set_index(key).fillna(False).astype(bool)


def changed_cells(a, b) -> tuple[dict[str, int], dict[str, int]]:
    """Cells that differ per column between two cohorts' trajectories on their common
    (stay, t) rows: (measured or held cells, cells imputed in either cohort). Imputed cells
    move with the donor pool, i.e. with the cohort."""
    key = [schema.STAY_ID, "t"]
    m = a.trajectories.merge(b.trajectories, on=key, suffixes=("_a", "_b"))
    fa, fb = _imputed_flags(a), _imputed_flags(b)
    idx = pd.MultiIndex.from_frame(m[key])
    measured, imputed = {}, {}
    for col in a.trajectories.columns:
        if col in key or f"{col}_b" not in m:
            continue
        x, y = m[f"{col}_a"], m[f"{col}_b"]
        if pd.api.types.is_numeric_dtype(x) and pd.api.types.is_numeric_dtype(y):
            xv, yv = x.to_numpy(float), y.to_numpy(float)
            same = np.isclose(xv, yv, rtol=0, atol=1e-9) | (np.isnan(xv) & np.isnan(yv))
        else:
            same = (x == y) | (x.isna() & y.isna())
        diff = ~np.asarray(same)
        was_imputed = np.zeros(len(m), bool)
        for f in (fa, fb):
            if col in f:
                was_imputed |= f[col].reindex(idx, fill_value=False).to_numpy()
        if (n := int((diff & ~was_imputed).sum())):
            measured[col] = n
        if (n := int((diff & was_imputed).sum())):
            imputed[col] = n
    return measured, imputed


def _counts(cells: dict[str, int]) -> str:
    return ", ".join(f"{col} {n}" for col, n in sorted(cells.items(), key=lambda kv: -kv[1]))


def effect(base, alt) -> str:
    """One cell of the table: what ``alt`` changes against ``base``."""
    c0 = base.consort.set_index("step")
    c1 = alt.consort.set_index("step")
    parts = [f"`{step}` {int(c1.at[step, 'n_stays'])} "
             f"({int(c1.at[step, 'n_stays']) - int(c0.at[step, 'n_stays']):+d})"
             for step in c0.index
             if step in c1.index and c0.at[step, "n_excluded"] != c1.at[step, "n_excluded"]]
    ids0 = set(base.trajectories[schema.STAY_ID])
    ids1 = set(alt.trajectories[schema.STAY_ID])
    if ids0 != ids1:
        parts.append(f"final {len(ids1)} ({len(ids1 - ids0)} stays in, "
                     f"{len(ids0 - ids1)} out)")
    else:
        parts.append(f"same {len(ids1)} stays")
    measured, imputed = changed_cells(base, alt)
    if measured:
        parts.append("charted or held cells changed on the stays in both: " + _counts(measured))
    if imputed:
        parts.append("imputed cells changed (the donor pool is the cohort): " + _counts(imputed))
    if not measured and not imputed and ids0 & ids1:
        parts.append("no cell of the stays in both changes")
    return "; ".join(parts)


def max_sofa_changes(base, alt) -> list[tuple[int, float, float]]:
    """(stay, max SOFA in ``base``, in ``alt``) for every stay whose max SOFA differs (a stay
    with an onset in only one of them: NaN on the other side)."""
    a = base.stays.set_index(schema.STAY_ID)["max_sofa"].astype(float)
    b = alt.stays.set_index(schema.STAY_ID)["max_sofa"].astype(float)
    both = a.index.union(b.index)
    a, b = a.reindex(both), b.reindex(both)
    diff = ~(np.isclose(a, b) | (a.isna() & b.isna()))
    return [(int(i), float(a[i]), float(b[i])) for i in both[diff]]


def preset_sofa(folder: Path, anchor: str, threads: int, keys) -> None:
    """Under the ai_clinician preset: the stays whose max SOFA changes when each of ``keys``
    takes the project's value alone, and all at once."""
    from dataclasses import replace
    preset = PRESETS["ai_clinician"]
    base = extract_mimic3(folder, anchor=anchor, threads=threads, options=preset)
    n_onset = int(base.stays["max_sofa"].notna().sum())
    print(f"preset: {n_onset} stays with an onset, final "
          f"{base.trajectories[schema.STAY_ID].nunique()}")
    print("| switch (project's value, alone) | stays whose max SOFA changes "
          "| stays (preset -> on) |")
    print("|---|---:|---|")
    runs = [(k, {k: CHOICES[k][0]}) for k in keys]
    runs.append(("all of them", {k: CHOICES[k][0] for k in keys}))
    for name, over in runs:
        alt = extract_mimic3(folder, anchor=anchor, threads=threads,
                             options=replace(preset, **over))
        ch = max_sofa_changes(base, alt)
        cells = ", ".join(f"{i} {x:g} -> {y:g}" for i, x, y in ch)
        print(f"| `{name}` | {len(ch)} | {cells} |", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder", type=Path)
    p.add_argument("--anchor", default="first_vitals")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--preset-sofa", action="store_true")
    p.add_argument("--keys", nargs="+", default=list(RULE_KEYS), choices=list(CHOICES))
    p.add_argument("--only", nargs="+", choices=list(CHOICES),
                   help="switch table rows of these switches only")
    a = p.parse_args()
    if a.preset_sofa:
        preset_sofa(a.folder, a.anchor, a.threads, a.keys)
        return
    base = extract_mimic3(a.folder, anchor=a.anchor, threads=a.threads)
    print(f"defaults: {base.trajectories[schema.STAY_ID].nunique()} stays")
    print("| key | alternative | effect of the alternative |")
    print("|---|---|---|")
    for key, (_default, *alternatives) in CHOICES.items():
        if a.only and key not in a.only:
            continue
        for value in alternatives:
            alt = extract_mimic3(a.folder, anchor=a.anchor, threads=a.threads,
                                 options=Mimic3Options(**{key: value}))
            print(f"| `{key}` | `{value}` | {effect(base, alt)} |", flush=True)


if __name__ == "__main__":
    main()
