"""Two twins, or two versions of one twin, on one design: what is newly rejected or passing.

    python -m twinfalsify.diff results/<study> TWIN_A TWIN_B
    python -m twinfalsify.diff results/<study> TWIN_A TWIN_B --results-b results/<study2>

compares the results of twin A (in the first folder) with those of twin B (in the first
folder, or in ``--results-b`` when given: a second study run with the same design, for
instance with a new version of a twin). Per method, a hypothesis counts as rejected when
either of its sides (H_lo, H_up) is; it is *newly rejected* when B rejects it and A does
not, *newly passing* when A rejects it and B does not. Each change is listed per outcome and
hour with both sides' means against the data's bounds and the size of the difference, in
the words of ``python -m twinfalsify.explain`` (``explain.mean_in_words`` and
``explain.sizes_in_words``; the sizes come from ``twin_tests.load_twin_tests`` through
``explain.study_sizes`` when the study's files are there), then a summary line.

Exit status: 0 when nothing is newly rejected (newly passing hypotheses alone are not a
regression), 1 when some hypothesis is newly rejected (a CI job can fail on it), 2 on bad
input (one line on stderr), e.g. two folders whose designs differ.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np
import pandas as pd

from twinfalsify.explain import mean_in_words, sizes_in_words, study_sizes, twins_with_results
from twinfalsify.io import read_json, read_parquet
from twinfalsify.schema import FEATURE_BY_NAME, ContractError

NEWLY_REJECTED, NEWLY_PASSING = "newly rejected", "newly passing"
# the design files two folders must share (compared as tables / as JSON)
DESIGN_FILES = ("hypotheses.parquet", "bins.json", "actions.json")


@dataclass(frozen=True)
class Side:
    """One side of a diff: a twin's results in a study folder."""

    label: str  # "A" or "B"
    results_dir: Path
    twin: str
    results: pd.DataFrame

    @classmethod
    def read(cls, label: str, results_dir: str | Path, twin: str) -> Side:
        r = Path(results_dir)
        if not (r / "design" / "hypotheses.parquet").is_file():
            raise ContractError(f"{r}: no design/hypotheses.parquet (not a study's results "
                                "folder, or the study has not run)")
        twins_with_results(r, twin)  # names the twins found when this one has no results
        return cls(label, r, twin, read_parquet(r / "twins" / twin / "results.parquet",
                                                "results"))

    def name(self) -> str:
        return f"{self.label} {self.twin}"


def design_difference(dir_a: str | Path, dir_b: str | Path) -> str | None:
    """Why two study folders do not share a design (one phrase), or None when their
    design/hypotheses.parquet, design/bins.json and design/actions.json agree."""
    a, b = Path(dir_a) / "design", Path(dir_b) / "design"
    if a.resolve() == b.resolve():
        return None
    ha = read_parquet(a / "hypotheses.parquet", "hypotheses").reset_index(drop=True)
    hb = read_parquet(b / "hypotheses.parquet", "hypotheses").reset_index(drop=True)
    if len(ha) != len(hb):
        return f"design/hypotheses.parquet has {len(ha)} vs {len(hb)} hypotheses"
    if list(ha.columns) != list(hb.columns) or not ha.equals(hb):
        return "design/hypotheses.parquet differs (subgroups, doses or bounds)"
    for name in DESIGN_FILES[1:]:
        if read_json(a / name) != read_json(b / name):
            return f"design/{name} differs"
    return None


def verdicts(results: pd.DataFrame) -> pd.DataFrame:
    """Per (method, hyp_id): kind, outcome, t, each side's p-value (p_lo, p_up), the side
    with the smaller one (``side``: lo on a tie) and rejected (either side)."""
    key = ["method", "hyp_id"]
    out = results.drop_duplicates(key).set_index(key)[["kind", "outcome", "t"]].sort_index()
    p = results.pivot_table(index=key, columns="side", values="p_value", aggfunc="min")
    out["p_lo"], out["p_up"] = p["lo"], p["up"]
    out["side"] = np.where(out["p_up"] < out["p_lo"], "up", "lo")
    out["rejected"] = results.groupby(key, sort=True)["rejected"].any()
    return out


def changes(res_a: pd.DataFrame, res_b: pd.DataFrame) -> pd.DataFrame:
    """The hypotheses whose verdict differs, per method both tables hold: columns method,
    hyp_id, kind, outcome, t, change (``NEWLY_REJECTED``: rejected by B, not by A;
    ``NEWLY_PASSING``: the reverse), side (the side the rejecting twin's smaller p-value is
    on) and p_a, p_b (A's and B's p-value on that side), sorted by outcome, hour, hyp_id,
    method."""
    va, vb = verdicts(res_a), verdicts(res_b)
    methods = sorted(set(va.index.get_level_values("method"))
                     & set(vb.index.get_level_values("method")))
    for m in methods:
        ids_a, ids_b = (set(v.loc[m].index) for v in (va, vb))
        if ids_a != ids_b:
            raise ContractError(f"method {m}: A and B tested different hypotheses "
                                f"({len(ids_a)} vs {len(ids_b)}, {len(ids_a ^ ids_b)} in one "
                                "only): not one design")
    va = va[va.index.get_level_values("method").isin(methods)]
    j = va.join(vb[["p_lo", "p_up", "side", "rejected"]].add_suffix("_b"), how="inner")
    newly_rej = j["rejected_b"] & ~j["rejected"]
    newly_pass = j["rejected"] & ~j["rejected_b"]
    j["change"] = np.select([newly_rej, newly_pass], [NEWLY_REJECTED, NEWLY_PASSING], "")
    j = j[j["change"] != ""].copy()
    j["side"] = np.where(j["change"] == NEWLY_REJECTED, j["side_b"], j["side"])
    up = (j["side"] == "up").to_numpy()
    j["p_a"] = np.where(up, j["p_up"], j["p_lo"])
    j["p_b"] = np.where(up, j["p_up_b"], j["p_lo_b"])
    cols = ["method", "hyp_id", "kind", "outcome", "t", "change", "side", "p_a", "p_b"]
    out = j.reset_index()[cols]
    return out.sort_values(["outcome", "t", "hyp_id", "method"], kind="stable") \
        .reset_index(drop=True)


def _p(v: float) -> str:
    return f"{v:.3g}"


def _rows_by_hyp(results: pd.DataFrame) -> pd.DataFrame:
    return results.drop_duplicates("hyp_id").set_index("hyp_id")


def report(a: Side, b: Side, sizes: bool = True) -> tuple[str, int]:
    """(the text ``python -m twinfalsify.diff`` prints, its exit status 0 or 1). sizes:
    add each side's unclipped sizes where the study's files are there."""
    why = design_difference(a.results_dir, b.results_dir)
    if why is not None:
        raise ContractError(f"{a.results_dir} and {b.results_dir} have different designs "
                            f"({why}): a diff compares twins on one design")
    ch = changes(a.results, b.results)
    methods_a, methods_b = (set(s.results["method"]) for s in (a, b))
    common = sorted(methods_a & methods_b)
    if not common:
        raise ContractError(f"A tested with {', '.join(sorted(methods_a))}, B with "
                            f"{', '.join(sorted(methods_b))}: no method in common")
    n_hyp = a.results["hyp_id"].nunique()
    lines = [f"A: twin {a.twin} of {a.results_dir}", f"B: twin {b.twin} of {b.results_dir}",
             f"one design: {n_hyp} hypotheses; compared per method ({', '.join(common)}), a "
             "hypothesis rejected when either side H_lo, H_up is"]
    for label, only in (("A", methods_a - methods_b), ("B", methods_b - methods_a)):
        if only:
            lines.append(f"not compared: {', '.join(sorted(only))} (only in {label})")
    for m in common:
        conf = [{(str(r.correction), float(r.alpha)) for r in
                 s.results[s.results["method"] == m].drop_duplicates(["correction", "alpha"])
                 .itertuples()} for s in (a, b)]
        if conf[0] != conf[1]:
            words = [", ".join(f"{c} at alpha {al:g}" for c, al in sorted(x)) for x in conf]
            lines.append(f"note: {m} corrected with {words[0]} in A, {words[1]} in B")
    sized = ({s.label: study_sizes(s.results_dir, s.twin) for s in (a, b)}
             if sizes and len(ch) else {})
    rows = {s.label: _rows_by_hyp(s.results) for s in (a, b)}
    for what, who in ((NEWLY_REJECTED, "rejected by B, not by A"),
                      (NEWLY_PASSING, "rejected by A, not by B")):
        part = ch[ch["change"] == what]
        n = part["hyp_id"].nunique()
        lines += ["", f"{what} ({who}): {n} hypothes{'is' if n == 1 else 'es'}"
                  if n else f"{what} ({who}): none"]
        for (outcome, t), group in part.groupby(["outcome", "t"], sort=False):
            unit = FEATURE_BY_NAME[str(outcome)].unit
            lines.append(f"  {outcome} at hour {int(t)}")
            for hyp_id, hg in group.groupby("hyp_id", sort=False):
                by = "; ".join(f"{m.method} (H_{m.side}: A p = {_p(m.p_a)}, B p = "
                               f"{_p(m.p_b)})" for m in hg.itertuples())
                lines.append(f"    hypothesis {int(hyp_id)} ({hg['kind'].iloc[0]}), "
                             f"{what} under {by}")
                for s in (a, b):
                    lines.append(f"      {s.name()}: "
                                 f"{mean_in_words(rows[s.label].loc[hyp_id], unit)}")
                    sz = sized.get(s.label)
                    if sz is not None and hyp_id in sz.index:
                        if words := sizes_in_words(sz.loc[hyp_id], unit):
                            lines.append("      " + words.strip())
    per = []
    for m in common:
        mine = ch[ch["method"] == m]
        both = int((verdicts(a.results).loc[m]["rejected"]
                    & verdicts(b.results).loc[m]["rejected"]).sum())
        per.append(f"{m}: {int((mine['change'] == NEWLY_REJECTED).sum())} newly rejected, "
                   f"{int((mine['change'] == NEWLY_PASSING).sum())} newly passing, {both} "
                   "rejected by both")
    n_rej = ch.loc[ch["change"] == NEWLY_REJECTED, "hyp_id"].nunique()
    n_pass = ch.loc[ch["change"] == NEWLY_PASSING, "hyp_id"].nunique()
    lines += ["", f"summary: {n_rej} newly rejected, {n_pass} newly passing of {n_hyp} "
              f"hypotheses ({'; '.join(per)})"]
    if len(ch):
        lines.append(f"one hypothesis in full: python -m twinfalsify.explain "
                     f"{b.results_dir} HYP_ID --twin {b.twin}")
    return "\n".join(lines), 1 if n_rej else 0


class _Parser(argparse.ArgumentParser):
    """Bad arguments end in one line (``io.cli_main``), not argparse's usage block."""

    def error(self, message: str) -> NoReturn:
        raise ContractError(f"{message} (usage: python -m twinfalsify.diff RESULTS TWIN_A "
                            "TWIN_B [--results-b RESULTS_B])")


def main(argv: Sequence[str] | None = None) -> int:
    parser = _Parser(prog="python -m twinfalsify.diff",
                     description="Compare two twins, or two versions of one twin, on one "
                                 "design: hypotheses newly rejected and newly passing.")
    parser.add_argument("results", help="the study's results folder (results/<study>)")
    parser.add_argument("twin_a", help="twin A (the reference, e.g. the released version)")
    parser.add_argument("twin_b", help="twin B (e.g. the new version)")
    parser.add_argument("--results-b", help="read twin B from this results folder (a study "
                                            "with the same design); default: RESULTS")
    parser.add_argument("--no-sizes", action="store_true",
                        help="skip the unclipped sizes (no reading of the twins' runs)")
    args = parser.parse_args(argv)
    a = Side.read("A", args.results, args.twin_a)
    b = Side.read("B", args.results_b or args.results, args.twin_b)
    if a.results_dir.resolve() == b.results_dir.resolve() and a.twin == b.twin:
        raise ContractError(f"A and B are both twin {a.twin} of {a.results_dir}: name two "
                            "twins, or give --results-b")
    text, status = report(a, b, sizes=not args.no_sizes)
    print(text)
    return status


if __name__ == "__main__":
    from twinfalsify.io import cli_main

    sys.exit(cli_main(lambda: main(), "twinfalsify.diff"))
