"""The ``meds`` source: hourly trajectories from any dataset in the Medical Event Data
Standard (MEDS), through a code map (``codemap``: the preset ``mimic4`` built from the MIMIC
item tables, or a user's YAML map). ``dataset`` checks and opens the folder, ``cohort``
builds the trajectories and their CONSORT / audit / unit-screen tables, ``labels`` reads and
writes MEDS label tables, ``coverage`` compares the MIMIC-IV item map with a dataset.
docs/how-to/meds.md is the user's page.
"""

from twinfalsify.sources.meds.codemap import CodeMap, load_code_map, mimic4_code_map
from twinfalsify.sources.meds.cohort import MedsCohort, extract_meds
from twinfalsify.sources.meds.dataset import MedsDataset, open_dataset

__all__ = ["CodeMap", "MedsCohort", "MedsDataset", "extract_meds", "load_code_map",
           "mimic4_code_map", "open_dataset"]
