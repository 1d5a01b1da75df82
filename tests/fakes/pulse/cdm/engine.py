"""Fake pulse.cdm.engine: data requests and the request manager."""

from __future__ import annotations

from enum import Enum

from pulse.cdm.scalars import SEScalarUnit


class eSerializationFormat(Enum):
    JSON = 0
    BINARY = 1


class SEDataRequest:
    """One requested value; ``column()`` names the recorded column that holds it."""

    def __init__(self, category: str, property_name: str, unit: SEScalarUnit | None = None,
                 compartment: str | None = None, substance: str | None = None):
        if unit is not None and not isinstance(unit, SEScalarUnit):
            raise TypeError(f"unit must be an SEScalarUnit, got {unit!r}")
        self.category, self.property_name, self.unit = category, property_name, unit
        self.compartment, self.substance = compartment, substance

    @staticmethod
    def create_physiology_request(property_name: str, unit: SEScalarUnit | None = None):
        return SEDataRequest("Physiology", property_name, unit)

    @staticmethod
    def create_patient_request(property_name: str, unit: SEScalarUnit | None = None):
        return SEDataRequest("Patient", property_name, unit)

    @staticmethod
    def create_substance_request(substance: str, property_name: str,
                                 unit: SEScalarUnit | None = None):
        return SEDataRequest("Substance", property_name, unit, substance=substance)

    @staticmethod
    def create_liquid_compartment_substance_request(compartment: str, substance: str,
                                                    property_name: str,
                                                    unit: SEScalarUnit | None = None):
        return SEDataRequest("LiquidCompartment", property_name, unit, compartment, substance)

    def column(self) -> str:
        """The recorded column for this request (naming of runs.csv / meta.json)."""
        suffix = {"": "", "mmHg": "mmHg", "1/min": "per_min", "degC": "degC", "mL": "mL",
                  "kg": "kg", "mg/dL": "mg_per_dL", "mmol/L": "mmol_per_L", "ug/L": "ug_per_L"}
        u = self.unit.get_string() if self.unit else ""
        if u not in suffix:
            raise LookupError(f"fake pulse: no recorded values in unit {u!r} ({self!r})")
        parts = [self.substance, self.compartment, self.property_name, suffix[u]]
        if self.category == "Substance":
            parts = [self.substance, self.property_name, suffix[u]]
        elif self.category in ("Physiology", "Patient"):
            parts = [self.property_name, suffix[u]]
        return "_".join(p for p in parts if p)

    def __repr__(self) -> str:
        return (f"SEDataRequest({self.category}, {self.compartment}, {self.substance}, "
                f"{self.property_name}, {self.unit})")


class SEDataRequestManager:
    def __init__(self, data_requests: list[SEDataRequest] | None = None):
        self._data_requests = list(data_requests or [])

    def set_data_requests(self, requests: list[SEDataRequest]) -> None:
        self._data_requests = list(requests)

    def get_data_requests(self) -> list[SEDataRequest]:
        return self._data_requests
