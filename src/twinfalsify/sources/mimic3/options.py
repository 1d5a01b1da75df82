"""The extraction's deliberate choices where the project departs from AI-Clinician, as named
switches (docs/how-to/mimic3.md, "Switches"), and the ``cohort_variant`` presets.

Each switch has the project's default and AI-Clinician's behaviour (Komorowski et al. 2018,
github.com/matthieukomorowski/AI_Clinician: AIClinician_sepsis3_def_160219.m,
AIClinician_mimic3_dataset_160219.m, AIClinician_Data_extract_MIMIC3_140219.ipynb):

- ``sofa``: ``project`` = CNS from the CareVue GCS total (198) and the MetaVision eye +
  verbal + motor components (220739, 223900, 223901) charted together, renal from creatinine
  only; ``ai_clinician`` = CNS from 198 and, where no GCS is charted, a GCS estimated from
  the MetaVision RASS (228096; Wesley et al., JAMA 2003), renal from creatinine and the
  urine output of the 4 h block (OUTPUTEVENTS, < 84 mL: 3 points, < 34 mL: 4).
- ``sofa_carry``: the SOFA of a 4 h block around the onset ``carry``s each component
  from the last earlier block that has it, for at most AI-Clinician's hold time of the
  component (AI-Clinician scores values sample-and-held that long: MAP 2 h, GCS 6 h, PaO2
  8 h, FiO2 12 h, labs 28 h; sample_and_hold.csv) or
  uses only values charted in the block (``none``: understates the maximum; kept to
  reproduce cohorts extracted that way).
- ``bp_items``: ``measured`` = MetaVision diastolic pressures 220051 (arterial) and 220180
  (non-invasive) are read; ``ai_clinician`` = they are not, so a MetaVision diastolic is
  only ever the completion formula (3 MAP - Sys) / 2.
- ``hold``: sample-and-hold into an hour without a value carries ``last_value`` (the last
  charted value, values of that instant averaged; AI-Clinician holds row by row, so the
  last value) or ``last_hour_mean`` (the mean of the last hour with values).
- ``rewritten``: MetaVision rows with STATUSDESCRIPTION 'Rewritten' are ``exclude``d for
  fluids and vasopressors (they are superseded orders: the rewritten order is charted again
  as its own row, so keeping both counts the same fluid twice); ``ai_clinician`` drops them
  for vasopressors only.
- ``gcs_intubated``: a verbal GCS charted as intubated (CareVue 723 'ET/Trach', MetaVision
  223900 'No Response-ETT') is ``not_assessable`` (the GCS total charted at that instant is
  not used) or ``verbal_1`` (the charted 1 counts; AI-Clinician reads 198 as charted).
- ``weight_missing``: an hour with no weight charted at or before its end is ``impute``d
  from other stays (1-NN, as the labs) or the stay is ``exclude``d.
- ``event_stay``: an antibiotic / culture without ICUSTAY_ID in the window of several stays
  of its admission goes to the ``nearest`` stay or the ``last`` one (AI-Clinician's loop).
- ``stays_per_patient``: ``all`` ICU stays of a patient that meet the criteria are kept
  (AI-Clinician, the paper), or only the patient's ``first`` ICU stay, if it meets them
  (one stay per patient: stays of one patient are not independent; the first ICU stay as
  the MIMIC Code Repository's first_icu_stay, not the first eligible one, so that a later
  stay never stands in for an ineligible first).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from twinfalsify.schema import ContractError

CHOICES: dict[str, tuple[str, ...]] = {
    "sofa": ("project", "ai_clinician"),
    "sofa_carry": ("carry", "none"),
    "bp_items": ("measured", "ai_clinician"),
    "hold": ("last_value", "last_hour_mean"),
    "rewritten": ("exclude", "ai_clinician"),
    "gcs_intubated": ("not_assessable", "verbal_1"),
    "weight_missing": ("impute", "exclude"),
    "event_stay": ("nearest", "last"),
    "stays_per_patient": ("all", "first"),
    "venous_gas": ("exclude", "keep"),
    "screens": ("exclude", "count"),
    "urine_irrigant": ("subtract", "ignore"),
    "tf_residual": ("exclude", "count"),
    "fio2_lab": ("read", "ignore"),
}
VARIANTS = ("project", "ai_clinician")


@dataclass(frozen=True)
class Mimic3Options:
    """One value per switch of ``CHOICES``; the defaults are the project's choices."""

    sofa: str = "project"
    sofa_carry: str = "carry"
    bp_items: str = "measured"
    hold: str = "last_value"
    rewritten: str = "exclude"
    gcs_intubated: str = "not_assessable"
    weight_missing: str = "impute"
    event_stay: str = "nearest"
    stays_per_patient: str = "all"
    venous_gas: str = "exclude"
    screens: str = "exclude"
    urine_irrigant: str = "subtract"
    tf_residual: str = "exclude"
    fio2_lab: str = "read"

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v not in CHOICES[f.name]:
                raise ContractError(f"config key source.mimic3.{f.name}: {v!r} is not one of "
                                    f"{', '.join(CHOICES[f.name])}")

    def as_dict(self) -> dict[str, str]:
        return asdict(self)


PRESETS: dict[str, Mimic3Options] = {
    "project": Mimic3Options(),
    # AI-Clinician's choice for every switch; hold: AI-Clinician's row-wise sample-and-hold
    # carries the last charted value, as the project's default does
    "ai_clinician": Mimic3Options(sofa="ai_clinician", sofa_carry="carry",
                                  bp_items="ai_clinician",
                                  hold="last_value", rewritten="ai_clinician",
                                  gcs_intubated="verbal_1", weight_missing="impute",
                                  event_stay="last", stays_per_patient="all",
                                  venous_gas="keep", screens="count", urine_irrigant="ignore",
                                  tf_residual="count", fio2_lab="ignore"),
}


def options_from_config(cfg: dict[str, Any] | None) -> Mimic3Options:
    """``cohort_variant`` preset (default ``project``) with any switch set in ``cfg``
    (source.mimic3) overriding it; ContractError naming the key for a bad value."""
    cfg = cfg or {}
    variant = cfg.get("cohort_variant") or "project"
    if variant not in PRESETS:
        raise ContractError(f"config key source.mimic3.cohort_variant: {variant!r} is not one "
                            f"of {', '.join(PRESETS)}")
    over = {k: cfg[k] for k in CHOICES if cfg.get(k) is not None}
    return replace(PRESETS[variant], **over)
