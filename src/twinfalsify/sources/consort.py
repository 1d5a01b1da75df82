"""The CONSORT table of a cohort extraction: stays left after each step, and how many it
excluded."""

from __future__ import annotations

import pandas as pd

COLUMNS = ["step", "description", "n_stays", "n_excluded"]


class Consort:
    """Rows appended step by step: ``add(step, description, ids)`` with the ids still in."""

    def __init__(self) -> None:
        self.rows: list[dict] = []

    def add(self, step: str, description: str, ids) -> None:
        n = len(ids)
        prev = self.rows[-1]["n_stays"] if self.rows else n
        self.rows.append({"step": step, "description": description, "n_stays": n,
                          "n_excluded": prev - n})

    def frame(self) -> pd.DataFrame:
        return pd.DataFrame(self.rows, columns=COLUMNS)
