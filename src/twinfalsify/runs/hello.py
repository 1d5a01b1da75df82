"""A twin's hello, checked before a study's expensive work (rule ``twin_hello``).

A served or command twin is started once, with no data: its hello must name protocol 1,
a name and a version, every feature of the trajectory contract in its unit
(``runs.protocol.check_hello``); a bad hello is a ContractError naming the twin, the field
and the problem. The worker then simulates one X_0 for ``PROBE_HOURS`` hours, timed: a first
measure of the twin's seconds per simulated hour, from which the rule ``twin_cost``
projects a study's wall time (``projected_cost``). A ``kind: python`` twin is built in
this process (its factory is called, the object it returns checked) and timed the same
way; builtin twins are the library's own and pass as they are.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify.runs.registry import BUILTIN_KINDS, make_twin
from twinfalsify.schema import FEATURES

PROBE_HOURS = 1  # hours of the one timed run: a slow engine (Pulse) pays ~minutes per hour


def probe_x0() -> dict[str, float]:
    """The X_0 of the probe run: the synthetic world's median patient, the first X_0 of
    ``runs.check.shipped_x0`` (not imported: its modules would join this rule's code)."""
    from twinfalsify.schema import STAY_ID, TIME
    from twinfalsify.sources.synthetic import generate

    x0 = generate({"n_stays": 400}, seed=11)
    x0 = x0[x0[TIME] == 0].set_index(STAY_ID)[list(FEATURES)]
    med = (x0 - x0.median()).abs().div(x0.std() + 1e-12).sum(axis=1).idxmin()
    return {f: float(x0.at[med, f]) for f in FEATURES}


def twin_hello(name: str, spec: dict[str, Any], hours: int = PROBE_HOURS) -> dict[str, Any]:
    """What ``hello.json`` holds for the twin ``name``: its kind, how it was checked, its
    hello answer (served and command twins) and ``probe`` (one timed run, or None)."""
    kind = spec.get("kind")
    out: dict[str, Any] = {"twin": name, "kind": kind}
    if kind in BUILTIN_KINDS:  # the library's own code (served or not): nothing to ask
        return {**out, "checked": "builtin", "probe": None}
    from twinfalsify.runs.protocol_twin import ProtocolTwin

    twin = make_twin(name, spec)  # kind python in-process: its factory runs and is checked
    if isinstance(twin, ProtocolTwin):
        hello = twin.hello(probe=probe_x0(), hours=hours)
        return {**out, "checked": "hello", "probe": hello.pop("probe"), "hello": hello}
    x0 = pd.DataFrame([probe_x0()])[list(FEATURES)]
    start = time.monotonic()
    res = twin.simulate(x0, np.zeros((1, hours, 2)), np.zeros(1, dtype=np.uint64))
    seconds = time.monotonic() - start
    status = str(np.asarray(res.status)[0])
    return {**out, "checked": "in-process", "class": type(twin).__name__,
            "probe": {"hours": hours, "seconds": seconds, "status": status,
                      "message": "" if status == "ok" else str(np.asarray(res.message)[0])}}


def split_timing(hello: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(hello without the probe's measured seconds, the measurement ``{"seconds": ...}``).

    The rule writes the first to ``twins/<twin>/hello.json``, identical from one run to the
    next, and the second under ``benchmarks/`` with the other measured times."""
    probe = hello.get("probe")
    if not probe or "seconds" not in probe:
        return hello, {"seconds": None}
    kept = {k: v for k, v in probe.items() if k != "seconds"}
    return {**hello, "probe": kept}, {"seconds": probe["seconds"]}


def with_timing(hello: dict[str, Any], timing: dict[str, Any]) -> dict[str, Any]:
    """The hello with its probe's measured seconds back (the inverse of
    :func:`split_timing`), as :func:`seconds_per_hour` and :func:`projected_cost` read it."""
    probe = hello.get("probe")
    if not probe or timing.get("seconds") is None:
        return hello
    return {**hello, "probe": {**probe, "seconds": timing["seconds"]}}


def seconds_per_hour(hello: dict[str, Any]) -> float | None:
    """Seconds per simulated hour measured by the probe run; None when it did not run ok."""
    probe = hello.get("probe") or {}
    if probe.get("status") != "ok" or not probe.get("hours") or probe.get("seconds") is None:
        return None
    return float(probe["seconds"]) / int(probe["hours"])


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
    probe = hello.get("probe")
    why = ("builtin twin, not probed" if probe is None else
           f"the hello's probe run ended {probe.get('status')}: {probe.get('message')}")
    return {
        **({"unknown_because": why} if sph is None else {}),
        "runs": int(runs),
        "engine_hours": hours,
        "counted_as": "prefix tree (save/restore)" if save_restore else "runs x hours",
        "seconds_per_hour": sph,
        "workers": int(workers),
        "wall_seconds": None if sph is None else hours * sph / max(int(workers), 1),
    }


def cost_line(twin: str, cost: dict[str, Any]) -> str:
    """One line for the console and the log: engine-hours and, when known, wall time."""
    from twinfalsify.runs.runner import format_duration

    line = (f"twin {twin}: the plan asks {cost['runs']:,} runs, {cost['engine_hours']:,} "
            f"engine-hours ({cost['counted_as']})")
    if cost["seconds_per_hour"] is None:
        why = cost.get("unknown_because") or "not measured"
        return line + f"; seconds per simulated hour unknown ({why})"
    return (line + f"; at {cost['seconds_per_hour']:.3g} s per simulated hour on "
            f"{cost['workers']} worker(s): about {format_duration(cost['wall_seconds'])} wall")
