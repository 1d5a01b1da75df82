"""Tables recomputed from the results table."""

from __future__ import annotations

import pandas as pd

from twinfalsify.schema import OUTCOMES


def rejections_table(results: pd.DataFrame) -> pd.DataFrame:
    """Paper's Table 1 layout, per method: per outcome, hypotheses tested and rejected
    (after the correction) with causal bounds ("ours") and with Manski bounds."""
    g = results.groupby(["method", "outcome", "kind"])
    counts = pd.DataFrame({"hypotheses": g.size(), "rejections": g["rejected"].sum()})
    wide = counts.unstack("kind", fill_value=0)
    wide.columns = [f"{kind}_{what}" for what, kind in wide.columns]
    for kind in ("causal", "manski"):
        for what in ("hypotheses", "rejections"):
            if f"{kind}_{what}" not in wide:
                wide[f"{kind}_{what}"] = 0
    wide = (
        wide[["causal_hypotheses", "causal_rejections", "manski_hypotheses", "manski_rejections"]]
        .astype(int)
        .reset_index()
    )
    order = {o: i for i, o in enumerate(OUTCOMES)}
    wide["_o"] = wide["outcome"].map(order).fillna(len(order))
    wide = wide.sort_values(["method", "_o"]).drop(columns="_o")
    totals = wide.groupby("method", as_index=False).sum(numeric_only=True)
    totals["outcome"] = "Total"
    return (
        pd.concat([wide, totals[wide.columns]], ignore_index=True)
        .sort_values("method", kind="stable")
        .reset_index(drop=True)
    )
