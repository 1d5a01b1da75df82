"""Fake pulse.cdm.patient: sex enum, patient and patient configuration."""

from __future__ import annotations

from enum import Enum

from pulse.cdm.scalars import SEScalar


class eSex(Enum):
    Male = 0
    Female = 1


class SEPatient:
    def __init__(self) -> None:
        self._name = ""
        self._sex = eSex.Male
        self._s = {k: SEScalar() for k in ("age", "weight", "height", "hr", "sbp", "dbp", "rr")}

    def set_name(self, name: str) -> None:
        self._name = name

    def set_sex(self, sex: eSex) -> None:
        if not isinstance(sex, eSex):
            raise TypeError(f"sex must be eSex, got {sex!r}")
        self._sex = sex

    def get_sex(self) -> eSex:
        return self._sex

    def get_age(self) -> SEScalar:
        return self._s["age"]

    def get_weight(self) -> SEScalar:
        return self._s["weight"]

    def get_height(self) -> SEScalar:
        return self._s["height"]

    def get_heart_rate_baseline(self) -> SEScalar:
        return self._s["hr"]

    def get_systolic_arterial_pressure_baseline(self) -> SEScalar:
        return self._s["sbp"]

    def get_diastolic_arterial_pressure_baseline(self) -> SEScalar:
        return self._s["dbp"]

    def get_respiration_rate_baseline(self) -> SEScalar:
        return self._s["rr"]


class SEPatientConfiguration:
    def __init__(self) -> None:
        self._patient = SEPatient()
        self._data_root_dir = "./"
        self._conditions: list = []

    def get_patient(self) -> SEPatient:
        return self._patient

    def set_data_root_dir(self, d: str) -> None:
        self._data_root_dir = d
