"""MIMIC-III v1.4 source: sepsis-3 cohort (AI-Clinician criteria) as hourly trajectories."""

from .cohort import Mimic3Cohort, extract_mimic3
from .tables import ENV_VAR, resolve_mimic3_dir

__all__ = ["ENV_VAR", "Mimic3Cohort", "extract_mimic3", "resolve_mimic3_dir"]
