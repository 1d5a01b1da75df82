"""Calibration harness: validity and power of every test method on the synthetic world.

The synthetic world (``sources.synthetic``) knows the truth: its oracle twin is
an exact sampler of the interventional law, so every null hypothesis about the
oracle is true, and a twin whose outcomes are shifted is wrong. A *replicate*
r draws a fresh observational cohort (seed r), splits it, fits the design on
D0, computes the observational side on D once, runs the oracle once on the
prefix-tree plan, and derives each biased twin from the same runs by adding
``bias * sd_k`` to every simulated hour of each outcome k (exactly what
``twins.builtin.BiasedTwin(shift=...)`` does with the same seeds; tested).
Every method then tests every hypothesis of every twin, with Holm (or the
configured correction) within each (method, kind) family, as ``falsify.run_tests``.

Measured (aggregated over R replicates by :func:`summarise`):

* FWER of the oracle: P(at least one rejection in a family) with a Clopper-
  Pearson 95 % interval (scipy.stats.binomtest). Exact methods (Hoeffding,
  betting, Bernstein) must have FWER <= alpha up to Monte-Carlo error; the
  bootstrap is asymptotic and is reported as measured.
* Power against biased twins: P(at least one rejection) and the mean share of
  hypotheses rejected, per bias size (in units of each outcome's D0 SD).
* Coverage of the bounds (Cornish et al. 2026, Theorem): for a sample of
  hypotheses, the true Q = E[f(X_t(a)) | X_0:t(a) in B_0:t] by Monte Carlo
  from a fresh population given a_1:t by intervention
  (``SyntheticWorld.simulate_interventional``), and the population
  Q_lo, Q_up estimated on a large observational cohort; reports the share with
  Q_lo <= Q <= Q_up strictly and up to ``z`` combined Monte-Carlo SEs.
* The naive-comparison pitfall: Welch's t-test of the twin's mean of f against
  the observational mean of f among followers (A_1:t = a_1:t, X in B), no
  bounds; with confounding it rejects the oracle.
* Widths: mean (Q_up - Q_lo) / (y_up - y_lo) = 1 - propensity, causal vs Manski.
* Adaptive twin runs (``adaptive: true``): ``inference.sequential.adaptive_test``
  on the same runs revealed in batches (method ``betting_sequential``): its FWER and power
  as above, and per twin the simulated twin-hours (prefix reuse) adaptive vs fixed and the
  share of the fixed betting / Hoeffding rejections it keeps (:func:`adaptive_summary`).

Caveat shared with the study: the twin receives the median dose of each action
bin while the observational followers of a bin received varied doses, so the
oracle is exact for "median dose" rather than for "some dose in the bin".

The package: ``config`` (settings, loader, table columns), ``replicates`` (one replicate's
cohort, twins and tests), ``metrics`` (aggregates over replicates), ``report`` (figures and
markdown). Everything public is re-exported here, so ``from twinfalsify import calibration``
reads as one module.
"""

from twinfalsify.calibration.config import (  # noqa: F401
    ADAPTIVE,
    ADAPTIVE_COLUMNS,
    COVERAGE_COLUMNS,
    EXACT_METHODS,
    HOURS_TARGET,
    KEPT_TARGET,
    NAIVE,
    TEST_COLUMNS,
    WIDTH_COLUMNS,
    CalibrationConfig,
    chunk_replicates,
    load_config,
)
from twinfalsify.calibration.metrics import (  # noqa: F401
    adaptive_summary,
    attach_hours,
    coverage_summary,
    dominance,
    summarise,
    width_summary,
)
from twinfalsify.calibration.replicates import (  # noqa: F401
    Population,
    Replicate,
    adaptive_rows,
    adaptive_state,
    build_replicate,
    coverage,
    evaluate_bias,
    fixed_results,
    run_adaptive,
    run_replicates,
    shifted_nodes,
    welch_pvalues,
    widths,
)
from twinfalsify.calibration.report import (  # noqa: F401
    adaptive_markdown,
    markdown_summary,
    plot_coverage,
    plot_power,
)
