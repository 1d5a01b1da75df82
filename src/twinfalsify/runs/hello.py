"""A twin's hello, checked before a study's expensive work (rule ``twin_hello``).

A served or command twin is started once, with no data: its hello must name protocol 1,
a name and a version, every feature of the trajectory contract in its unit
(``runs.protocol.check_hello``); a bad hello is a ContractError naming the twin, the field
and the problem. The worker then simulates one X_0 ``PROBE_RUNS`` times for ``PROBE_HOURS``
hours, each run timed: a first measure of the twin's seconds per simulated hour (the
median run) and of its spread (the fastest and the slowest run), from which the rule
``twin_cost`` projects a study's wall time (``projected_cost``). A ``kind: python`` twin is built in
this process (its factory is called, the object it returns checked) and timed the same
way; builtin twins are the library's own and pass as they are.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.runs.protocol_twin import probe_record
from twinfalsify.runs.registry import BUILTIN_KINDS, make_twin
from twinfalsify.schema import FEATURES

PROBE_HOURS = 1  # hours of each timed run: a slow engine (Pulse) pays ~minutes per hour
PROBE_RUNS = 3  # timed runs: one run's time can be far from a typical run's


def probe_x0() -> dict[str, float]:
    """The X_0 of the probe run: the synthetic world's median patient, the first X_0 of
    ``runs.check.shipped_x0`` (not imported: its modules would join this rule's code)."""
    from twinfalsify.schema import STAY_ID, TIME
    from twinfalsify.sources.synthetic import generate

    x0 = generate({"n_stays": 400}, seed=11)
    x0 = x0[x0[TIME] == 0].set_index(STAY_ID)[list(FEATURES)]
    med = (x0 - x0.median()).abs().div(x0.std() + 1e-12).sum(axis=1).idxmin()
    return {f: float(x0.at[med, f]) for f in FEATURES}


def twin_hello(name: str, spec: dict[str, Any], hours: int = PROBE_HOURS,
               runs: int = PROBE_RUNS) -> dict[str, Any]:
    """What ``hello.json`` holds for the twin ``name``: its kind, how it was checked, its
    hello answer (served and command twins) and ``probe`` (``runs`` timed runs, or None)."""
    kind = spec.get("kind")
    out: dict[str, Any] = {"twin": name, "kind": kind}
    if kind in BUILTIN_KINDS:  # the library's own code (served or not): nothing to ask
        return {**out, "checked": "builtin", "probe": None}
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    twin = make_twin(name, spec)  # kind python in-process: its factory runs and is checked
    if isinstance(twin, ProtocolTwin):
        hello = twin.hello(probe=probe_x0(), hours=hours, runs=runs)
        return {**out, "checked": "hello", "probe": hello.pop("probe"), "hello": hello}
    x0 = pd.DataFrame([probe_x0()])[list(FEATURES)]
    each, status, message = [], "ok", ""
    for k in range(max(int(runs), 1)):
        start = time.monotonic()
        res = twin.simulate(x0, np.zeros((1, hours, 2)), np.full(1, k, dtype=np.uint64))
        each.append(time.monotonic() - start)
        status = str(np.asarray(res.status)[0])
        if status != "ok":
            message = str(np.asarray(res.message)[0])
            break
    return {**out, "checked": "in-process", "class": type(twin).__name__,
            "probe": probe_record(hours, each, status, message)}


MEASURED = ("seconds", "seconds_each")  # the probe's timings: never in hello.json


def split_timing(hello: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(hello without the probe's measured times, the measurement ``{"seconds": ...,
    "seconds_each": [...]}``).

    The rule writes the first to ``twins/<twin>/hello.json``, identical from one run to the
    next, and the second under ``benchmarks/`` with the other measured times."""
    probe = hello.get("probe")
    if not probe or "seconds" not in probe:
        return hello, {"seconds": None}
    kept = {k: v for k, v in probe.items() if k not in MEASURED}
    return {**hello, "probe": kept}, {k: probe[k] for k in MEASURED if k in probe}


def with_timing(hello: dict[str, Any], timing: dict[str, Any]) -> dict[str, Any]:
    """The hello with its probe's measured times back (the inverse of
    :func:`split_timing`), as :func:`seconds_per_hour` and :func:`projected_cost` read it."""
    probe = hello.get("probe")
    if not probe or timing.get("seconds") is None:
        return hello
    return {**hello, "probe": {**probe, **{k: timing[k] for k in MEASURED if k in timing}}}


def seconds_per_hour(hello: dict[str, Any]) -> float | None:
    """Seconds per simulated hour measured by the probe (its median run); None when it did
    not run ok."""
    probe = hello.get("probe") or {}
    if probe.get("status") != "ok" or not probe.get("hours") or probe.get("seconds") is None:
        return None
    return float(probe["seconds"]) / int(probe["hours"])


def seconds_per_hour_range(hello: dict[str, Any]) -> tuple[float, float] | None:
    """(fastest, slowest) seconds per simulated hour over the probe's runs; None when the
    probe did not run ok or timed fewer than two runs."""
    probe = hello.get("probe") or {}
    each = probe.get("seconds_each") or []
    if seconds_per_hour(hello) is None or len(each) < 2:
        return None
    return min(each) / int(probe["hours"]), max(each) / int(probe["hours"])


def projected_cost(plan_hours: dict[str, int], runs: int, hello: dict[str, Any],
                   workers: int, save_restore: bool | None = None) -> dict[str, Any]:
    """The engine-hours a plan asks of one twin and, when its seconds per simulated hour
    are known, the projected wall time on ``workers`` processes.

    engine_hours: runs x hours, every action sequence simulated as a leaf (what a twin
    without save/restore computes); a twin advertising ``capabilities.save_restore``
    branches shared prefixes and needs only the prefix tree's hours. Wall time =
    engine_hours x seconds per hour / workers: perfect parallelism and a per-hour cost
    as the probe's (a first hour may cost more or less than later ones), so a rough guide,
    not a bound.
    """
    if save_restore is None:
        save_restore = bool(((hello.get("hello") or {}).get("capabilities") or {})
                            .get("save_restore", False))
    hours = int(plan_hours["prefix_tree" if save_restore else "leaves"])
    sph = seconds_per_hour(hello)
    spread = seconds_per_hour_range(hello)
    probe = hello.get("probe")
    why = ("builtin twin, not probed" if probe is None else
           f"the hello's probe run ended {probe.get('status')}: {probe.get('message')}")
    return {
        **({"unknown_because": why} if sph is None else {}),
        "runs": int(runs),
        "engine_hours": hours,
        "counted_as": "prefix tree (save/restore)" if save_restore else "runs x hours",
        "seconds_per_hour": sph,
        "probe_runs": int((probe or {}).get("runs", 1)) if sph is not None else 0,
        "seconds_per_hour_range": None if spread is None else list(spread),
        "workers": int(workers),
        "wall_seconds": None if sph is None else hours * sph / max(int(workers), 1),
        "wall_seconds_range": None if spread is None else
        [hours * v / max(int(workers), 1) for v in spread],
    }


def cost_line(twin: str, cost: dict[str, Any]) -> str:
    """One line for the console and the log: engine-hours and, when known, wall time."""
    from twinfalsify.runs.runner import format_duration

    line = (f"twin {twin}: the plan asks {cost['runs']:,} runs, {cost['engine_hours']:,} "
            f"engine-hours ({cost['counted_as']})")
    if cost["seconds_per_hour"] is None:
        why = cost.get("unknown_because") or "not measured"
        return line + f"; seconds per simulated hour unknown ({why})"
    spread = cost.get("seconds_per_hour_range")
    if not spread:
        return (line + f"; at {cost['seconds_per_hour']:.3g} s per simulated hour on "
                f"{cost['workers']} worker(s): about {format_duration(cost['wall_seconds'])} "
                "wall")
    lo, hi = cost["wall_seconds_range"]
    return (line + f"; at {cost['seconds_per_hour']:.3g} s per simulated hour (median of "
            f"{cost['probe_runs']} probe runs, {spread[0]:.3g}-{spread[1]:.3g} s) on "
            f"{cost['workers']} worker(s): about {format_duration(cost['wall_seconds'])} wall "
            f"({format_duration(lo)} to {format_duration(hi)})")
