"""The replay twin ``recorded-pulse``: recorded real Pulse 4.2 runs served over protocol v1.

    python -m twinfalsify.pulse.replay [--data DIR]

A study recording (``answers-*.jsonl`` from ``python -m twinfalsify.runs.record`` around
the real worker, e.g. tests/fixtures/pulse-demo) is served by ``runs.replay.ReplayTwin``:
the worker's answers exactly as the runner received them. Otherwise
DIR holds ``patients.csv`` and ``runs.csv`` as recorded from a real Pulse 4.2
engine (README of the pulse-reference data). A ``simulate`` request is answered
from the recording when its X_0 init features (schema.INIT_FEATURES) equal a
recorded patient's baselines and its doses for hours 1..t equal the first t hours
of a recorded sequence; the features are converted with the same tables as the
Pulse worker (conversions.csv; age and sex echo X_0) and checked against
physiological_limits.csv (the recorded P3-S4 hour 4 is a collapsed state ->
"irreversible"). A recorded out-of-range patient gets the engine's recorded
answer ("init_failed" with its [ERROR] text). Anything else is a clear "error"
naming what the recording holds: this twin never simulates and never clamps.
Recorded patients' heights (not a study feature) are those of patients.csv.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from twinfalsify.pulse.units import (
    load_conversions,
    load_physiological_limits,
    physiological_violation,
    pulse_conversions,
    to_study_features,
)
from twinfalsify.runs import protocol
from twinfalsify.runs.replay import ReplayTwin, refuse
from twinfalsify.schema import FEATURE_TABLE, INIT_FEATURES, T_MAX, ContractError

NAME = "recorded-pulse"
DATA_ENV = "TWINFALSIFY_PULSE_REFERENCE"
# patients.csv column for each init feature (sex is 'Male'/'Female' there).
PATIENT_COLUMNS = {"age": "age_yr", "weight": "weight_kg", "HR": "HR_baseline_per_min",
                   "SysBP": "SBP_baseline_mmHg", "DiaBP": "DBP_baseline_mmHg",
                   "RR": "RR_baseline_per_min"}


CHECKOUT = Path(__file__).resolve().parents[3]


def default_data_dir() -> Path:
    """$TWINFALSIFY_PULSE_REFERENCE, else the checkout's tests/fixtures/pulse-reference."""
    if os.environ.get(DATA_ENV):
        return Path(os.environ[DATA_ENV])
    return CHECKOUT / "tests" / "fixtures" / "pulse-reference"


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


class RecordedPulse:
    """Serves recorded Pulse runs; ``simulate(request)`` returns the result fields."""

    def __init__(self, data_dir: str | Path | None = None):
        self.data_dir = Path(data_dir) if data_dir else default_data_dir()
        pfile, rfile = self.data_dir / "patients.csv", self.data_dir / "runs.csv"
        for f in (pfile, rfile):
            if not f.exists():
                raise ContractError(f"{f}: recorded Pulse data not found (pass --data DIR or set "
                                    f"{DATA_ENV})")
        self.patients = pd.read_csv(pfile)
        self.runs = pd.read_csv(rfile)
        need = ["patient_id", "kind", "sex", "init_ok", "init_message", *PATIENT_COLUMNS.values()]
        miss = [c for c in need if c not in self.patients.columns]
        if miss:
            raise ContractError(f"{pfile}: missing column(s) {', '.join(miss)}")
        self.conversions = load_conversions()
        self.limits = load_physiological_limits()
        cols = [c.recorded_column for c in pulse_conversions(self.conversions)]
        need = ["run_id", "patient_id", "hour", "iv_ml_h", "vaso_ug_kg_min", "status", *cols]
        miss = [c for c in need if c not in self.runs.columns]
        if miss:
            raise ContractError(f"{rfile}: missing column(s) {', '.join(miss)}")
        self.version = "4.2.0 (recorded)"
        meta = self.data_dir / "meta.json"
        if meta.exists():
            import json

            self.version = f"{json.loads(meta.read_text()).get('pulse_version', '?')} (recorded)"

    def hello(self) -> dict[str, Any]:
        return {"name": NAME, "version": self.version,
                "features": [{"name": f.name, "unit": f.unit} for f in FEATURE_TABLE],
                "capabilities": {"save_restore": False, "max_hours": T_MAX}}

    def _patient(self, x0: dict) -> pd.Series | None:
        for _, p in self.patients.iterrows():
            if float(x0["sex"]) != (1.0 if p["sex"] == "Female" else 0.0):
                continue
            if all(_close(float(x0[f]), float(p[c])) for f, c in PATIENT_COLUMNS.items()):
                return p
        return None

    def holdings(self) -> str:
        pats = ", ".join(self.patients["patient_id"])
        seqs = []
        for run_id, g in self.runs[self.runs["hour"] > 0].groupby("run_id", sort=True):
            d = ",".join(f"({r.iv_ml_h:g},{r.vaso_ug_kg_min:g})"
                         for r in g.sort_values("hour").itertuples())
            seqs.append(f"{run_id}: {d}")
        return f"patients {pats}; runs {'; '.join(seqs)}"

    def simulate(self, request: dict[str, Any]) -> dict[str, Any]:
        x0, hours, doses = request.get("x0"), request.get("hours"), request.get("doses")
        if not isinstance(x0, dict) or any(f not in x0 for f in INIT_FEATURES):
            raise ContractError(f"simulate request: x0 needs {', '.join(INIT_FEATURES)}")
        if not isinstance(hours, int) or not 1 <= hours <= T_MAX:
            raise ContractError(f"simulate request: hours = {hours!r} must be in 1..{T_MAX}")
        if not isinstance(doses, list) or len(doses) < hours:
            raise ContractError(f"simulate request: doses must list >= {hours} pairs")
        doses = [(float(a), float(b)) for a, b in doses[:hours]]
        p = self._patient(x0)
        if p is None:
            return {"status": "error", "hours": [], "clamped": {},
                    "message": f"{NAME} holds no recorded patient with these X_0 baselines "
                               f"({ {f: x0[f] for f in INIT_FEATURES} }); it holds "
                               + self.holdings()}
        if not bool(p["init_ok"]):
            return {"status": "init_failed", "hours": [], "clamped": {},
                    "message": f"recorded Pulse 4.2 answer for {p['patient_id']}: "
                               f"{p['init_message']}"}
        run = self._run(p["patient_id"], doses)
        if run is None:
            return {"status": "error", "hours": [], "clamped": {},
                    "message": f"{NAME} holds no recorded run of {p['patient_id']} with doses "
                               f"{doses}; it holds " + self.holdings()}
        rows = run.set_index("hour")
        out: list[dict[str, float]] = []
        cols = [c.recorded_column for c in pulse_conversions(self.conversions)]
        for h in range(1, hours + 1):
            r = rows.loc[h]
            if r["status"] != "ok":
                return {"status": r["status"], "hours": out, "clamped": {},
                        "message": f"recorded run {r['run_id']} hour {h}: {r.get('note', '')}"}
            feats = to_study_features({c: float(r[c]) for c in cols}, x0, self.conversions)
            bad = physiological_violation(feats, self.limits)
            if bad:
                return {"status": "irreversible", "hours": out, "clamped": {},
                        "message": f"recorded run {r['run_id']}: collapsed state at the end of "
                                   f"hour {h} although Pulse reported success: {bad}"}
            out.append(feats)
        return {"status": "ok", "message": f"recorded run {run['run_id'].iloc[0]}",
                "hours": out, "clamped": {}}

    def _run(self, pid: str, doses: list[tuple[float, float]]) -> pd.DataFrame | None:
        for _run_id, g in self.runs[self.runs["patient_id"] == pid].groupby("run_id", sort=True):
            g = g.set_index("hour", drop=False)
            if all(h in g.index and _close(g.at[h, "iv_ml_h"], d[0])
                   and _close(g.at[h, "vaso_ug_kg_min"], d[1])
                   for h, d in enumerate(doses, start=1)):
                return g.reset_index(drop=True)
        return None


def resolve_data_dir(data: str | None) -> Path:
    """--data as given when it exists; a relative path that does not exist here is read
    relative to the checkout (Snakemake may run the twin from another working folder)."""
    if not data:
        return default_data_dir()
    path = Path(data)
    if path.is_absolute() or path.exists():
        return path
    in_checkout = CHECKOUT / path
    return in_checkout if in_checkout.exists() else path


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m twinfalsify.pulse.replay",
        description="replay twin: recorded real Pulse 4.2 runs, either the reference "
                    "recording (patients.csv, runs.csv) or a study recorded with "
                    "python -m twinfalsify.runs.record (answers-*.jsonl)")
    ap.add_argument("--data", help="recording folder (relative paths are also tried from the "
                                   "checkout); default: $" + DATA_ENV + " or the reference")
    args = ap.parse_args(argv)
    data = resolve_data_dir(args.data)
    try:
        if any(data.glob("answers*.jsonl")):
            study = ReplayTwin(data, name=NAME)
            return protocol.serve_forever(study.hello, study.simulate)
        twin = RecordedPulse(data)
    except ContractError as exc:
        return refuse(f"{NAME}: {exc}")
    return protocol.serve_forever(twin.hello, twin.simulate)


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(main, "twinfalsify.pulse.replay"))  # bad input: one line, exit 2
