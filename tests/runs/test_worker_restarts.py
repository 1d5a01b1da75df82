"""Worker crashes and restarts are counted per shard, kept with the runs and warned about.

A twin crashing on some requests still ends with every run ok (each run is retried on a
fresh worker): the restarts are the only trace, so they must reach the shard's runs, the
twin's run_summary.json, the study summary and the console.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fakes import FAULTY_TWIN
from helpers.paths import ENV

from twinfalsify.runs.plan import restart_warning, worker_summary
from twinfalsify.runs.protocol_twin import ProtocolTwin
from twinfalsify.runs.runner import simulate_via_protocol
from twinfalsify.schema import FEATURES
from twinfalsify.summary import study_summary, summary_markdown, summary_warnings


def _runs(n: int, t: int = 2):
    rng = np.random.default_rng(3)
    x0 = pd.DataFrame({f: rng.uniform(50, 100, n).round(3) for f in FEATURES})
    x0["sex"] = 1.0
    return x0, np.zeros((n, t, 2)), np.arange(n, dtype=np.uint64)


@pytest.mark.parametrize("workers", [1, 2])
def test_every_third_seed_crashing_once_ends_all_ok_with_its_restarts_counted(tmp_path, workers):
    n = 12
    state = tmp_path / "state"
    state.mkdir()
    cmd = [*FAULTY_TWIN, "--mode=crash_once:%3=0", f"--state-dir={state}"]
    stats: dict = {}
    res = simulate_via_protocol(cmd, *_runs(n), env=ENV, workers=workers, retries=2,
                                progress=False, stats_out=stats)
    assert (res.status == "ok").all()  # the retries hide the crashes from the statuses ...
    crashing = sum(1 for s in range(n) if s % 3 == 0)
    # ... but not from the counts: one crash and one restart per crashing seed
    assert stats == {"restarts": crashing, "crashes": crashing, "hangs": 0,
                     "protocol_breaks": 0}


def test_a_stable_twin_restarts_nothing_and_a_hang_is_counted_as_such(tmp_path):
    stats: dict = {}
    simulate_via_protocol([*FAULTY_TWIN, "--mode=ok"], *_runs(6), env=ENV, workers=2,
                          progress=False, stats_out=stats)
    assert stats == {"restarts": 0, "crashes": 0, "hangs": 0, "protocol_breaks": 0}
    stats = {}
    res = simulate_via_protocol([*FAULTY_TWIN, "--mode=hang:0"], *_runs(3), env=ENV,
                                retries=1, timeout_s=0.5, fail_fast_runs=0, progress=False,
                                stats_out=stats)
    assert list(res.status).count("timeout") == 1
    assert stats["hangs"] == 2 and stats["restarts"] == 2 and stats["crashes"] == 0


def test_protocol_twin_keeps_the_counts_of_its_last_call(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    twin = ProtocolTwin("t", [*FAULTY_TWIN, "--mode=crash_once:%2=1", f"--state-dir={state}"],
                        env=ENV, progress=False)
    twin.simulate(*_runs(4))
    assert twin.last_workers["restarts"] == 2 and twin.last_workers["crashes"] == 2
    twin.simulate(*_runs(4))  # the markers exist: no crash the second time
    assert twin.last_workers["restarts"] == 0


def test_worker_summary_sums_shards_and_warns_once_per_twin():
    quiet = {"restarts": 0, "crashes": 0, "hangs": 0, "protocol_breaks": 0}
    shaky = {"restarts": 3, "crashes": 2, "hangs": 1, "protocol_breaks": 0}
    summary = worker_summary([quiet, shaky])
    assert summary["total"] == shaky and summary["per_shard"] == [quiet, shaky]
    assert worker_summary([None, None]) == {}  # in-process twins record none
    assert restart_warning("x", 0, quiet) == ""
    line = restart_warning("x", 1, shaky)
    assert "\n" not in line and "twin x: shard 1" in line and "3 time(s)" in line
    assert "crashes 2, hangs 1" in line


def test_study_summary_shows_restarts_per_shard_and_a_warning():
    hyps = pd.DataFrame({"hyp_id": [0], "kind": ["causal"]})
    d = pd.DataFrame({"stay_id": [1, 2]})
    runs = pd.DataFrame({"node": ["0"] * 2, "t": [1, 1], "init_stay_id": [1, 2],
                         "status": ["ok", "ok"], "clamped": ["{}", "{}"]})
    res = pd.DataFrame({"hyp_id": [0], "kind": ["causal"], "method": ["hoeffding"],
                        "rejected": [False], "refused": [False], "n": [5], "nhat": [5],
                        "p_value": [0.5]})
    shaky = {"restarts": 4, "crashes": 4, "hangs": 0, "protocol_breaks": 0}
    calm = dict.fromkeys(shaky, 0)
    stable = runs.copy()
    runs.attrs = {"twin_workers": worker_summary([calm, shaky])}
    tables = study_summary("s", d, d, hyps, {"shaky": {"runs": runs, "results": res},
                                              "inproc": {"runs": stable, "results": res}})
    w = tables["workers"]
    assert list(w["twin"]) == ["shaky", "shaky"] and list(w["shard"]) == [0, 1]
    assert list(w["restarts"]) == [0, 4]
    warnings = summary_warnings(tables)
    assert len(warnings) == 1 and "twin shaky: its shards restarted" in warnings[0]
    assert "Twin worker restarts per shard" in summary_markdown("s", tables)


def test_restart_counts_survive_the_parquet_round_trip(tmp_path):
    runs = pd.DataFrame({"a": [1]})
    runs.attrs = {"twin_workers": worker_summary([{"restarts": 1, "crashes": 1}])}
    runs.to_parquet(tmp_path / "r.parquet", index=False)
    back = pd.read_parquet(tmp_path / "r.parquet")
    assert back.attrs["twin_workers"]["total"]["restarts"] == 1
