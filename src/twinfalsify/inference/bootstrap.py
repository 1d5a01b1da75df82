"""Bootstrap test of H_lo / H_up, as in the paper's appendix (approximate, asymptotic).

For each side S in {Y_lo, Y_up, Y_twin} draw B resamples with replacement of the
side's sample (size n, resp. nhat) and record the resampled means theta*_1..B,
sorted: theta*_(1) <= ... <= theta*_(B). With the inverse-ECDF quantile
q_p = theta*_(ceil(p B)), the one-sided (1 - delta) bounds are

- reverse percentile (basic bootstrap; Davison & Hinkley 1997, eq. 5.6):
  lower = 2 thetahat - q_{1-delta},   upper = 2 thetahat - q_delta;
- percentile (Efron 1979): lower = q_delta,   upper = q_{1-delta}.

The union rule at level alpha puts delta = alpha/2 on each side (docs/explanation/method.md).
Both bounds are step functions of delta, constant on (j/B, (j+1)/B): there
(1-indexed order statistics) the reverse-percentile rule for H_lo reads

    2 thetahat_twin - theta*_twin,(j+1)  <  2 thetahat_lo - theta*_lo,(B-j),

monotone in j, so the p-value inf{alpha : reject} is exactly 2 j*/B with j* the
first j in 0..ceil(B/2)-1 satisfying it (p = 1 if none). j* = 0 means even the
extreme order statistics separate ("all resamples separated"): with B resamples
the bootstrap cannot resolve levels below 2/B, so p in {0, 2/B, 4/B, ...} and 0 is
not a measurement but "below the resolution". It is reported at the floor
``p_floor`` (default P_FLOOR = 1e-6, the lowest level of the authors' alpha grid
reading; any floor below the smallest Holm threshold alpha / (2 H_f)
keeps the paper's decisions, 1e-6 does so for families of up to 25,000 one-sided
hypotheses at alpha = 0.05, and it keeps p > 0 for Holm and for -log10 in figures).
``at_floor`` flags such p-values ("all resamples separated" in results and figures).
With Holm over hundreds of hypotheses only these survive, which is how the
paper's bootstrap rejects.
The authors' code instead scans a 500-point alpha grid with level alpha (not
alpha/2) on each side and numpy's interpolated quantiles: ``variant="authors_grid"``
reproduces that reading for comparison only.

Resampling uses the compact form of the observational sample (docs/explanation/implementation.md): a
resample of n values of Y_lo picks K ~ Binomial(n, n_follow/n) followers (drawn
uniformly with replacement among them) and n - K copies of y_lo; the same draw
gives the Y_up resample with y_up copies. This is exactly the distribution of a
resample of the materialised sample, without materialising it.

Assumptions: i.i.d. samples; validity is only asymptotic (no finite-sample
guarantee); refuses (p = 1) when n < min_n or nhat < min_n (paper: 100).
References: Efron (1979) Ann. Statist. 7:1-26; Davison & Hinkley (1997)
Bootstrap Methods and their Application, ch. 5; Cornish et al. (2026) JMLR, appendix.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from twinfalsify.inference import options
from twinfalsify.inference.samples import HypothesisSamples, Ragged

KINDS = ("reverse_percentile", "percentile")
VARIANTS = ("exact", "authors_grid")
#: the p reported when every resample separates (module doc): below the bootstrap's resolution
P_FLOOR = 1e-6
#: the authors' scan: 500 levels (our reading of their code; configurable)
AUTHORS_GRID = np.linspace(0.0, 1.0, 500)
_CHUNK_DRAWS = 1 << 18  # draws per block: cache-sized working arrays (fastest measured)


@dataclass(frozen=True)
class BootstrapDistributions:
    """Point estimates (H,) and sorted bootstrap means (H, B) of the three samples.

    Rows of hypotheses that are refused (n < min_n or nhat < min_n) are NaN.
    """

    lo_hat: np.ndarray
    up_hat: np.ndarray
    twin_hat: np.ndarray
    lo: np.ndarray
    up: np.ndarray
    twin: np.ndarray
    eligible: np.ndarray  # (H,) bool


def _resample_sums(
    values: Ragged, rows: np.ndarray, counts: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Sums of ``counts[i, b]`` uniform draws with replacement from group ``rows[i]``.

    Vectorised over (row, resample, draw) in padded blocks of rows of similar size
    (rows sorted by their largest count, so padding wastes little). An index in
    0..size-1 is drawn as (u * size) >> 32 from a uniform 32-bit u (Lemire 2019):
    non-uniformity below size / 2^32, i.e. < 3e-6 for 11,000 values. Returns (len(rows), B).

    The block shapes, the stream of u and the padded sums fix every result bit: the draws
    are read straight from ``values`` (no padded copy of each group) and the padding draws
    zeroed in place, which is faster and changes none of them.
    """
    n_rows, n_b = counts.shape
    out = np.zeros((n_rows, n_b))
    if n_rows == 0:
        return out
    sizes = values.sizes[rows]
    if np.any((counts > 0) & (sizes[:, None] == 0)):
        raise ValueError("bootstrap: cannot draw from an empty group")
    starts = values.offsets[rows]
    m_row = counts.max(axis=1)
    for block in draw_blocks(m_row, n_b):
        m = int(m_row[block].max())
        if m > 0:
            r = block.size
            size_i = sizes[block].astype(np.int64)
            # one 32-bit output of the generator per u, as integers(..., dtype=int64) reads
            # them (the same stream), stored at half the width; u < 2^32 and size < 2^31, so
            # u * size < 2^63 in int64
            u = rng.integers(0, 1 << 32, size=(r, n_b * m), dtype=np.uint32)
            idx = np.multiply(u, size_i[:, None], dtype=np.int64)
            idx >>= 32
            idx += starts[block][:, None]
            # clip: only an empty group's draws (never kept) can point past the last value
            g = values.values.take(idx, mode="clip").reshape(r, n_b, m)
            np.copyto(g, 0.0, where=np.arange(m) >= counts[block][:, :, None])
            out[block] = g.sum(axis=2)
    return out


def draw_blocks(m_row: np.ndarray, n_b: int) -> list[np.ndarray]:
    """Rows grouped into blocks drawn together, in increasing order of their largest count
    ``m_row``: a block grows while its draws fit ``_CHUNK_DRAWS`` and its counts stay within
    25 % of its first (the random stream is read block after block, so the blocks fix it)."""
    order = np.argsort(m_row, kind="stable")
    blocks, i, n_rows = [], 0, len(m_row)
    while i < n_rows:
        m_first = int(m_row[order[i]])
        j = i + 1
        while j < n_rows:
            m_j = int(m_row[order[j]])
            if (j + 1 - i) * n_b * max(m_j, 1) > _CHUNK_DRAWS or m_j > 1.25 * m_first + 16:
                break
            j += 1
        blocks.append(order[i:j])
        i = j
    return blocks


def _split_clipped(values: Ragged, y_lo: np.ndarray, y_up: np.ndarray):
    """(interior values as a Ragged, count at y_lo, count at y_up) per group of clipped values."""
    gid = values.group_ids()
    at_lo = values.values <= y_lo[gid]
    at_up = values.values >= y_up[gid]
    inner = ~(at_lo | at_up)
    h = len(values)
    sizes = np.bincount(gid[inner], minlength=h)
    interior = Ragged(values.values[inner], np.concatenate([[0], np.cumsum(sizes)]))
    return interior, np.bincount(gid[at_lo], minlength=h), np.bincount(gid[at_up], minlength=h)


def _binom(rng: np.random.Generator, total: np.ndarray, count: np.ndarray, pool: np.ndarray):
    """Binomial(total, count / pool) draws, 0 where pool is 0 (count <= pool elementwise)."""
    p = np.where(pool > 0, count / np.maximum(pool, 1), 0.0)
    return rng.binomial(total, np.broadcast_to(p, total.shape))


def _side_draws(
    kind: str, samples: HypothesisSamples, rows: np.ndarray, b: int, rng: np.random.Generator
) -> tuple[np.ndarray, ...]:
    """Bootstrap means of one sample for ``rows``: ("obs" -> (lo, up), "twin" -> (twin,)).

    A resample of the materialised sample is a multinomial count over the categories
    {copies of the fill value (obs only), values clipped at y_lo, values clipped at
    y_up, interior values}, then uniform draws with replacement among the interior
    values only: the same law, with fewer random draws (clipped masses are common:
    y_lo, y_up are quantiles of the outcome).
    """
    y_lo, y_up = samples.y_lo[rows, None], samples.y_up[rows, None]
    ragged = samples.follow_f if kind == "obs" else samples.twin_f
    interior, at_lo, at_up = _split_clipped(ragged, samples.y_lo, samples.y_up)
    size = (samples.n if kind == "obs" else samples.nhat)[rows][:, None]
    tot = np.broadcast_to(size, (rows.size, b))
    n_in, n_lo, n_up = (interior.sizes[rows][:, None], at_lo[rows][:, None],
                        at_up[rows][:, None])
    c_in = _binom(rng, tot, n_in, size)
    c_lo = _binom(rng, tot - c_in, n_lo, size - n_in)
    c_up = _binom(rng, tot - c_in - c_lo, n_up, size - n_in - n_lo)
    fill = tot - c_in - c_lo - c_up  # non-followers (obs); 0 for the twin
    s = _resample_sums(interior, rows, c_in, rng) + c_lo * y_lo + c_up * y_up
    if kind == "obs":
        return (s + fill * y_lo) / size, (s + fill * y_up) / size
    return (s / size,)


def bootstrap_distributions(
    samples: HypothesisSamples, *, n_resamples: int = 100, min_n: int = 100, seed: int = 0
) -> BootstrapDistributions:
    """Draw the B bootstrap means of Y_lo, Y_up and Y_twin for every eligible hypothesis.

    The observational and twin resamples run in two threads with independent
    streams spawned from ``seed`` (deterministic: same seed, same draws).
    """
    if n_resamples < 1:
        raise ValueError(f"bootstrap: n_resamples must be >= 1, got {n_resamples}")
    h, b = len(samples), n_resamples
    eligible = (samples.n >= max(min_n, 1)) & (samples.nhat >= max(min_n, 1))
    rows = np.flatnonzero(eligible)
    lo, up, tw = (np.full((h, b), np.nan) for _ in range(3))
    if rows.size:
        rng_obs, rng_tw = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
        with ThreadPoolExecutor(2) as pool:
            f_obs = pool.submit(_side_draws, "obs", samples, rows, b, rng_obs)
            f_tw = pool.submit(_side_draws, "twin", samples, rows, b, rng_tw)
            (lo[rows], up[rows]), (tw[rows],) = f_obs.result(), f_tw.result()
    return BootstrapDistributions(
        lo_hat=samples.q_lo_hat, up_hat=samples.q_up_hat, twin_hat=samples.q_twin_hat,
        lo=np.sort(lo, axis=1), up=np.sort(up, axis=1), twin=np.sort(tw, axis=1),
        eligible=eligible,
    )


def union_pvalue_sorted(
    small_hat: np.ndarray, small: np.ndarray, large_hat: np.ndarray, large: np.ndarray,
    kind: str = "reverse_percentile",
) -> np.ndarray:
    """Exact p = inf{alpha : upper_(1-alpha/2)(small) < lower_(1-alpha/2)(large)}.

    ``small``/``large`` are sorted bootstrap means (H, B) of the side hypothesised
    to have the smaller / larger mean (H_lo: twin / Y_lo; H_up: Y_up / twin).
    On delta in (j/B, (j+1)/B) (0-indexed sorted columns):
    reverse percentile: upper(small) = 2 hat_s - small[:, j],
                        lower(large) = 2 hat_L - large[:, B-1-j];
    percentile:         upper(small) = small[:, B-1-j], lower(large) = large[:, j].
    """
    if kind not in KINDS:
        raise ValueError(f"bootstrap: unknown kind {kind!r}; choose one of {KINDS}")
    h, b = small.shape
    j = np.arange((b + 1) // 2)  # delta = alpha/2 < 1/2
    if kind == "reverse_percentile":
        upper = 2 * small_hat[:, None] - small[:, j]
        lower = 2 * large_hat[:, None] - large[:, b - 1 - j]
    else:
        upper = small[:, b - 1 - j]
        lower = large[:, j]
    with np.errstate(invalid="ignore"):
        rej = upper < lower  # NaN rows (refused) never reject
    first = np.argmax(rej, axis=1)
    any_rej = rej.any(axis=1)
    return np.where(any_rej, np.minimum(1.0, 2.0 * first / b), 1.0)


def _sorted_quantile(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """numpy's default (linear) quantiles of pre-sorted rows x (H, B) at levels q (G,) -> (H, G)."""
    pos = q * (x.shape[1] - 1)
    i0 = np.floor(pos).astype(np.int64)
    i1 = np.minimum(i0 + 1, x.shape[1] - 1)
    frac = pos - i0
    return x[:, i0] * (1 - frac) + x[:, i1] * frac


def _grid_pvalue(
    small_hat: np.ndarray, small: np.ndarray, large_hat: np.ndarray, large: np.ndarray,
    kind: str, grid: np.ndarray,
) -> np.ndarray:
    """The authors' variant: smallest grid alpha, level alpha on EACH side, linear quantiles."""
    grid = np.sort(np.asarray(grid, float))
    if grid.size == 0 or grid[0] < 0 or grid[-1] > 1:
        raise ValueError("bootstrap: alpha_grid must be a non-empty set of levels in [0, 1]")
    if kind == "reverse_percentile":
        upper = 2 * small_hat[:, None] - _sorted_quantile(small, grid)
        lower = 2 * large_hat[:, None] - _sorted_quantile(large, 1 - grid)
    else:
        upper = _sorted_quantile(small, 1 - grid)
        lower = _sorted_quantile(large, grid)
    with np.errstate(invalid="ignore"):
        rej = upper < lower
    return np.where(rej.any(axis=1), grid[np.argmax(rej, axis=1)], 1.0)


MIN_RESAMPLES = 50  # p-values come in steps of 2 / n_resamples: fewer cannot reach 0.05


def check_options(opts: dict) -> None:
    """Config options of :func:`bootstrap_test`, types and ranges (p_floor's bound depends
    on n_resamples, default 100)."""
    options.integer(opts, "n_resamples", lo=MIN_RESAMPLES,
                    note="p-values come in steps of 2 / n_resamples; the paper uses 100")
    options.integer(opts, "min_n", lo=1, note="the paper uses 100")
    options.choice(opts, "kind", KINDS)
    options.choice(opts, "variant", VARIANTS)
    b = int(opts.get("n_resamples", 100))
    options.number(opts, "p_floor", lo=0.0, hi=2.0 / b, lo_open=True, hi_open=True,
                   note="below the resolution 2 / n_resamples")


def bootstrap_test(
    samples: HypothesisSamples,
    *,
    alpha_grid: np.ndarray | None = None,
    n_resamples: int = 100,
    min_n: int = 100,
    kind: str = "reverse_percentile",
    seed: int = 0,
    variant: str = "exact",
    p_floor: float = P_FLOOR,
) -> tuple[np.ndarray, np.ndarray]:
    """Bootstrap p-values (p_lo, p_up), shape (H,) each; same seed, same p-values.

    A p of 0 (every resample separated: below the resolution 2/B) is reported as
    ``p_floor`` (module doc), which must lie in (0, 2/B).

    ``variant="exact"`` (default): the paper's alpha/2-per-side rule, exact smallest
    rejecting alpha from the sorted bootstrap means (``alpha_grid`` must be None).
    ``variant="authors_grid"``: the authors' code, alpha per side scanned on
    ``alpha_grid`` (default: 500 points on [0, 1]); for comparison only.
    """
    if kind not in KINDS:
        raise ValueError(f"bootstrap: unknown kind {kind!r}; choose one of {KINDS}")
    if variant not in VARIANTS:
        raise ValueError(f"bootstrap: unknown variant {variant!r}; choose one of {VARIANTS}")
    if variant == "exact" and alpha_grid is not None:
        raise ValueError("bootstrap: alpha_grid is only used by variant='authors_grid'")
    if not 0 < p_floor < 2.0 / n_resamples:
        raise ValueError(f"bootstrap: p_floor must be in (0, 2 / n_resamples), got {p_floor}")
    d = bootstrap_distributions(samples, n_resamples=n_resamples, min_n=min_n, seed=seed)
    if variant == "exact":
        p_lo = union_pvalue_sorted(d.twin_hat, d.twin, d.lo_hat, d.lo, kind)
        p_up = union_pvalue_sorted(d.up_hat, d.up, d.twin_hat, d.twin, kind)
    else:
        grid = AUTHORS_GRID if alpha_grid is None else np.asarray(alpha_grid, float)
        p_lo = _grid_pvalue(d.twin_hat, d.twin, d.lo_hat, d.lo, kind, grid)
        p_up = _grid_pvalue(d.up_hat, d.up, d.twin_hat, d.twin, kind, grid)
    p_lo, p_up = (np.where(p > 0, p, p_floor) for p in (p_lo, p_up))
    return np.where(d.eligible, p_lo, 1.0), np.where(d.eligible, p_up, 1.0)


def at_floor(p: np.ndarray, p_floor: float = P_FLOOR) -> np.ndarray:
    """True where a bootstrap p is the floor: every resample separated (below resolution)."""
    return np.asarray(p, float) <= p_floor
