"""The product rule of adaptive mode (inference.product): an exact (conservative) inf over m,
agreement with the union rule's capitals, validity and power against the union rule."""

from __future__ import annotations

import numpy as np
import pytest
from test_sequential import _side, _state, _world, concat_worlds

from twinfalsify.inference.betting import log_capital
from twinfalsify.inference.multiple_testing import correct
from twinfalsify.inference.product import (
    grid,
    mirrored,
    obs_cell_capital,
    product_stat,
    twin_grid,
)
from twinfalsify.inference.sequential import FUTILE, REJECTED, SequentialState


def _running(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mu_{i-1}, sigma2_{i-1}) before each value, by a plain loop (mu_0 = 1/2, s2_0 = 1/4)."""
    mus, s2s, mu_prev, s2_prev, tot, dev = [], [], 0.5, 0.25, 0.0, 0.0
    for t, xi in enumerate(x, 1):
        mus.append(mu_prev)
        s2s.append(s2_prev)
        tot += xi
        mu_t = (0.5 + tot) / (t + 1)
        dev += (xi - mu_t) ** 2
        mu_prev, s2_prev = mu_t, (0.25 + dev) / (t + 1)
    return np.array(mus), np.array(s2s)


def _obs_capital_at(x: np.ndarray, bet_at: float, m: float, c: float = 0.9) -> float:
    """log K+_n(m) of one sample with the aGRAPA bets of the point ``bet_at``."""
    mu, s2 = _running(x)
    logk = 0.0
    for xi, mu_i, s2_i in zip(x, mu, s2, strict=True):
        d = mu_i - bet_at
        lam = min(max(d / (s2_i + d * d), 0.0), c / bet_at)
        logk += np.log1p(lam * (xi - m))
    return logk


def test_obs_cell_capital_matches_a_loop():
    rng = np.random.default_rng(11)
    groups = [rng.beta(2, 3, n) for n in (0, 1, 7, 40)]
    offs = np.concatenate([[0], np.cumsum([len(g) for g in groups])]).astype(np.int64)
    mg = grid(8)
    left, right = obs_cell_capital(np.concatenate(groups), offs, mg)
    for i, g in enumerate(groups):
        np.testing.assert_allclose(right[i], [_obs_capital_at(g, m, m) for m in mg[1:]],
                                   atol=1e-10)
        np.testing.assert_allclose(left[i], [_obs_capital_at(g, b, a)
                                             for a, b in zip(mg[:-1], mg[1:], strict=True)],
                                   atol=1e-10)


def test_twin_grid_matches_log_capital():
    rng = np.random.default_rng(12)
    x = rng.beta(2, 5, (30, 50))
    x[3] = 0.0  # one group entirely at the bottom: capital grows without bound in m
    side = _side(x, 1e-3)
    mg = grid(16)
    run_max, end = twin_grid(side, mg)
    for k, m in enumerate(mg):
        mm = np.full(30, m)
        np.testing.assert_allclose(run_max[:, k], log_capital(side, mm, -1, True), atol=1e-9)
        np.testing.assert_allclose(end[:, k], log_capital(side, mm, -1, False), atol=1e-9)
    # the mirror: K+ at m of x is K- at 1 - m of 1 - x
    up, _ = twin_grid(mirrored(side), mg)
    for k, m in enumerate(mg[:-1]):
        np.testing.assert_allclose(up[:, k], log_capital(side, np.full(30, 1 - m), +1, True),
                                   atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cell_bound_never_exceeds_the_inf_over_m(seed):
    """Brute force: on a fine grid, with each cell's own bets, G(m) K(m) is never below the
    bound (the reported p is never smaller than the exact one); more sub-steps or cells
    give a tighter bound."""
    rng = np.random.default_rng(seed)
    xo = rng.beta(3, 3, 200)  # observational sample around 0.5
    xt = rng.beta(2, 4, 60)  # twin around 1/3
    tw = _side(xt[None, :], 1e-3)
    one = np.array([0, len(xo)])
    cells = 16
    mg = grid(cells)
    fine = []
    for k in range(cells):
        for m in np.linspace(mg[k], mg[k + 1], 41):
            fine.append(_obs_capital_at(xo, mg[k + 1], m)
                        + log_capital(tw, np.array([m]), -1, True)[0])
    exact = min(fine)
    gl, gr = obs_cell_capital(xo, one, mg)
    bounds = [product_stat(gl, gr, twin_grid(tw, grid(cells, sub))[0])[0] for sub in (1, 4, 16)]
    assert bounds[0] <= bounds[1] <= bounds[2] <= exact + 1e-9
    assert exact - bounds[2] < 0.25 * (exact - bounds[0]) + 1e-6
    assert exact - bounds[2] < 0.5


def _mixed_world(rng, h=400, m=500):
    return concat_worlds([_world(h // 4, 300, m, 0.45, tm, 0.8, rng, b0_frac=0.4)
                          for tm in (0.2, 0.3, 0.38, 0.5)])


def test_product_futility_never_loses_a_rejection_and_rejects_more_than_union():
    rng = np.random.default_rng(13)
    hyps, obs, runs = _mixed_world(rng)
    h, m = len(hyps), runs.in_b0.shape[1]
    nf = np.full(h, 2 * h)
    seq = _state(hyps, obs, runs, m, 25, n_family=nf, combine="product")
    full = _state(hyps, obs, runs, m, m, n_family=nf, holm_aware=False, combine="product")
    p_full_lo, p_full_up, _ = full.p_values(runs)
    p_lo, p_up, _ = seq.p_values(runs)
    dec = seq.side
    assert (dec == REJECTED).sum() > 20 and (dec == FUTILE).sum() > 20
    lvl = seq.fut_level
    for col, pf in ((0, p_full_lo), (1, p_full_up)):
        fut = dec[:, col] == FUTILE
        assert np.all(pf[fut] > lvl[fut, col])
    holm_full = correct(np.concatenate([p_full_lo, p_full_up]), 0.05, "holm").reshape(2, -1).T
    assert not holm_full[dec == FUTILE].any()
    a_star = 0.05 / nf[0]
    assert np.all(p_lo[dec[:, 0] == REJECTED] <= a_star)
    assert np.all(p_full_lo[dec[:, 0] == REJECTED] <= a_star * (1 + 1e-9))
    assert seq.runs_used().mean() < 0.9 * m
    # power: at the full budget the product rule rejects more than the union rule here,
    # where both samples are uncertain (each side sees the whole gap)
    union = _state(hyps, obs, runs, m, m, n_family=nf, holm_aware=False)
    u_lo, u_up, _ = union.p_values(runs)
    n_prod = correct(np.concatenate([p_full_lo, p_full_up]), 0.05, "holm").sum()
    n_union = correct(np.concatenate([u_lo, u_up]), 0.05, "holm").sum()
    assert n_prod > 1.1 * n_union > 0


def test_bad_combine_raises():
    rng = np.random.default_rng(5)
    hyps, obs, _ = _world(3, 20, 10, 0.4, 0.4, 1.0, rng)
    with pytest.raises(ValueError, match="combine must be one of union, product"):
        SequentialState(hyps, obs, None, budget=10, batch_size=5, combine="sum")
    with pytest.raises(ValueError, match="grid cells and sub-steps"):
        SequentialState(hyps, obs, None, budget=10, batch_size=5, combine="product",
                        grid_cells=0)
