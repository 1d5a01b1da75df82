"""The code map of the ``meds`` source: which MEDS codes give the trajectory features and the
two actions, in which units, and how they are converted to the contract's units.

A map is a YAML file (docs/how-to/meds.md, "The code map") or the preset ``mimic4``, which
:func:`mimic4_code_map` builds from the MIMIC item tables the ``mimic3`` / ``mimic4``
sources read (``twinfalsify/data/mimic3/items.csv``, ``fluids.csv``, ``vasopressors.csv``):
one item map, two readers. :func:`load_code_map` checks every rule of a map and stops at the
first broken one with one line naming the file, the entry and the rule
(:class:`~twinfalsify.schema.ContractError`).

A code is matched exactly, or, when it ends in ``//*``, as a prefix: ``LAB//220045//*``
matches ``LAB//220045//bpm`` and ``LAB//220045//UNK``; the part after the last ``//`` is the
event's unit, which must be one of the entry's ``units`` (an event in another unit is not
read and is counted per code: the unit screen).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from twinfalsify import schema
from twinfalsify.schema import ContractError
from twinfalsify.sources.mimic3.itemmap import MIMIC4_RELEASES, releases_of
from twinfalsify.sources.mimic3.tables import data_table

PRESETS = ("mimic4",)
# the trajectory features a map can give (age and sex come from MEDS_BIRTH and the sex codes)
MAPPABLE: tuple[str, ...] = tuple(f for f in schema.FEATURES if f not in ("age", "sex"))
ACTIONS = ("fluid", "vasopressor")
# MIMIC-IV's unit strings per (feature, conversion): what the preset accepts in a code's unit
# part; "UNK" (no unit charted: the MIMIC item id fixes the unit) is accepted for every item
MIMIC4_UNITS: dict[tuple[str, str], tuple[str, ...]] = {
    ("HR", "none"): ("bpm",),
    **{(f, "none"): ("mmHg", "mm Hg") for f in ("SysBP", "DiaBP", "MeanBP", "paO2", "paCO2")},
    ("RR", "none"): ("insp/min", "bpm"),
    ("Temp_C", "none"): ("°C",),
    ("Temp_C", "F_to_C"): ("°F",),
    **{(f, "none"): ("mEq/L", "mmol/L") for f in ("Potassium", "Sodium", "Chloride", "HCO3")},
    ("Glucose", "none"): ("mg/dL",),
    ("Calcium", "none"): ("mg/dL",),
    ("Arterial_pH", "none"): ("units",),
    ("weight", "none"): ("kg",),
    ("weight", "lb_to_kg"): ("lbs", "lb"),
}
NO_UNIT = "UNK"


@dataclass(frozen=True)
class CodeMap:
    """A validated code map.

    ``features``: code, feature, conversion, units (tuple; empty = any unit);
    ``infusions``: item (int key), start, end, action, tonicity (fluids), drug;
    ``vaso_rules``: vasopressors.csv's columns (itemid = the infusion's item key, system
    ``mv``): norepinephrine-equivalent rate = rate * factor / weight_divisor by rate unit;
    ``stays``: admission / discharge code (prefix with ``//*``) and the stay-id column;
    ``sex``: code -> 1 (female) / 0 (male); ``specimen``: the blood-gas specimen code, the
    values that are not arterial and the features they void (or None); ``strict``: every code
    must occur in the dataset (user maps) rather than be reported as absent (preset)."""

    name: str
    features: pd.DataFrame
    infusions: pd.DataFrame
    vaso_rules: pd.DataFrame
    stays: dict[str, str | None]
    birth: str
    sex: dict[str, int]
    specimen: dict[str, Any] | None
    strict: bool
    source: str = ""
    notes: tuple[str, ...] = field(default=())

    def all_codes(self) -> list[str]:
        """Every code or ``//*`` pattern the map names."""
        codes = [*self.features["code"], *self.infusions["start"], *self.infusions["end"],
                 self.stays["admission"], self.stays["discharge"], self.birth, *self.sex]
        if self.specimen:
            codes.append(self.specimen["code"])
        return [c for c in dict.fromkeys(codes) if c]

    def to_yaml(self) -> str:
        """The map in the YAML format :func:`load_code_map` reads (a template for a user)."""
        inf = []
        for _, r in self.infusions.iterrows():
            e: dict[str, Any] = {"start": r["start"], "end": r["end"], "action": r["action"]}
            if r["action"] == "fluid":
                e["tonicity"] = float(r["tonicity"])
            else:
                e["drug"] = r["drug"]
                rules = self.vaso_rules[self.vaso_rules["itemid"] == r["item"]]
                e["rates"] = [{k: v for k, v in (
                    ("unit", rr["rateuom"]), ("factor", float(rr["factor"])),
                    ("weight_divisor", None if pd.isna(rr["weight_divisor"])
                     else float(rr["weight_divisor"])),
                    ("min_rate_exclusive", None if pd.isna(rr["min_rate_exclusive"])
                     else float(rr["min_rate_exclusive"]))) if v is not None}
                    for _, rr in rules.sort_values("priority", kind="stable").iterrows()]
            inf.append(e)
        doc = {"name": self.name,
               "features": [{"code": r["code"], "feature": r["feature"],
                             "conversion": r["conversion"], "units": list(r["units"])}
                            for _, r in self.features.iterrows()],
               "infusions": inf, "stays": dict(self.stays), "birth": self.birth,
               "sex": dict(self.sex)}
        if self.specimen:
            doc["specimen"] = {k: list(v) if isinstance(v, tuple) else v
                               for k, v in self.specimen.items()}
        return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=100)


def split_unit(code: str) -> tuple[str, str]:
    """``LAB//50912//mg/dL`` -> (``LAB//50912``, ``mg/dL``): the stem and the unit part."""
    stem, sep, unit = code.rpartition("//")
    return (stem, unit) if sep else (code, "")


def _mimic4_itemids(ids) -> list[int]:
    return [int(i) for i in ids if any(r in MIMIC4_RELEASES for r in releases_of(int(i)))]


def mimic4_code_map() -> CodeMap:
    """The preset ``mimic4``: the MIMIC-IV items of the MIMIC item tables as MEDS codes of the
    MIMIC-IV MEDS ETL (MEDS_transforms): chart and lab values ``LAB//{itemid}//{unit}``,
    infusions ``INFUSION_START//{itemid}`` (rate, rate unit in ``unit``) and
    ``INFUSION_END//{itemid}`` (amount), ICU stays ``ICU_ADMISSION//...`` /
    ``ICU_DISCHARGE//...`` with ``icustay_id``, the blood-gas specimen ``LAB//52033``."""
    items = data_table("items.csv")
    items = items[items["feature"].isin(MAPPABLE)]
    rows = []
    for _, r in items.iterrows():
        if not _mimic4_itemids([r["itemid"]]):
            continue
        units = MIMIC4_UNITS[(r["feature"], r["conversion"])]
        rows.append({"code": f"LAB//{int(r['itemid'])}//*", "feature": r["feature"],
                     "conversion": r["conversion"], "units": (*units, NO_UNIT)})
    feats = pd.DataFrame(rows)
    fl = data_table("fluids.csv")
    va = data_table("vasopressors.csv")
    va = va[va["system"] == "mv"]
    inf = [{"item": int(i), "start": f"INFUSION_START//{int(i)}",
            "end": f"INFUSION_END//{int(i)}", "action": "fluid", "tonicity": float(t),
            "drug": ""}
           for i, t in zip(fl["itemid"], fl["tonicity_factor"], strict=True)
           if _mimic4_itemids([i])]
    for i, drug in va[["itemid", "drug"]].drop_duplicates("itemid").itertuples(index=False):
        inf.append({"item": int(i), "start": f"INFUSION_START//{int(i)}",
                    "end": f"INFUSION_END//{int(i)}", "action": "vasopressor",
                    "tonicity": float("nan"), "drug": drug})
    rules = va[["itemid", "system", "drug", "rateuom", "min_rate_exclusive", "priority",
                "factor", "weight_divisor"]].reset_index(drop=True)
    spec = data_table("specimens.csv")
    spec = spec[spec["itemid"] == 52033]
    return CodeMap(
        name="mimic4", features=feats, infusions=pd.DataFrame(inf), vaso_rules=rules,
        stays={"admission": "ICU_ADMISSION//*", "discharge": "ICU_DISCHARGE//*",
               "id_column": "icustay_id"},
        birth="MEDS_BIRTH", sex={"GENDER//F": 1, "GENDER//M": 0},
        specimen={"code": "LAB//52033//*",
                  "not_arterial": tuple(spec.loc[spec["arterial"] == 0, "value"]),
                  "features": ("paO2", "paCO2", "Arterial_pH")},
        strict=False,
        source="preset mimic4: twinfalsify/data/mimic3/items.csv, fluids.csv, "
               "vasopressors.csv, specimens.csv (the mimic3 / mimic4 sources' item tables)")


def _err(where: str, msg: str) -> ContractError:
    return ContractError(f"{where}: {msg}")


def _keys(where: str, entry: Any, allowed: set[str], required: set[str]) -> dict:
    if not isinstance(entry, dict):
        raise _err(where, f"expected a mapping, got {type(entry).__name__} {entry!r}")
    unknown = set(entry) - allowed
    if unknown:
        raise _err(where, f"unknown key(s) {', '.join(sorted(map(str, unknown)))} (allowed: "
                          f"{', '.join(sorted(allowed))})")
    missing = required - set(entry)
    if missing:
        raise _err(where, f"missing key(s) {', '.join(sorted(missing))}")
    return entry


def _code(where: str, code: Any, pattern: bool = True) -> str:
    if not isinstance(code, str) or not code.strip():
        raise _err(where, f"a code is a non-empty string, got {code!r}")
    if "*" in code and not (pattern and code.endswith("//*") and code.count("*") == 1):
        raise _err(where, f"code {code!r}: the only wildcard is a final '//*' (a code prefix"
                          + (")" if pattern else "; not allowed here)"))
    return code


def _number(where: str, v: Any, *, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _err(where, f"expected a number, got {v!r}")
    if positive and not v > 0:
        raise _err(where, f"must be > 0, got {v!r}")
    return float(v)


def parse_code_map(doc: Any, where: str = "code map") -> CodeMap:
    """A :class:`CodeMap` from the YAML document ``doc`` (see the module doc); ContractError
    naming the entry at the first broken rule."""
    doc = _keys(where, doc, {"name", "features", "infusions", "stays", "birth", "sex",
                             "specimen"}, {"features", "infusions", "stays", "birth", "sex"})
    conversions = set(data_table("unit_conversions.csv")["conversion"])
    feats, seen = [], {}
    if not isinstance(doc["features"], list) or not doc["features"]:
        raise _err(f"{where}: features", "a non-empty list of {code, feature, units} entries")
    for i, e in enumerate(doc["features"]):
        w = f"{where}: features[{i}]"
        e = _keys(w, e, {"code", "feature", "conversion", "units"}, {"code", "feature"})
        code = _code(w, e["code"])
        if e["feature"] not in MAPPABLE:
            raise _err(w, f"feature {e['feature']!r} is not a trajectory feature a code can "
                          f"give (one of {', '.join(MAPPABLE)})")
        conv = e.get("conversion", "none")
        if conv not in conversions:
            raise _err(w, f"conversion {conv!r} unknown (one of {', '.join(sorted(conversions))})")
        units = e.get("units", [])
        if not isinstance(units, list) or not all(isinstance(u, str) for u in units):
            raise _err(w, f"units is a list of unit strings, got {units!r}")
        if code in seen:
            raise _err(w, f"code {code!r} listed twice (first as features[{seen[code]}])")
        seen[code] = i
        feats.append({"code": code, "feature": e["feature"], "conversion": conv,
                      "units": tuple(units)})
    inf, rules = [], []
    if not isinstance(doc["infusions"], list):
        raise _err(f"{where}: infusions", "a list of {start, end, action} entries")
    for i, e in enumerate(doc["infusions"]):
        w = f"{where}: infusions[{i}]"
        e = _keys(w, e, {"start", "end", "action", "tonicity", "drug", "rates"},
                  {"start", "end", "action"})
        start, end = _code(w, e["start"], False), _code(w, e["end"], False)
        if e["action"] not in ACTIONS:
            raise _err(w, f"action {e['action']!r} is not one of {', '.join(ACTIONS)}")
        for c in (start, end):
            if c in seen:
                raise _err(w, f"code {c!r} is also a feature code")
        item = i + 1
        if e["action"] == "fluid":
            if "rates" in e:
                raise _err(w, "rates are for vasopressors; a fluid's volume is its amount")
            ton = _number(f"{w}.tonicity", e.get("tonicity", 1.0), positive=True)
            inf.append({"item": item, "start": start, "end": end, "action": "fluid",
                        "tonicity": ton, "drug": ""})
            continue
        rates = e.get("rates")
        if not isinstance(rates, list) or not rates:
            raise _err(w, "a vasopressor needs rates: [{unit, factor, weight_divisor?}] (the "
                          "norepinephrine-equivalent ug/kg/min = rate * factor / divisor)")
        for j, r in enumerate(rates):
            wr = f"{w}.rates[{j}]"
            r = _keys(wr, r, {"unit", "factor", "weight_divisor", "min_rate_exclusive"},
                      {"unit", "factor"})
            if not isinstance(r["unit"], str):
                raise _err(wr, f"unit is a string, got {r['unit']!r}")
            rules.append({"itemid": item, "system": "mv", "drug": str(e.get("drug", "")),
                          "rateuom": r["unit"], "priority": j + 1,
                          "factor": _number(f"{wr}.factor", r["factor"], positive=True),
                          "weight_divisor": (float("nan") if r.get("weight_divisor") is None
                                             else _number(f"{wr}.weight_divisor",
                                                          r["weight_divisor"], positive=True)),
                          "min_rate_exclusive": (float("nan") if r.get("min_rate_exclusive")
                                                 is None else _number(
                                                     f"{wr}.min_rate_exclusive",
                                                     r["min_rate_exclusive"]))})
        inf.append({"item": item, "start": start, "end": end, "action": "vasopressor",
                    "tonicity": float("nan"), "drug": str(e.get("drug", ""))})
    acts = {r["action"] for r in inf}
    for a in ACTIONS:
        if a not in acts:
            raise _err(f"{where}: infusions", f"no {a} infusion: the trajectories need both "
                                              "actions (fluid, vasopressor)")
    missing = [f for f in MAPPABLE if f not in {r["feature"] for r in feats}]
    if missing:
        raise _err(f"{where}: features", f"no code gives {', '.join(missing)} (every "
                                         "trajectory feature needs one)")
    st = _keys(f"{where}: stays", doc["stays"], {"admission", "discharge", "id_column"},
               {"admission", "discharge"})
    stays = {"admission": _code(f"{where}: stays.admission", st["admission"]),
             "discharge": _code(f"{where}: stays.discharge", st["discharge"]),
             "id_column": st.get("id_column")}
    birth = _code(f"{where}: birth", doc["birth"], False)
    sex = doc["sex"]
    if not isinstance(sex, dict) or set(sex.values()) != {0, 1}:
        raise _err(f"{where}: sex", f"a mapping code -> 1 (female) / 0 (male) naming both, "
                                    f"got {sex!r}")
    spec = doc.get("specimen")
    if spec is not None:
        spec = _keys(f"{where}: specimen", spec, {"code", "not_arterial", "features"},
                     {"code", "not_arterial", "features"})
        bad = [f for f in spec["features"] if f not in MAPPABLE]
        if bad:
            raise _err(f"{where}: specimen.features", f"{bad} are not trajectory features")
        spec = {"code": _code(f"{where}: specimen.code", spec["code"]),
                "not_arterial": tuple(str(v) for v in spec["not_arterial"]),
                "features": tuple(spec["features"])}
    return CodeMap(name=str(doc.get("name") or "user"), features=pd.DataFrame(feats),
                   infusions=pd.DataFrame(inf),
                   vaso_rules=pd.DataFrame(rules, columns=[
                       "itemid", "system", "drug", "rateuom", "min_rate_exclusive",
                       "priority", "factor", "weight_divisor"]),
                   stays=stays, birth=birth, sex={str(k): int(v) for k, v in sex.items()},
                   specimen=spec, strict=True, source=where)


def load_code_map(spec: str | Path) -> CodeMap:
    """The preset named ``spec`` (``mimic4``) or the YAML map file at ``spec``."""
    if str(spec) in PRESETS:
        return mimic4_code_map()
    path = Path(spec)
    if not path.is_file():
        raise ContractError(f"source.meds.code_map: {spec} is neither a preset "
                            f"({', '.join(PRESETS)}) nor a file")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise ContractError(f"{path}: not YAML ({first})") from None
    return parse_code_map(doc, str(path))
