"""Fake pulse.cdm.patient_actions: the four actions the worker sends."""

from __future__ import annotations

from pulse.cdm.scalars import SEScalar


class SEAction:
    def __init__(self) -> None:
        self._comment = ""

    def set_comment(self, comment: str) -> None:
        self._comment = comment

    def get_comment(self) -> str:
        return self._comment

    def has_comment(self) -> bool:
        return bool(self._comment)


class SESubstanceCompoundInfusion(SEAction):
    def __init__(self) -> None:
        super().__init__()
        self._compound = ""
        self._rate, self._bag_volume = SEScalar(), SEScalar()

    def set_compound(self, compound: str) -> None:
        self._compound = compound

    def get_compound(self) -> str:
        return self._compound

    def get_rate(self) -> SEScalar:
        return self._rate

    def get_bag_volume(self) -> SEScalar:
        return self._bag_volume


class SESubstanceInfusion(SEAction):
    def __init__(self) -> None:
        super().__init__()
        self._substance = ""
        self._rate, self._concentration = SEScalar(), SEScalar()

    def set_substance(self, substance: str) -> None:
        self._substance = substance

    def get_substance(self) -> str:
        return self._substance

    def get_rate(self) -> SEScalar:
        return self._rate

    def get_concentration(self) -> SEScalar:
        return self._concentration


class SENutrition:
    def __init__(self) -> None:
        self._s = {k: SEScalar() for k in ("carbohydrate", "carbohydrate_digestion_rate", "fat",
                                           "fat_digestion_rate", "protein",
                                           "protein_digestion_rate", "calcium", "sodium",
                                           "water")}

    def __getattr__(self, name: str):
        if name.startswith("get_") and name[4:] in self.__dict__.get("_s", {}):
            return lambda: self._s[name[4:]]
        raise AttributeError(name)

    def values(self) -> dict[str, float]:
        return {k: s.get_value() for k, s in self._s.items() if s.is_valid()}


class SEConsumeNutrients(SEAction):
    def __init__(self) -> None:
        super().__init__()
        self._nutrition = SENutrition()
        self._nutrition_file = ""

    def get_nutrition(self) -> SENutrition:
        return self._nutrition

    def set_nutrition_file(self, f: str) -> None:
        self._nutrition_file = f


class SEUrinate(SEAction):
    pass
