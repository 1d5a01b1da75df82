"""Sensitivity sweep over Delta: agreement with a direct run, monotonicity, table shape, figure."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers.reference import resample_sums_reference

from twinfalsify.inference.hoeffding import hoeffding_test
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.samples import HypothesisSamples, Ragged
from twinfalsify.inference.sensitivity import sensitivity_sweep, sweep_pvalues, widened


def _case(seed=0, h=120):
    rng = np.random.default_rng(seed)
    n = rng.integers(200, 2000, h)
    nf = (n * rng.uniform(0.6, 1, h)).astype(int)
    nh = rng.integers(200, 1000, h)
    shift = rng.uniform(-3, 3, h)
    # outcomes inside [y_lo, y_up] = [60, 100] so widening never changes the clipping
    follow = Ragged.from_groups([rng.uniform(65, 95, k) for k in nf])
    twin = Ragged.from_groups([np.clip(rng.uniform(65, 95, k) + 8 * shift[i], 60, 100)
                               for i, k in enumerate(nh)])
    s = HypothesisSamples(np.full(h, 60.0), np.full(h, 100.0), n.astype(np.int64), follow, twin)
    return s, np.array(["hr", "map", "rr"])[np.arange(h) % 3]


def test_delta_zero_matches_direct_run_and_counts_per_group():
    s, g = _case()
    t = sensitivity_sweep(s, [0.0], {"hoeffding": hoeffding_test}, group=g)
    p_lo, p_up = hoeffding_test(s)
    rej = correct(np.concatenate([p_lo, p_up]), 0.05, "holm")
    per = rej[: len(s)].astype(int) + rej[len(s):]
    for grp in ("hr", "map", "rr"):
        row = t[t.group == grp].iloc[0]
        assert row.n_rejected == per[g == grp].sum()
        assert row.n_hypotheses == 2 * (g == grp).sum()
    assert t.n_rejected.sum() > 0


def test_rejections_fall_as_the_range_widens():
    s, g = _case(seed=1)
    deltas = [0.0, 0.1, 0.2, 0.4, 0.8]
    t = sensitivity_sweep(s, deltas, {"hoeffding": hoeffding_test}, correction="by")
    counts = t.sort_values("delta").n_rejected.to_numpy()
    assert counts[0] > counts[-1] and np.all(np.diff(counts) <= 0)
    w = widened(s, 0.2)
    np.testing.assert_allclose(w.y_lo, 60 * 0.9)
    np.testing.assert_allclose(w.y_up, 100 * 1.1)


def test_bad_input_and_table_shape():
    s, g = _case(h=9)
    with pytest.raises(ValueError, match="group"):
        sensitivity_sweep(s, [0.0], {"h": hoeffding_test}, group=g[:3])
    with pytest.raises(ValueError, match="family"):
        sensitivity_sweep(s, [0.0], {"h": hoeffding_test}, family=g[:3])
    with pytest.raises(ValueError, match="empty range"):
        widened(s, -3.0)
    t = sensitivity_sweep(s, [0.0, 0.5], {"h": hoeffding_test, "h4": lambda x: hoeffding_test(
        x, factor=4)}, group=g)
    assert list(t.columns) == ["delta", "method", "family", "group", "n_hypotheses",
                               "n_rejected"]
    assert len(t) == 2 * 2 * 3


def _with_failures(seed=3, h=60):
    """Samples with failed runs at their places and values that cross the bounds (clipping
    moves with Delta)."""
    rng = np.random.default_rng(seed)
    n = rng.integers(100, 400, h)
    nf = (n * rng.uniform(0.5, 1, h)).astype(int)
    follow = Ragged.from_groups([rng.uniform(55, 105, k) for k in nf])
    m = 150
    twin_groups, run_groups, fail_groups = [], [], []
    for _ in range(h):
        runs = rng.permutation(m)
        k_ok, k_fail = int(rng.integers(30, 120)), int(rng.integers(0, 8))
        ok = np.sort(runs[:k_ok])
        twin_groups.append(rng.uniform(50, 110, k_ok) + rng.uniform(-15, 15))
        run_groups.append(ok)
        fail_groups.append(np.sort(runs[k_ok:k_ok + k_fail]))
    s = HypothesisSamples(
        np.full(h, 60.0), np.full(h, 100.0), n.astype(np.int64), follow,
        Ragged.from_groups(twin_groups), keys=np.arange(h) * 7 + 3,
        follow_pos=Ragged.from_groups([np.sort(rng.choice(n[i], nf[i], replace=False))
                                       for i in range(h)]),
        twin_run=Ragged.from_groups(run_groups), failed_run=Ragged.from_groups(fail_groups),
    )  # fmt: skip
    return s, s.failed_run.sizes.astype(np.int64)


@pytest.mark.parametrize("failed_runs", ["conservative", "drop"])
def test_delta_zero_equals_run_tests_with_failed_runs(failed_runs):
    """At Delta = 0 the sweep gives exactly the main analysis' decisions, failed runs
    included (conservative: at their places), for every method and each family."""
    from twinfalsify.falsify import make_methods, run_tests

    s, f = _with_failures()
    assert f.sum() > 0
    h = len(s)
    kind = np.where(np.arange(h) % 2, "causal", "manski")
    outcome = np.array(["HR", "MeanBP", "SysBP"])[np.arange(h) % 3]
    hyps = pd.DataFrame({"hyp_id": np.arange(h), "kind": kind, "outcome": outcome, "t": 1})
    methods = make_methods({"hoeffding": {}, "betting": {}, "bootstrap": {"min_n": 10}}, 5)
    res = run_tests(hyps, s, f, methods, alpha=0.2, correction="holm", failed_runs=failed_runs)
    sweep = sensitivity_sweep(s, [0.0, 0.1], methods, 0.2, "holm", group=outcome,
                              n_failed=f, failed_runs=failed_runs, family=kind)
    want = res.groupby(["method", "kind", "outcome"])["rejected"].sum()
    got = sweep[sweep["delta"] == 0.0].set_index(["method", "family", "group"])["n_rejected"]
    assert want.sum() > 0
    for key, n_rej in want.items():
        assert got[key] == n_rej, key


def test_sweep_equals_one_call_per_widening_bit_for_bit():
    """The sweep reuses the data order across widenings (betting.order_cache): every p-value
    equals a separate call's, bit for bit, and the widenings do change them."""
    from functools import partial

    from twinfalsify.inference.betting import betting_test
    from twinfalsify.inference.failures import failure_pvalues

    s, f = _with_failures(seed=4, h=40)
    deltas = [0.0, 0.02, 0.1, 0.3]
    m = partial(betting_test, alpha=0.05)
    p_lo, p_up = sweep_pvalues(m, s, f, deltas, "conservative")
    for j, d in enumerate(deltas):
        lo, up = failure_pvalues(m, widened(s, d), f, "conservative")
        np.testing.assert_array_equal(p_lo[j], lo)
        np.testing.assert_array_equal(p_up[j], up)
    assert not np.allclose(p_lo[0], p_lo[-1])


def _emptied(r: Ragged, groups: list[int]) -> Ragged:
    return Ragged.from_groups([np.zeros(0) if i in groups else r.group(i) for i in range(len(r))])


@pytest.mark.parametrize("failed_runs", ["conservative", "drop"])
def test_sweep_bootstrap_equals_one_call_per_widening_bit_for_bit(failed_runs, monkeypatch):
    """The bootstrap's p-values at every Delta are a separate call's on the widened samples,
    and the reference draws' (``test_bootstrap``), bit for bit: hypotheses with n = 0 and
    nhat = 0 (with and without failed runs) included, and the widenings do change them."""
    from dataclasses import replace
    from functools import partial

    from twinfalsify.inference import bootstrap
    from twinfalsify.inference.bootstrap import bootstrap_test
    from twinfalsify.inference.failures import failure_pvalues

    s, f = _with_failures(seed=6, h=40)
    no_obs, no_twin = [0, 1], [2, 3]
    s = replace(s, n=np.where(np.isin(np.arange(len(s)), no_obs), 0, s.n),
                follow=_emptied(s.follow, no_obs), follow_pos=_emptied(s.follow_pos, no_obs),
                twin=_emptied(s.twin, no_twin), twin_run=_emptied(s.twin_run, no_twin))
    assert (s.n[no_obs] == 0).all() and (s.nhat[no_twin] == 0).all() and f[no_twin].any()
    deltas = [0.0, 0.02, 0.1, 0.3]
    m = partial(bootstrap_test, n_resamples=60, min_n=10, seed=9)
    p_lo, p_up = sweep_pvalues(m, s, f, deltas, failed_runs)
    monkeypatch.setattr(bootstrap, "_resample_sums", resample_sums_reference)
    for j, d in enumerate(deltas):
        lo, up = failure_pvalues(m, widened(s, d), f, failed_runs)
        assert np.array_equal(p_lo[j], lo) and np.array_equal(p_up[j], up)
    assert (p_lo[:, no_obs + (no_twin if failed_runs == "drop" else [])] == 1).all()
    assert not np.array_equal(p_lo[0], p_lo[-1]) and (p_lo < 1).any()
