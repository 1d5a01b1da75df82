"""One hypothesis in clinical words: who, under which doses, what, and what each test said.

    python -m twinfalsify.explain results/<study> HYP_ID [--twin NAME]

prints the patient subgroup (sex, age quartile and the outcome above or below its D0 median
at each hour, with the numbers and units behind each bin), the action sequence as doses
(the D0 median dose of each bin the twin was given, with the bin's range), the outcome and
hour, the bounds [y_lo, y_up] the outcomes are clipped to, and per twin the twin's mean
against the data's bounds with n and n_hat, the size of the difference the clipping hides
(the twin's unclipped mean and median and its shares below y_lo and above y_up, beside the
data's followers'), and every method's p-value and decision per side with the threshold of
the correction it was held to. It reads only what a study wrote: design/hypotheses.parquet,
design/bins.json, design/actions.json and twins/<twin>/results.parquet, and for the sizes
the files the tests read (``twin_tests.load_twin_tests``), when they are there.
"""

from __future__ import annotations

import argparse
import base64
import html
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from twinfalsify.design import N_DOSE_BINS, WHOLE_SPACE, ActionBins, StateBins, subgroup_parts
from twinfalsify.inference.multiple_testing import thresholds_within
from twinfalsify.io import read_json, read_parquet
from twinfalsify.schema import FEATURE_BY_NAME, ContractError
from twinfalsify.twin_tests import STORED_INPUTS, load_twin_tests, outcome_sizes

QUARTILES = ("1st", "2nd", "3rd", "4th")


def _num(v: float) -> str:
    return f"{v:.4g}"


def dose_bin_range(edges: Sequence[float], k: int) -> str:
    """The dose range of bin k (0 = none, 1-4 = quartiles of the non-zero D0 doses)."""
    if k == 0:
        return "none"
    lo = 0.0 if k == 1 else edges[k - 2]
    if k == 4:
        return f"> {_num(lo)}"
    return f"{'> 0' if k == 1 else '> ' + _num(lo)} to {_num(edges[k - 1])}"


def doses_in_words(codes: Sequence[int], actions: ActionBins) -> list[str]:
    """One line per hour: the doses the twin was given and the bins they stand for."""
    out = []
    for h, a in enumerate(codes, start=1):
        iv, vaso = int(a) // N_DOSE_BINS, int(a) % N_DOSE_BINS
        out.append(f"hour {h}: IV fluid {_num(actions.iv_medians[iv])} mL/h (bin {iv}: "
                   f"{dose_bin_range(actions.iv_edges, iv)}), vasopressor "
                   f"{_num(actions.vaso_medians[vaso])} ug/kg/min (bin {vaso}: "
                   f"{dose_bin_range(actions.vaso_edges, vaso)})")
    return out


def subgroup_in_words(codes: Sequence[int], outcome: str, states: StateBins) -> list[str]:
    """The B-sets B_0..B_t as patients: sex, age quartile, outcome vs the D0 median."""
    if all(int(c) == WHOLE_SPACE for c in codes):
        return ["every patient (Manski bounds: no subgroup)"]
    sex, age_q, _ = subgroup_parts(codes[0])
    edges = states.age_edges
    # quartile by searchsorted(..., side="right"): [e_{q-1}, e_q)
    age = (f"age < {_num(edges[0])}" if age_q == 0 else f"age >= {_num(edges[-1])}"
           if age_q == 3 else f"age {_num(edges[age_q - 1])} to < {_num(edges[age_q])}")
    unit = FEATURE_BY_NAME[outcome].unit
    lines = [f"{'female' if sex else 'male'}, {age} years ({QUARTILES[age_q]} age quartile "
             "of D0)"]
    for s, c in enumerate(codes):
        med = states.medians[outcome][s]
        rel = "above" if int(c) % 2 else "at or below"
        lines.append(f"{outcome} at hour {s} {rel} {_num(med)} {unit} (the D0 median at "
                     f"hour {s})")
    return lines


def twins_with_results(results_dir: Path, twin: str | None) -> list[str]:
    """The twins of a study with a results.parquet (only ``twin`` when given, an error
    naming those found when it has none)."""
    found = sorted(p.name for p in (results_dir / "twins").glob("*")
                   if (p / "results.parquet").is_file())
    if twin is not None:
        if twin not in found:
            raise ContractError(f"{results_dir}/twins: no twin {twin!r} with results (found "
                                f"{', '.join(found) or 'none'})")
        return [twin]
    if not found:
        raise ContractError(f"{results_dir}/twins: no twin has results.parquet yet (run the "
                            "study first)")
    return found


def stored_paths(results_dir: str | Path, twin: str) -> dict[str, Path]:
    """The files ``twin_tests.load_twin_tests`` reads, where a study writes them."""
    r = Path(results_dir)
    return {"d": r / "d.parquet", "bins": r / "design" / "bins.json",
            "hypotheses": r / "design" / "hypotheses.parquet",
            "counts": r / "observational" / "counts.parquet",
            "follow": r / "observational" / "follow.parquet", "plan": r / "twin_plan.json",
            "runs": r / "twins" / twin / "runs.parquet"}


def study_sizes(results_dir: str | Path, twin: str) -> pd.DataFrame | None:
    """``twin_tests.outcome_sizes`` of a stored twin, indexed by hyp_id; None when the
    study's files the tests read are not all there."""
    paths = stored_paths(results_dir, twin)
    if set(paths) != set(STORED_INPUTS) or not all(p.is_file() for p in paths.values()):
        return None
    tt = load_twin_tests(paths)
    return outcome_sizes(tt.samples).set_index(tt.hyps["hyp_id"].to_numpy())


def _pct(v: float) -> str:
    return f"{v:.0%}" if np.isfinite(v) else "-"


def sizes_in_words(row: pd.Series | None, unit: str) -> str:
    """The line on the size of the difference: unclipped mean and median and the shares
    beyond each bound, the twin's beside the data's followers'."""
    if row is None or not np.isfinite(row["twin_mean"]):
        return ""
    data = (f"data's followers: mean {_num(row['data_mean'])}, median "
            f"{_num(row['data_median'])} {unit}, {_pct(row['data_below'])} below y_lo, "
            f"{_pct(row['data_above'])} above y_up" if np.isfinite(row["data_mean"])
            else "no data follower")
    return (f"  unclipped: twin mean {_num(row['twin_mean'])}, median "
            f"{_num(row['twin_median'])} {unit}, {_pct(row['twin_below'])} of its outputs "
            f"below y_lo, {_pct(row['twin_above'])} above y_up ({data})")


def mean_in_words(row: pd.Series, unit: str) -> str:
    """The twin's clipped mean against the data's bounds, from one row of a results table:
    'mean (clipped) M unit from n_hat = N runs; data bounds [L, U] unit from n = n stays
    (f followed these doses): inside the bounds' (or below / above, or no twin runs)."""
    mean, lo, up = row["q_twin_hat"], row["q_lo_hat"], row["q_up_hat"]
    where = ("below the lower bound" if mean < lo else "above the upper bound"
             if mean > up else "inside the bounds") if np.isfinite(mean) else "no twin runs"
    return (f"mean (clipped) {_num(mean)} {unit} from n_hat = {int(row['nhat'])} runs; data "
            f"bounds [{_num(lo)}, {_num(up)}] {unit} from n = {int(row['n'])} stays "
            f"({int(row['n_follow'])} followed these doses): {where}")


def explain(results_dir: str | Path, hyp_id: int, twin: str | None = None,
            sizes: Mapping[str, pd.DataFrame | None] | None = None) -> str:
    """The text ``python -m twinfalsify.explain`` prints. sizes: twin name ->
    ``study_sizes`` (computed from the study's files for a twin not in it)."""
    r = Path(results_dir)
    hyps = read_parquet(r / "design" / "hypotheses.parquet", "hypotheses")
    row = hyps[hyps["hyp_id"] == hyp_id]
    if row.empty:
        raise ContractError(f"{r}/design/hypotheses.parquet: no hypothesis {hyp_id} (ids "
                            f"{int(hyps['hyp_id'].min())}..{int(hyps['hyp_id'].max())})")
    h = row.iloc[0]
    states = StateBins.from_json(read_json(r / "design" / "bins.json"))
    actions = ActionBins.from_json(read_json(r / "design" / "actions.json"))
    outcome, t, unit = str(h["outcome"]), int(h["t"]), FEATURE_BY_NAME[str(h["outcome"])].unit
    lines = [f"hypothesis {hyp_id} ({h['kind']}): the mean {outcome} at hour {t}, outcomes "
             f"clipped to [y_lo, y_up] = [{_num(h['y_lo'])}, {_num(h['y_up'])}] {unit}",
             "patients:"]
    lines += [f"  {x}" for x in subgroup_in_words(list(h["bins"]), outcome, states)]
    lines.append("doses (each the D0 median of its bin):")
    lines += [f"  {x}" for x in doses_in_words(list(h["actions"]), actions)]
    for name in twins_with_results(r, twin):
        res = read_parquet(r / "twins" / name / "results.parquet", "results")
        sized = sizes[name] if sizes is not None and name in sizes else study_sizes(r, name)
        if len(res):
            level, rank, size = thresholds_within(
                res["p_value"].to_numpy(),
                (res["method"].astype(str) + "\x00" + res["kind"].astype(str)).to_numpy(),
                float(res["alpha"].iloc[0]), str(res["correction"].iloc[0]))
            res = res.assign(threshold=level, rank=rank, family=size)
        mine = res[res["hyp_id"] == hyp_id]
        if mine.empty:
            lines.append(f"twin {name}: not tested (no results row)")
            continue
        lines.append(f"twin {name}: {mean_in_words(mine.iloc[0], unit)}")
        if sized is not None and hyp_id in sized.index:
            if words := sizes_in_words(sized.loc[hyp_id], unit):
                lines.append(words)
        for m in mine.sort_values(["method", "side"]).itertuples():
            verdict = "REJECTED" if m.rejected else "not rejected"
            lines.append(f"  {m.method:<10} H_{m.side}: p = {m.p_value:.3g}, {verdict} "
                         f"({_threshold_words(m)})")
    return "\n".join(lines)


def _threshold_words(m: object) -> str:
    """The level a p-value was held to: 'Holm threshold T at rank r of m in its family
    (method, kind), alpha A'."""
    name = {"holm": "Holm", "bonferroni": "Bonferroni", "by": "Benjamini-Yekutieli",
            "none": "uncorrected"}.get(m.correction, m.correction)
    return (f"{name} threshold {m.threshold:.3g} at rank {m.rank} of {m.family} in its "
            f"family ({m.method}, {m.kind}), alpha {m.alpha:g}")


def rejections_to_explain(results: pd.DataFrame, k: int) -> tuple[list[int], int]:
    """The first ``k`` hypotheses rejected by any method (smallest p first, then hyp_id)
    and how many were rejected in all."""
    rej = results[results["rejected"]]
    per = rej.groupby("hyp_id")["p_value"].min().reset_index()
    per = per.sort_values(["p_value", "hyp_id"], kind="stable")
    return [int(h) for h in per["hyp_id"].head(max(int(k), 0))], len(per)


def explained_html(twin: str, sections: Sequence[tuple[int, str, bytes]], n_rejected: int) -> str:
    """A self-contained page: per rejection (hyp_id, ``explain`` text, PNG of its bounds
    figure) the text and the figure, for the Snakemake report."""
    style = ("body{font-family:sans-serif;margin:1.5em;max-width:62em}"
             "pre{background:#f6f6f6;padding:.6em;white-space:pre-wrap}img{max-width:100%}")
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>twin {html.escape(twin)}: "
           f"rejections explained</title><style>{style}</style></head><body>",
           f"<h1>Twin <code>{html.escape(twin)}</code>: rejections explained</h1>",
           f"<p>{len(sections)} of {n_rejected} rejected hypotheses (smallest p-value first)."
           "</p>"]
    if not n_rejected:
        out.append("<p>No hypothesis was rejected for this twin.</p>")
    for hyp_id, text, png in sections:
        data = base64.b64encode(png).decode("ascii")
        out += [f"<h2 id='h{hyp_id}'>Hypothesis {hyp_id}</h2>",
                f"<pre>{html.escape(text)}</pre>",
                f"<img alt='bounds over time of hypothesis {hyp_id}' "
                f"src='data:image/png;base64,{data}'>"]
    out.append("</body></html>")
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twinfalsify.explain",
                                     description="Explain one hypothesis of a study.")
    parser.add_argument("results", help="the study's results folder (results/<study>)")
    parser.add_argument("hyp_id", type=int, help="the hypothesis id (results' hyp_id)")
    parser.add_argument("--twin", help="only this twin (default: every twin with results)")
    args = parser.parse_args(argv)
    print(explain(args.results, args.hyp_id, args.twin))
    return 0


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(lambda: main(), "twinfalsify.explain"))

