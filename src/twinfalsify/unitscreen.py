"""Unit screen: name a feature whose values look like another unit than the contract's.

Two screens share the conversions below. ``against_reference`` compares a median with a
reference median of the same feature (a twin's hour 1 against the data's, or against its
X_0) and names the unit that would explain a ratio far from 1: "Glucose: twin median 6.1,
data 128 mg/dL: mmol/L?". ``against_typical`` compares a median with the range an ICU
cohort's median typically falls in (a table's glucose median of 7 is not mg/dL).
``swapped`` names two features of one unit whose medians each sit in the other's typical
range ("Sodium and Chloride swapped?"), and ``against_reference`` names a median within
the factor of its reference but outside the feature's typical range when the reference is
inside it (a twin's sodium of 104 against the data's 140).
"""

from __future__ import annotations

import math

from twinfalsify.schema import FEATURE_BY_NAME

# value in the other unit = a * (value in the contract's unit) + b; the slips seen in
# practice (SI labs, imperial vitals, per-second rates)
CONVERSIONS: dict[str, tuple[tuple[str, float, float], ...]] = {
    "weight": (("lb", 2.20462, 0.0), ("g", 1000.0, 0.0)),
    "HR": (("/s", 1 / 60, 0.0),),
    "RR": (("/s", 1 / 60, 0.0),),
    "SysBP": (("kPa", 1 / 7.50062, 0.0),),
    "DiaBP": (("kPa", 1 / 7.50062, 0.0),),
    "MeanBP": (("kPa", 1 / 7.50062, 0.0),),
    "Temp_C": (("degF", 1.8, 32.0), ("K", 1.0, 273.15)),
    "Potassium": (("mg/dL", 3.91, 0.0),),
    "Glucose": (("mmol/L", 1 / 18.016, 0.0), ("g/L", 0.01, 0.0)),
    "Calcium": (("mmol/L", 1 / 4.008, 0.0),),
    "paO2": (("kPa", 1 / 7.50062, 0.0),),
    "paCO2": (("kPa", 1 / 7.50062, 0.0),),
    "age": (("months", 12.0, 0.0), ("days", 365.25, 0.0)),
}
# Where the median of an adult ICU cohort falls, in the contract's units (wide on purpose:
# only a unit slip, not a sick cohort, should leave it). sex has no unit to slip.
TYPICAL: dict[str, tuple[float, float]] = {
    "age": (25, 90), "weight": (40, 150), "HR": (50, 140), "SysBP": (75, 180),
    "DiaBP": (30, 110), "MeanBP": (45, 125), "RR": (8, 40), "Temp_C": (33, 40),
    "Potassium": (2.5, 6.5), "Sodium": (120, 160), "Chloride": (85, 125),
    "Glucose": (60, 350), "Calcium": (5, 13), "HCO3": (10, 40), "paO2": (40, 400),
    "paCO2": (20, 80), "Arterial_pH": (7.0, 7.7),
}
FAR = 2.0  # a median ratio outside [1/FAR, FAR] is named
CLOSE = 1.3  # a converted reference within this factor of the value names that unit


def _close(a: float, b: float) -> bool:
    return a > 0 and b > 0 and max(a / b, b / a) <= CLOSE


def against_reference(feature: str, value: float, reference: float,
                      who: str = "twin", ref_name: str = "data") -> str:
    """'' when ``value`` is within a factor FAR of ``reference``; else the message naming
    the likely unit (or the ratio when no known unit explains it)."""
    if not (math.isfinite(value) and math.isfinite(reference)) or reference <= 0:
        return ""
    if value > 0 and 1 / FAR <= value / reference <= FAR:
        return ""
    unit = FEATURE_BY_NAME[feature].unit
    head = f"{feature}: {who} median {value:.3g}, {ref_name} {reference:.3g} {unit}"
    for other, a, b in CONVERSIONS.get(feature, ()):
        if _close(value, a * reference + b):
            return f"{head}: {other}?"
    ratio = value / reference
    return f"{head}: ratio {ratio:.3g}, not a unit this screen knows (scale or offset?)"


def outside_typical(feature: str, value: float, reference: float,
                    who: str = "twin", ref_name: str = "data") -> str:
    """'' unless ``value`` is outside the feature's typical range while ``reference`` is
    inside it: then the message (an error smaller than a unit slip, still a wrong value)."""
    if feature not in TYPICAL or not (math.isfinite(value) and math.isfinite(reference)):
        return ""
    lo, hi = TYPICAL[feature]
    if lo <= value <= hi or not lo <= reference <= hi:
        return ""
    unit = FEATURE_BY_NAME[feature].unit
    return (f"{feature}: {who} median {value:.3g}, {ref_name} {reference:.3g} {unit}, "
            f"outside the typical {lo:g}-{hi:g}")


def swapped(medians: dict[str, float], who: str = "twin") -> list[str]:
    """Pairs of features with the same unit whose medians each lie outside their own
    typical range and inside the other's: one message per pair, naming the swap."""
    out, seen = [], set()
    for a, va in medians.items():
        for b, vb in medians.items():
            if a == b or a not in TYPICAL or b not in TYPICAL or (b, a) in seen:
                continue
            if FEATURE_BY_NAME[a].unit != FEATURE_BY_NAME[b].unit:
                continue
            (alo, ahi), (blo, bhi) = TYPICAL[a], TYPICAL[b]
            if (not alo <= va <= ahi and blo <= va <= bhi
                    and not blo <= vb <= bhi and alo <= vb <= ahi):
                seen.add((a, b))
                unit = FEATURE_BY_NAME[a].unit
                out.append(f"{a} and {b} swapped? ({who} median {a} {va:.3g}, typical "
                           f"{alo:g}-{ahi:g}; {b} {vb:.3g}, typical {blo:g}-{bhi:g} {unit})")
    return out


def drifts(feature: str, by_hour: list[float], who: str = "twin") -> str:
    """'' unless the hour-1 median (``by_hour[0]``) is inside the feature's typical range
    and a later hour's is outside it, at least half the range's width away from hour 1:
    then the message naming the first such hour. The distance keeps a twin whose patients
    simply run high (a tachycardia drifting from 127 to 156 /min) from being called a
    drift; a state that grows hour by hour soon covers it."""
    if feature not in TYPICAL or not by_hour or not math.isfinite(by_hour[0]):
        return ""
    lo, hi = TYPICAL[feature]
    if not lo <= by_hour[0] <= hi:
        return ""
    for h, v in enumerate(by_hour[1:], start=2):
        if math.isfinite(v) and not lo <= v <= hi and abs(v - by_hour[0]) > (hi - lo) / 2:
            unit = FEATURE_BY_NAME[feature].unit
            return (f"{feature}: {who} median {by_hour[0]:.3g} at hour 1, {v:.3g} at hour "
                    f"{h} (typical {lo:g}-{hi:g} {unit}): drifts after hour 1?")
    return ""


def against_typical(feature: str, value: float, who: str = "data") -> str:
    """'' when ``value`` (a cohort median) is inside the feature's typical range; else the
    message, naming the unit that converts it into that range if one does."""
    if feature not in TYPICAL or not math.isfinite(value):
        return ""
    lo, hi = TYPICAL[feature]
    if lo <= value <= hi:
        return ""
    unit = FEATURE_BY_NAME[feature].unit
    head = f"{feature}: {who} median {value:.3g}, typical {lo:g}-{hi:g} {unit}"
    for other, a, b in CONVERSIONS.get(feature, ()):
        if lo <= (value - b) / a <= hi:
            return f"{head}: {other}?"
    return head
