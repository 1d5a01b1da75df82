"""The capital of a bet on a bounded mean: ordered sides, plug-in bets, log capital,
the crossing of two capitals and the level bound (Waudby-Smith & Ramdas 2024).

The formulas, assumptions and references are in :mod:`twinfalsify.inference.betting`'s
docstring, the test that uses these kernels; the sequential mode
(:mod:`twinfalsify.inference.sequential`) uses them too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

C_TRUNC = 0.9  # WSR suggest 1/2 or 3/4; 0.9 measured tighter at Holm-size levels (docs)
STAR_R0 = 0.5  # r0: the need (nats) below which a STaR bet decays exponentially (star_log_capital)


@dataclass
class StarBets:
    """What a target-recalculating bet reads besides the values (:func:`star_bets`).

    ``sig2``: the predictable plug-in variance sigma2_{i-1} before every value (N,);
    ``target``: log(1/delta0)
    per group (G,). ``order``: the groups by decreasing size (built once, for the kernel).
    """

    sig2: np.ndarray
    target: np.ndarray
    order: np.ndarray | None = None

@dataclass
class OrderedSide:
    """One side's rescaled sample of many hypotheses, ordered, with its bets (flat arrays).

    ``copies`` K > 1: the side holds K independently ordered copies of G groups, copy-major
    (group k G + g is copy k of group g); :func:`log_capital` then returns, per group, the
    log of the *average over the copies* of the terminal capital (module doc, "Order").
    """

    x: np.ndarray  # (N,) values in [0, 1], group after group
    lam: np.ndarray | None  # (N,) plug-in bets lambda_i (before the m-dependent truncation);
    # None with target-recalculating bets, which are formed from ``star`` for each m
    offsets: np.ndarray  # (K G + 1,)
    copies: int = 1
    star: StarBets | None = None  # target-recalculating bets (then ``lam`` is None)

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def n_groups(self) -> int:
        """G: groups per copy."""
        return (len(self.offsets) - 1) // self.copies

    def take(self, groups: np.ndarray) -> OrderedSide:
        """The listed groups (sorted indices, every copy), compacted."""
        g = self.n_groups
        rows = (np.arange(self.copies)[:, None] * g + np.asarray(groups)[None, :]).ravel()
        keep = np.repeat(np.isin(np.arange(len(self.offsets) - 1), rows), self.sizes)
        sizes = self.sizes[rows]
        star = None if self.star is None else StarBets(
            self.star.sig2[keep], self.star.target[rows])
        return OrderedSide(
            self.x[keep], None if self.lam is None else self.lam[keep],
            np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            self.copies, star,
        )


def segment_cumsum(v: np.ndarray, offsets: np.ndarray, gid: np.ndarray) -> np.ndarray:
    """Cumulative sums restarting at every group start (gid: group of every element)."""
    cs = np.cumsum(v)
    base = np.concatenate([[0.0], cs])[offsets[:-1]]
    return cs - base[gid]


def flat_layout(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(group id, 1-based position in its group) of every element of a flat layout."""
    sizes = np.diff(offsets)
    gid = np.repeat(np.arange(len(sizes)), sizes)
    t = np.arange(offsets[-1]) - offsets[:-1][gid] + 1
    return gid, t


def running_moments(
    x: np.ndarray, offsets: np.ndarray, layout: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Predictable plug-in moments per group: (mu_{i-1}, sigma2_{i-1}) before each value, with
    mu_t = (1/2 + sum_{j<=t} x_j) / (t + 1), sigma2_t = (1/4 + sum_{j<=t} (x_j - mu_j)^2) /
    (t + 1) (WSR 2024, eq. 26-27), so mu_0 = 1/2 and sigma2_0 = 1/4 at every group start."""
    gid, t = flat_layout(offsets) if layout is None else layout
    mu = (0.5 + segment_cumsum(x, offsets, gid)) / (t + 1)
    sig2 = (0.25 + segment_cumsum((x - mu) ** 2, offsets, gid)) / (t + 1)
    starts = offsets[:-1][np.diff(offsets) > 0]
    mu_prev, sig2_prev = np.empty_like(mu), np.empty_like(sig2)
    mu_prev[1:], sig2_prev[1:] = mu[:-1], sig2[:-1]
    mu_prev[starts], sig2_prev[starts] = 0.5, 0.25
    return mu_prev, sig2_prev


def plugin_bets(
    x: np.ndarray, offsets: np.ndarray, delta0: np.ndarray, c: float = C_TRUNC,
    layout: tuple[np.ndarray, np.ndarray] | None = None, sig2: np.ndarray | None = None,
) -> np.ndarray:
    """WSR's fixed-n predictable plug-in bets lambda_i for every group (see module doc);
    ``sig2``: the predictable variances sigma2_{i-1} if already computed.

    ``delta0`` has one tuning level per group. lambda_i uses sigma2_{i-1} only. Not
    truncated here: ``c`` truncation is m-dependent (c/m, c/(1-m), in :func:`log_capital`);
    ``c`` is accepted for backward compatibility and ignored.
    """
    sizes = np.diff(offsets)
    gid, t = flat_layout(offsets) if layout is None else layout
    if sig2 is None:
        _, sig2 = running_moments(x, offsets, (gid, t))
    with np.errstate(divide="ignore"):
        k = 2.0 * np.log(1.0 / np.asarray(delta0, float)) / sizes  # per group
    return np.sqrt(k[gid] / sig2)


def star_bets(x: np.ndarray, offsets: np.ndarray, delta0: np.ndarray,
              layout: tuple[np.ndarray, np.ndarray] | None = None,
              sig2: np.ndarray | None = None) -> StarBets:
    """Target-recalculating (STaR) bets' inputs for every group; the bets themselves depend
    on m and on the capital so far, and are formed in :func:`star_log_capital`.

    Parameters: ``x`` values in [0, 1] group after group in their order; ``offsets`` the
    groups' bounds; ``delta0`` one tuning level per group (the capital's target is
    1/delta0); ``sig2`` the predictable variances if already computed (else those of
    :func:`running_moments`). Returns sigma2_{i-1} and log(1/delta0).
    """
    sizes = np.diff(offsets)
    if sig2 is None:
        _, sig2 = running_moments(x, offsets, layout)
    with np.errstate(divide="ignore"):
        target = np.log(1.0 / np.broadcast_to(np.asarray(delta0, float), sizes.shape))
    return StarBets(sig2, target)


def star_log_capital(side: OrderedSide, m: np.ndarray, sign: int, running_max: bool = True,
                     c: float = C_TRUNC) -> np.ndarray:
    """log max_{0<=t<=n} K^{sign}_t(m) per group with target-recalculating bets.

    K+ (``sign`` +1), for each group with values x_1..x_n in [0, 1], target T = 1/delta0,
    R = log T, l_i = log K+_i(m) (l_0 = 0) and r_i = R - l_{i-1} the need left::

        K+_i(m) = K+_{i-1}(m) (1 + b_i(m) (x_i - m)),
        b_i(m) = min( sqrt(2 max(r_i, r0) / ((n - i + 1) S_i(m))) exp(min(r_i - r0, 0)),
                      c / m ),
        S_i(m) = min(sigma2_{i-1}, m (1 - m)),   r0 = 1/2 (``STAR_R0``),

    sigma2_{i-1} the predictable plug-in variance of :func:`running_moments`. The bet is the
    one that, at the current variance, lets the n - i + 1 values left raise the capital by the
    factor still missing to the target, exp(r_i) (Voracek & Orabona 2025, STaR-Bets; for
    one-sided tests of mean <= m the largest variance is m (1 - m), their cap of S). Below a
    need of r0 it decays as exp(r_i - r0) instead of sqrt(r_i): the continuation whose
    logarithmic derivative in l stays -1, which keeps the capital monotone in m.
    K- is K+ of 1 - x at 1 - m (S and sigma2 are symmetric). Validity and monotonicity in m:
    :mod:`twinfalsify.inference.betting`'s module doc, "STaR bets". Terminal capital
    (``running_max`` False) or running maximum; compiled (numba), groups of similar size
    stepped together.
    """
    st = side.star
    if st.order is None:
        st.order = np.argsort(-side.sizes, kind="stable")
    from twinfalsify.inference import kernels  # numba: imported when first needed

    out = np.empty(side.n_groups)
    kernels.star_kernel(side.x, st.sig2, side.offsets, np.asarray(m, float), st.target,
                        int(sign), bool(running_max), float(c), STAR_R0, st.order, out)
    return out


_CHUNK = 1 << 17  # elements per chunk: keeps the working arrays in cache (~3x faster)


def chunk_ranges(sizes: np.ndarray, per: int = _CHUNK) -> list[tuple[int, int]]:
    """Consecutive hypothesis ranges [h0, h1) holding about ``per`` elements each."""
    cum = np.concatenate([[0], np.cumsum(sizes)])
    out, h0, h = [], 0, len(sizes)
    while h0 < h:
        h1 = int(np.searchsorted(cum, cum[h0] + per, side="right")) - 1
        h1 = min(max(h1, h0 + 1), h)
        out.append((h0, h1))
        h0 = h1
    return out


def log_capital(side: OrderedSide, m: np.ndarray, sign: int, running_max: bool = True,
                c: float = C_TRUNC) -> np.ndarray:
    """log max_{0<=t<=n} K^{sign}_t(m) per group (sign +1: K+, -1: K-); m has shape (G,).

    ``running_max=False``: log K_n (terminal). A side with K copies (orders, or the bets of
    the grid mixture) gives log((1/K) sum_k K^(k)_n(m)), always terminal whatever
    ``running_max`` says (the running maximum of an average over different orders is not
    covered by Ville's inequality; the mixture is defined by its terminal value), so a
    mixture side can be paired with a running-maximum side. Evaluated chunk by chunk of
    groups (cache-sized working arrays).
    """
    if side.star is not None:
        if side.copies > 1:
            raise ValueError("betting: target-recalculating bets take one order")
        return star_log_capital(side, m, sign, running_max, c)
    if side.copies > 1:
        one = OrderedSide(side.x, side.lam, side.offsets)
        per = log_capital(one, np.tile(np.asarray(m, float), side.copies), sign, False, c)
        per = per.reshape(side.copies, -1)
        top = per.max(axis=0)
        return top + np.log(np.mean(np.exp(per - top), axis=0))
    sizes = side.sizes
    m = np.asarray(m, float)
    with np.errstate(divide="ignore"):
        cap = c / m if sign > 0 else c / (1.0 - m)
    out = np.zeros(len(sizes))
    for h0, h1 in chunk_ranges(sizes):
        o = side.offsets[h0: h1 + 1]
        sl = slice(o[0], o[-1])
        sz = sizes[h0:h1]
        gid = np.repeat(np.arange(h1 - h0), sz)
        lam = np.minimum(side.lam[sl], cap[h0:h1][gid])
        term = np.log1p(sign * lam * (side.x[sl] - m[h0:h1][gid]))
        cs = np.cumsum(term)
        starts = o[:-1] - o[0]
        base = np.concatenate([[0.0], cs])[starts]
        nz = sz > 0
        if not nz.any():
            continue
        if running_max:
            mx = np.maximum.reduceat(cs, starts[nz])
            out[h0:h1][nz] = np.maximum(0.0, mx - base[nz])  # t = 0: K_0 = 1
        else:
            out[h0:h1][nz] = cs[o[1:][nz] - o[0] - 1] - base[nz]
    return out


def crossing(
    dec: OrderedSide, inc: OrderedSide, m0: np.ndarray, running_max: bool, c: float,
    tol: float, max_iter: int,
) -> np.ndarray:
    """log K* lower bound per group: max_m min(g_dec(m), g_inc(m)), g = log max_t K.

    g_dec = log max_t K+ of the side hypothesised larger (non-increasing in m),
    g_inc = log max_t K- of the side hypothesised smaller (non-decreasing). Known:
    g_inc(0) = 0 and g_dec(1) = 0 (every factor <= 1 there, K_0 = 1). Safeguarded
    Illinois false position on h = g_dec - g_inc over the bracket [a, b] with
    h(a) >= 0 >= h(b); K* lies between exp(max(g_dec(b), g_inc(a))) (attained,
    returned) and exp(min(g_dec(a), g_inc(b))). Stops when these agree within tol,
    or when the upper one is below log 2 (then p = 1 whatever K* is).
    """
    g = len(m0)
    out = np.zeros(g)
    a, b = np.zeros(g), np.ones(g)
    da, ia = np.full(g, np.inf), np.zeros(g)  # g_dec(a), g_inc(a) at a = 0
    db, ib = np.zeros(g), np.full(g, np.inf)  # g_dec(b), g_inc(b) at b = 1
    act = np.arange(g)
    d_side, i_side = dec, inc
    last = np.zeros(g, dtype=np.int8)  # which end moved last (+1 a, -1 b), for Illinois
    ha_w, hb_w = np.full(g, np.nan), np.full(g, np.nan)  # Illinois-weighted h at the ends
    m = np.clip(np.asarray(m0, float), 1e-9, 1 - 1e-9)
    for it in range(max_iter):
        gd = log_capital(d_side, m[act], +1, running_max, c)
        gi = log_capital(i_side, m[act], -1, running_max, c)
        h = gd - gi
        right = h >= 0  # crossing is to the right of m: m becomes a
        ai = act[right]
        bi = act[~right]
        a[ai], da[ai], ia[ai] = m[ai], gd[right], gi[right]
        b[bi], db[bi], ib[bi] = m[bi], gd[~right], gi[~right]
        # Illinois: halve the weight of an end that stays put twice in a row
        new_ha = np.where(right, h, ha_w[act])
        new_hb = np.where(~right, h, hb_w[act])
        stay_b = right & (last[act] == 1)
        stay_a = ~right & (last[act] == -1)
        new_hb = np.where(stay_b, new_hb / 2, new_hb)
        new_ha = np.where(stay_a, new_ha / 2, new_ha)
        ha_w[act], hb_w[act] = new_ha, new_hb
        last[act] = np.where(right, 1, -1)
        lower = np.maximum(db[act], ia[act])
        upper = np.minimum(da[act], ib[act])
        done = (upper - lower <= tol) | (upper <= np.log(2.0)) | (b[act] - a[act] <= 1e-14)
        out[act] = lower
        keep = ~done
        if not keep.any():
            break
        if keep.sum() < 0.75 * act.size:
            # compact; otherwise finished groups ride along (their bracket only tightens)
            kept = np.flatnonzero(keep)
            d_side, i_side, act = d_side.take(kept), i_side.take(kept), act[kept]
        # next point: false position where both end values are known, else bisection
        aa, bb = a[act], b[act]
        hw_a, hw_b = ha_w[act], hb_w[act]
        fp = np.isfinite(hw_a) & np.isfinite(hw_b) & (hw_a - hw_b > 0) & (it % 4 != 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            mf = aa + (bb - aa) * hw_a / (hw_a - hw_b)
        mid = 0.5 * (aa + bb)
        nxt = np.where(fp, mf, mid)
        # stay strictly inside the bracket
        eps = 1e-3 * (bb - aa)
        m[act] = np.clip(nxt, aa + eps, bb - eps)
    return out


def capital_bound(side: OrderedSide, log_level: np.ndarray, sign: int, running_max: bool, c: float,
           n_iter: int = 42) -> np.ndarray:
    """sup{m : log max K+(m) >= level} (sign +1) or inf{m : log max K-(m) >= level} (sign -1)."""
    g = side.n_groups
    a, b = np.zeros(g), np.ones(g)  # sign +1: K+ >= level holds at a, fails at b
    for _ in range(n_iter):
        mid = 0.5 * (a + b)
        hit = log_capital(side, mid, sign, running_max, c) >= log_level
        if sign > 0:
            a, b = np.where(hit, mid, a), np.where(hit, b, mid)
        else:
            a, b = np.where(hit, a, mid), np.where(hit, mid, b)
    return a if sign > 0 else b
