"""Fake pulse.cdm.scalars: unit objects carrying Pulse's unit strings, and scalars."""

from __future__ import annotations


class SEScalarUnit:
    def __init__(self, string: str):
        self._string = string

    def get_string(self) -> str:
        return self._string

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SEScalarUnit) and other._string == self._string

    def __hash__(self) -> int:
        return hash(self._string)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._string!r})"


class TimeUnit(SEScalarUnit):
    pass


class MassUnit(SEScalarUnit):
    pass


class LengthUnit(SEScalarUnit):
    pass


class FrequencyUnit(SEScalarUnit):
    pass


class PressureUnit(SEScalarUnit):
    pass


class TemperatureUnit(SEScalarUnit):
    pass


class VolumeUnit(SEScalarUnit):
    pass


class VolumePerTimeUnit(SEScalarUnit):
    pass


class MassPerVolumeUnit(SEScalarUnit):
    pass


class MassPerTimeUnit(SEScalarUnit):
    pass


TimeUnit.s, TimeUnit.min, TimeUnit.hr, TimeUnit.yr = (
    TimeUnit("s"), TimeUnit("min"), TimeUnit("hr"), TimeUnit("yr"))
MassUnit.g, MassUnit.ug, MassUnit.mg, MassUnit.kg = (
    MassUnit("g"), MassUnit("ug"), MassUnit("mg"), MassUnit("kg"))
LengthUnit.m, LengthUnit.cm, LengthUnit.inch, LengthUnit.ft = (
    LengthUnit("m"), LengthUnit("cm"), LengthUnit("in"), LengthUnit("ft"))
FrequencyUnit.Per_min, FrequencyUnit.Per_s, FrequencyUnit.Hz = (
    FrequencyUnit("1/min"), FrequencyUnit("1/s"), FrequencyUnit("Hz"))
PressureUnit.mmHg, PressureUnit.cmH2O, PressureUnit.Pa = (
    PressureUnit("mmHg"), PressureUnit("cmH2O"), PressureUnit("Pa"))
TemperatureUnit.C, TemperatureUnit.F, TemperatureUnit.K = (
    TemperatureUnit("degC"), TemperatureUnit("degF"), TemperatureUnit("K"))
VolumeUnit.L, VolumeUnit.mL, VolumeUnit.uL = VolumeUnit("L"), VolumeUnit("mL"), VolumeUnit("uL")
VolumePerTimeUnit.mL_Per_min, VolumePerTimeUnit.mL_Per_hr, VolumePerTimeUnit.L_Per_min = (
    VolumePerTimeUnit("mL/min"), VolumePerTimeUnit("mL/hr"), VolumePerTimeUnit("L/min"))
MassPerVolumeUnit.ug_Per_mL, MassPerVolumeUnit.mg_Per_dL, MassPerVolumeUnit.ug_Per_L = (
    MassPerVolumeUnit("ug/mL"), MassPerVolumeUnit("mg/dL"), MassPerVolumeUnit("ug/L"))
MassPerVolumeUnit.g_Per_L = MassPerVolumeUnit("g/L")
MassPerTimeUnit.g_Per_min = MassPerTimeUnit("g/min")


class SEScalar:
    """A value with a unit (the fake keeps exactly what was set)."""

    def __init__(self) -> None:
        self._value: float | None = None
        self._unit: SEScalarUnit | None = None

    def set_value(self, value: float, unit: SEScalarUnit | None = None) -> None:
        if unit is not None and not isinstance(unit, SEScalarUnit):
            raise TypeError(f"unit must be an SEScalarUnit, got {unit!r}")
        self._value, self._unit = float(value), unit

    def get_value(self, unit: SEScalarUnit | None = None) -> float:
        if self._value is None:
            raise ValueError("scalar has no value")
        if unit is not None and unit != self._unit:
            raise NotImplementedError(
                f"fake pulse does not convert units ({self._unit} -> {unit})")
        return self._value

    def unit_string(self) -> str:
        return self._unit.get_string() if self._unit else ""

    def is_valid(self) -> bool:
        return self._value is not None
