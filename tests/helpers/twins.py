"""Twin runs in the tests: inputs, the fault-injecting twin's expected answers, a small plan,
and a twin served over the protocol in-process (no subprocess)."""

from __future__ import annotations

import io
import re

import numpy as np
import pandas as pd

from twinfalsify.runs.plan import TwinPlan
from twinfalsify.runs.protocol import decode, encode, serve_forever
from twinfalsify.runs.serve import BATCH_MAX, batch_handler, handlers
from twinfalsify.schema import FEATURE_BY_NAME, FEATURES
from twinfalsify.twins.base import SimResult

HR = FEATURES.index("HR")
UNITS = {name: f.unit for name, f in FEATURE_BY_NAME.items()}


def make_inputs(n: int, t: int = 3, seed: int = 0) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """(x0, doses, seeds) of ``n`` runs of ``t`` hours: random X_0 and doses of the bins'
    medians' magnitudes."""
    rng = np.random.default_rng(seed)
    x0 = pd.DataFrame({f: rng.uniform(50, 100, n).round(3) for f in FEATURES})
    doses = np.stack(
        [rng.choice([0.0, 10.0, 50.0, 150.0], (n, t)), rng.choice([0.0, 0.05, 0.2], (n, t))],
        axis=2,
    )
    seeds = np.arange(100, 100 + n, dtype=np.uint64)
    return x0, doses, seeds


def zero_dose_inputs(n: int = 3, t: int = 2) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """(x0, doses, seeds) of ``n`` runs of ``t`` hours without any dose."""
    rng = np.random.default_rng(0)
    x0 = pd.DataFrame({f: rng.uniform(50, 100, n).round(3) for f in FEATURES})
    doses = np.zeros((n, t, 2))
    return x0, doses, np.arange(10, 10 + n, dtype=np.uint64)


def expected_features(x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The faulty twin's good answer, recomputed here from its formula."""
    out = np.empty((len(x0), doses.shape[1], len(FEATURES)))
    for i in range(len(x0)):
        iv = np.cumsum(doses[i, :, 0])
        vaso = np.cumsum(doses[i, :, 1])
        hours = np.arange(1, doses.shape[1] + 1)
        shift = 0.001 * (0.5 * hours + 0.01 * iv + 10.0 * vaso + 0.001 * (int(seeds[i]) % 97))
        moves = np.array([f not in ("age", "sex", "weight") for f in FEATURES], dtype=float)
        out[i] = (x0.iloc[i][list(FEATURES)].to_numpy(float)[None, :]
                  + shift[:, None] * moves[None, :])
    return out


def stamps(message: str) -> tuple[int, float, float]:
    """(pid, start, end) the faulty twin wrote into a run's message."""
    m = re.search(r"pid=(\d+) start=([\d.]+) end=([\d.]+)", message)
    assert m, f"no timestamp in message {message!r}"
    return int(m.group(1)), float(m.group(2)), float(m.group(3))


def study_bits(n: int = 6):
    """X_0 from the synthetic world (inside the contract), a plan with one 3-hour leaf."""
    from twinfalsify.design import ActionBins
    from twinfalsify.sources.synthetic import generate

    d = generate({"n_stays": 40}, seed=3)
    x0 = d[d.t == 0].iloc[:n][["stay_id", *FEATURES]].reset_index(drop=True)
    ids = [int(s) for s in x0.stay_id]
    # seed 1: run seeds (by plan position) of both parities, which the faulty twin needs
    plan = TwinPlan(x0_stay_ids=ids, seed=1, shards=[["1-2-3"]], nodes=["1", "1-2", "1-2-3"])
    actions = ActionBins(iv_edges=(1.0, 2.0, 3.0), vaso_edges=(0.1, 0.2, 0.3),
                         iv_medians=(0.0, 1.0, 2.0, 3.0, 4.0),
                         vaso_medians=(0.0, 0.1, 0.2, 0.3, 0.4))
    return x0, plan, actions


class CountingTwin:
    """x_h = x0 + h * (iv_h / 100 - vaso_h) + (seed mod 7) / 10; records every call's n.

    Row-wise arithmetic, so a run's numbers cannot depend on its batch; a run
    with seed 13 raises (to exercise the one-at-a-time fallback).
    """

    name = "counting"

    def __init__(self) -> None:
        self.calls: list[int] = []

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        self.calls.append(len(x0))
        if (seeds == 13).any():
            raise RuntimeError("seed 13 is unlucky")
        n, t, _ = doses.shape
        h = np.arange(1, t + 1)[None, :]
        shift = h * (doses[..., 0] / 100 - doses[..., 1]) + (seeds % 7)[:, None] / 10
        feats = x0[list(FEATURES)].to_numpy(float)[:, None, :] + shift[..., None]
        return SimResult(feats, np.full(n, "ok", dtype=object))


def simulate_request(i: int, hours: int, seed: int) -> dict:
    """A protocol ``simulate`` message for run ``r{i}``."""
    x0 = {f: 50.0 + i + 0.25 * j for j, f in enumerate(FEATURES)}
    doses = [[10.0 * (i + h), 0.01 * h] for h in range(hours)]
    return {"op": "simulate", "id": f"r{i}", "x0": x0, "doses": doses, "hours": hours,
            "seed": seed}


def serve_in_process(messages: list[dict], *, batch: bool, twin=None) -> list[dict]:
    """The answers of ``twin`` (a ``CountingTwin`` by default) served over the protocol to
    ``messages``, batched or not, in this process."""
    twin = twin or CountingTwin()
    hello, simulate = handlers(twin, batch=BATCH_MAX)
    stdout = io.StringIO()
    serve_forever(hello, simulate, io.StringIO("".join(map(encode, messages))), stdout,
                  simulate_batch=batch_handler(twin) if batch else None)
    return [decode(line) for line in stdout.getvalue().splitlines()]


def synthetic_context(folder, n_stays: int, d0_stays: int):
    """A twin context in ``folder`` (twin_context.json, d0.parquet): the synthetic world of
    ``n_stays`` stays (seed 3) and its first ``d0_stays`` stays as D0 (what the fitted twin
    fits on). Returns the context file's path."""
    import json

    from twinfalsify.sources.synthetic import generate

    synthetic = {"n_stays": n_stays}
    generate(synthetic, 3).query(f"stay_id <= {200000 + d0_stays}").to_parquet(
        folder / "d0.parquet")
    (folder / "twin_context.json").write_text(json.dumps(
        {"source": {"kind": "synthetic", "synthetic": synthetic},
         "d0": str(folder / "d0.parquet")}))
    return folder / "twin_context.json"
