"""Figure hypothesis ids of a study config, checked against the study's hypotheses.

A module of its own (no library imports) so that the design rule, which runs the check, does
not depend on the rest of the config checks (its code fingerprint stays small).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def figure_ids_error(config: Mapping[str, Any], hyp_ids: Any) -> str | None:
    """``figures.longitudinal.hyp_id`` / ``figures.histograms.hyp_ids`` naming no hypothesis
    of the study, as one line, or None. Checked when the hypotheses are built (rule design)
    and at every start once they exist, not when the figure rule finally runs."""
    known = {int(h) for h in hyp_ids}
    figures = config.get("figures") or {}
    asked = {"figures.longitudinal.hyp_id": [(figures.get("longitudinal") or {}).get("hyp_id")],
             "figures.histograms.hyp_ids": (figures.get("histograms") or {}).get("hyp_ids")}
    for key, ids in asked.items():
        bad = [int(h) for h in ids or [] if h is not None and int(h) not in known]
        if bad:
            span = f"{min(known)}..{max(known)}" if known else "none"
            return (f"config key {key}: {', '.join(map(str, bad))} not a hypothesis of this "
                    f"study (hyp_id {span}, {len(known)} hypotheses; see "
                    "design/hypotheses.parquet)")
    return None
