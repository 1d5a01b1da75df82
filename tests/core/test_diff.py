"""python -m twinfalsify.diff: two twins on one design, newly rejected and newly passing."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers.paths import ROOT  # noqa: E402

from twinfalsify.diff import NEWLY_PASSING, NEWLY_REJECTED, changes, main
from twinfalsify.schema import FEATURE_BY_NAME, ContractError

METHODS = ("hoeffding", "betting")


def results_table(rejected: np.ndarray, p: np.ndarray, outcomes: list[str]) -> pd.DataFrame:
    """A results table as the tests rule writes it: rejected and p of shape (H, methods, 2
    sides); the means inside the bounds."""
    h = rejected.shape[0]
    rows = []
    for k in range(h):
        for j, m in enumerate(METHODS):
            for s, side in enumerate(("lo", "up")):
                rows.append({"hyp_id": 10 + k, "kind": "causal", "outcome": outcomes[k],
                             "t": 1 + k % 3, "side": side, "method": m, "n": 50,
                             "n_follow": 20, "nhat": 100, "n_failed": 0,
                             "failed_runs": "conservative", "y_lo": 60.0, "y_up": 120.0,
                             "q_lo_hat": 80.0, "q_up_hat": 95.0, "q_twin_hat": 90.0 + k,
                             "q_obs_hat": 88.0, "propensity": 0.4,
                             "p_value": float(p[k, j, s]), "p_floor": False,
                             "rejected": bool(rejected[k, j, s]), "correction": "holm",
                             "alpha": 0.05})
    return pd.DataFrame(rows)


def random_pair(seed: int, h: int = 40) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    outcomes = list(rng.choice(["HR", "MeanBP", "SysBP"], size=h))
    out = []
    for _ in range(2):
        rej = rng.random((h, len(METHODS), 2)) < 0.2
        p = np.where(rej, rng.uniform(0, 0.01, rej.shape), rng.uniform(0.02, 1, rej.shape))
        out.append(results_table(rej, p, outcomes))
    return out[0], out[1]


def rejected_set(res: pd.DataFrame) -> set[tuple[str, int]]:
    """(method, hyp_id) rejected on either side, straight from the rows."""
    return {(str(r.method), int(r.hyp_id)) for r in res[res["rejected"]].itertuples()}


@pytest.mark.parametrize("seed", range(5))
def test_newly_rejected_and_passing_are_the_set_differences(seed):
    a, b = random_pair(seed)
    ch = changes(a, b)
    rows = list(zip(ch["method"], ch["hyp_id"], ch["change"], strict=True))
    got_rej = {(m, int(h)) for m, h, c in rows if c == NEWLY_REJECTED}
    got_pass = {(m, int(h)) for m, h, c in rows if c == NEWLY_PASSING}
    ra, rb = rejected_set(a), rejected_set(b)
    assert got_rej == rb - ra and got_pass == ra - rb
    assert got_rej and got_pass  # the random tables hold both kinds of change
    # each change shows the rejecting twin's rejected side and both p-values on it
    for r in ch.itertuples():
        by = b if r.change == NEWLY_REJECTED else a
        row = by[(by["method"] == r.method) & (by["hyp_id"] == r.hyp_id)
                 & (by["side"] == r.side)]
        assert bool(row["rejected"].iloc[0])
        for res, p in ((a, r.p_a), (b, r.p_b)):
            assert p == res[(res["method"] == r.method) & (res["hyp_id"] == r.hyp_id)
                             & (res["side"] == r.side)]["p_value"].iloc[0]
    # grouped per outcome and hour
    keys = list(zip(ch["outcome"], ch["t"], ch["hyp_id"], strict=True))
    assert keys == sorted(keys)
    # swapping A and B swaps the two lists
    back = changes(b, a)
    assert len(back) == len(ch)
    assert (back["change"] == NEWLY_REJECTED).sum() == (ch["change"] == NEWLY_PASSING).sum()


def test_same_tables_no_change():
    a, _ = random_pair(1)
    assert changes(a, a.copy()).empty


def test_different_hypotheses_are_refused():
    a, b = random_pair(2)
    with pytest.raises(ContractError, match="tested different hypotheses"):
        changes(a, b[b["hyp_id"] != 10])


def write_study(r: Path, twins: dict[str, pd.DataFrame], hyps: pd.DataFrame) -> Path:
    (r / "design").mkdir(parents=True)
    hyps.to_parquet(r / "design" / "hypotheses.parquet")
    (r / "design" / "bins.json").write_text(json.dumps({"age_edges": [50.0, 64.0, 75.0]}))
    (r / "design" / "actions.json").write_text(json.dumps({"iv_edges": [1.0, 2.0, 3.0]}))
    for name, res in twins.items():
        (r / "twins" / name).mkdir(parents=True)
        res.to_parquet(r / "twins" / name / "results.parquet")
    return r


def hyps_of(res: pd.DataFrame) -> pd.DataFrame:
    h = res.drop_duplicates("hyp_id")[["hyp_id", "kind", "outcome", "t", "y_lo", "y_up"]]
    return h.reset_index(drop=True)


def test_exit_statuses_and_the_report(tmp_path, capsys):
    a, b = random_pair(3)
    none = a.assign(rejected=False)
    r = write_study(tmp_path / "s", {"a": a, "b": b, "none": none}, hyps_of(a))
    assert main([str(r), "a", "b"]) == 1
    out = capsys.readouterr().out
    ch = changes(a, b)
    n_rej = ch.loc[ch["change"] == NEWLY_REJECTED, "hyp_id"].nunique()
    n_pass = ch.loc[ch["change"] == NEWLY_PASSING, "hyp_id"].nunique()
    assert f"summary: {n_rej} newly rejected, {n_pass} newly passing of 40 hypotheses" in out
    first = ch[ch["change"] == NEWLY_REJECTED].iloc[0]
    assert f"  {first['outcome']} at hour {first['t']}\n" in out
    assert f"    hypothesis {first['hyp_id']} (causal), newly rejected under " in out
    # both sides' means in explain's words
    q = 90.0 + first["hyp_id"] - 10
    unit = FEATURE_BY_NAME[first["outcome"]].unit
    assert f"      A a: mean (clipped) {q:.4g} {unit} from n_hat = 100 runs" in out
    assert "data bounds [80, 95]" in out and "inside the bounds" in out
    # only newly passing: 0 (no regression); nothing changed: 0
    assert main([str(r), "a", "none"]) == 0
    assert "newly rejected (rejected by B, not by A): none" in capsys.readouterr().out
    assert main([str(r), "none", "a"]) == 1
    assert "newly passing (rejected by A, not by B): none" in capsys.readouterr().out


def test_command_line_exit_codes_and_one_line_errors(tmp_path):
    a, b = random_pair(4)
    r = write_study(tmp_path / "s", {"a": a, "b": b}, hyps_of(a))
    r2 = write_study(tmp_path / "s2", {"b": b}, hyps_of(a))  # same design, another folder
    env = {"PYTHONPATH": str(ROOT / "src")}

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "twinfalsify.diff", *map(str, args)],
                              capture_output=True, text=True, env=env, timeout=120)

    assert run(r, "a", "b").returncode == 1
    assert run(r, "b", "b", "--results-b", r2).returncode == 0  # same design, same twin
    same = run(r, "a", "a", "--results-b", r2.parent / "s")  # A is B
    assert same.returncode == 2 and "both twin a" in same.stderr
    for bad, words in (((r, "a", "zz"), "no twin 'zz' with results (found a, b)"),
                       ((r, "a"), "the following arguments are required: twin_b"),
                       ((tmp_path / "nope", "a", "b"), "no design/hypotheses.parquet")):
        p = run(*bad)
        assert p.returncode == 2 and p.stdout == "", p.stderr
        assert len(p.stderr.strip().splitlines()) == 1 and words in p.stderr, p.stderr
        assert p.stderr.startswith("twinfalsify.diff: error: ")
    # another design: refused in one line, whichever file differs
    other = hyps_of(a).assign(y_up=lambda h: h["y_up"] + 1)
    r3 = write_study(tmp_path / "s3", {"b": b}, other)
    p = run(r, "a", "b", "--results-b", r3)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1
    assert "have different designs (design/hypotheses.parquet differs" in p.stderr
    r4 = write_study(tmp_path / "s4", {"b": b}, hyps_of(a))
    (r4 / "design" / "bins.json").write_text(json.dumps({"age_edges": [50.0, 65.0, 75.0]}))
    p = run(r, "a", "b", "--results-b", r4)
    assert p.returncode == 2 and "(design/bins.json differs)" in p.stderr
    r5 = write_study(tmp_path / "s5", {"b": b}, hyps_of(a).head(30))
    p = run(r, "a", "b", "--results-b", r5)
    assert p.returncode == 2 and "has 40 vs 30 hypotheses" in p.stderr


def test_oracle_against_biased_on_the_test_study(test_study, tmp_path):
    """config/test.yaml: the biased twin (HR + 25 /min) against the oracle. Every newly
    rejected hypothesis is an HR one the biased twin's results reject, the exit status is
    1, and each side's unclipped size comes from the study's stored runs."""
    work, _ = test_study
    r = work / "results" / "test"
    res = {t: pd.read_parquet(r / "twins" / t / "results.parquet")
           for t in ("oracle", "biased")}
    want = rejected_set(res["biased"]) - rejected_set(res["oracle"])
    assert want  # the study shows a change
    p = subprocess.run([sys.executable, "-m", "twinfalsify.diff", str(r), "oracle", "biased"],
                       capture_output=True, text=True, timeout=300,
                       env={"PYTHONPATH": str(ROOT / "src")})
    assert p.returncode == 1, p.stderr
    hyps = {h for _, h in want}
    assert f"summary: {len(hyps)} newly rejected" in p.stdout
    for h in hyps:
        assert f"    hypothesis {h} (" in p.stdout
    assert "above the upper bound" in p.stdout and "unclipped: twin mean" in p.stdout
    # a second study folder with the same design: the biased twin against itself
    copy = tmp_path / "again"
    shutil.copytree(r / "design", copy / "design")
    shutil.copytree(r / "twins" / "biased", copy / "twins" / "biased",
                    ignore=shutil.ignore_patterns("shards", "figures"))
    same = subprocess.run([sys.executable, "-m", "twinfalsify.diff", str(r), "biased",
                           "biased", "--results-b", str(copy)], capture_output=True,
                          text=True, timeout=300, env={"PYTHONPATH": str(ROOT / "src")})
    assert same.returncode == 0, same.stderr
    assert "summary: 0 newly rejected, 0 newly passing" in same.stdout
