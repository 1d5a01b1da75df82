"""What each test method's options mean: type, default, limits, meaning and an example.

The configuration reference (``twinfalsify.config_reference``) lists the options of
``testing.methods.<method>`` from here. The limits restate each method module's
``check_options`` and the defaults its function's signature; ``tests/docs/test_config_reference.py``
holds them to it (every option of ``registry.METHODS`` documented; a documented default equal
to the signature's; a value just past a documented limit refused by ``check_options``, the
limit itself accepted unless open), so this page cannot drift from what a run does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class OptionDoc:
    """One option of a test method.

    ``default`` is the value a run uses when the option is absent (``None`` = YAML null, with
    ``default_text`` saying what null means); ``lo``/``hi`` (open or closed) and ``choices``
    are the limits ``check_options`` enforces.
    """

    type: str
    default: Any
    meaning: str
    example: Any
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()
    default_text: str = ""
    needs: tuple[tuple[str, Any], ...] = ()  # other options the example needs, (key, value)

    def limits(self) -> str:
        """The accepted range in words, as the reference page shows it."""
        if self.choices:
            return "one of " + ", ".join(f"`{c}`" for c in self.choices)
        parts = []
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
        return "; ".join(parts)


METHOD_DOCS: dict[str, str] = {
    "hoeffding": "exact (finite-sample) test from Hoeffding's inequality on the clipped "
                 "outcomes; the paper's main test",
    "bootstrap": "the paper's bootstrap test: asymptotic, with no finite-sample guarantee; "
                 "its p-values come in steps of 2 / n_resamples",
    "betting": "exact test from betting confidence bounds (Waudby-Smith & Ramdas 2024); the "
               "default bets are target-recalculating (after STaR-Bets, Voracek & Orabona "
               "2025), each sample in the data's order, keyed by the study seed "
               "(testing.order_seed)",
    "bernstein": "exact test from the empirical-Bernstein bound (Maurer & Pontil 2009); no "
                 "options",
}

OPTIONS: dict[str, dict[str, OptionDoc]] = {
    "hoeffding": {
        "factor": OptionDoc(
            "number", 2.0, "constant of the union bound in p = min(1, factor exp(...)): 2 = "
            "Hoeffding's two-sided bound, the paper's proposition; 4 = the authors' code; "
            "below 2 the p-value is understated", 4, lo=2.0),
    },
    "bootstrap": {
        "n_resamples": OptionDoc(
            "integer", 100, "bootstrap resamples B per side; p-values come in steps of 2/B "
            "(the paper: 100)", 1000, lo=50),
        "min_n": OptionDoc(
            "integer", 100, "smallest n and n_hat tested; a hypothesis with fewer "
            "observational trajectories or twin runs gets p = 1 (the paper: 100)", 50, lo=1),
        "kind": OptionDoc(
            "string", "reverse_percentile", "bootstrap bound: reverse percentile (basic "
            "bootstrap, Davison & Hinkley 1997) or percentile (Efron 1979)", "percentile",
            choices=("reverse_percentile", "percentile")),
        "variant": OptionDoc(
            "string", "exact", "exact: the paper's alpha/2-per-side rule, exact smallest "
            "rejecting alpha; authors_grid: the authors' code's 500-point alpha grid, for "
            "comparison only", "authors_grid", choices=("exact", "authors_grid")),
        "p_floor": OptionDoc(
            "number", 1e-6, "p reported when every resample separates (below the resolution "
            "2/B: 'all resamples separated' in results and figures)", 1e-8,
            lo=0.0, hi=0.02, lo_open=True, hi_open=True,
            default_text="1e-06; must lie below 2 / n_resamples (0.02 at the default B)"),
    },
    "betting": {
        "bets": OptionDoc(
            "string", "star", "star: target-recalculating bets after STaR-Bets (one order "
            "of each sample); plugin: WSR's predictable plug-in bets (the same order); mixture: "
            "order-free mixture of `grid` constant bets", "plugin",
            choices=("plugin", "mixture", "star")),
        "order": OptionDoc(
            "string or null", None, "star and plugin bets: each sample in its data order, keyed by "
            "the study seed (data), or a random order drawn from the study's seed (seed)", "seed",
            choices=("data", "seed"), default_text="null = data"),
        "orders": OptionDoc(
            "integer or null", None, "plugin bets: K orders whose terminal capitals are "
            "averaged (K > 1 needs running_max false)", 4, lo=1, default_text="null = 1",
            needs=(("bets", "plugin"),)),
        "running_max": OptionDoc(
            "boolean or null", None, "star and plugin bets: use the running maximum of the "
            "capital (Ville's inequality) instead of the terminal capital", False,
            default_text="null = true when orders is 1, else false"),
        "c": OptionDoc(
            "number", 0.9, "bet truncation: a bet against mean m is at most c/m (c/(1-m)); "
            "WSR suggest 1/2 or 3/4", 0.75, lo=0.0, hi=1.0, lo_open=True, hi_open=True),
        "tune_alpha": OptionDoc(
            "number or null", None, "the level the bets are tuned for (every kind of bets)",
            0.001,
            lo=0.0, hi=1.0, lo_open=True, hi_open=True,
            default_text="null = testing.alpha / (2 H), H the parameter sets of the family"),
        "grid": OptionDoc(
            "integer", 6, "mixture bets: J constant bets in the mixture", 8, lo=1),
        "grid_ratio": OptionDoc(
            "number", 1.7, "mixture bets: ratio between neighbouring bets of the grid", 2.0,
            lo=1.0, lo_open=True),
        "tol": OptionDoc(
            "number", 1e-3, "accuracy of log K* in the search for the crossing (p's relative "
            "accuracy); p is never understated", 1e-4, lo=0.0, lo_open=True),
        "max_iter": OptionDoc(
            "integer", 100, "iterations of that search at most", 200, lo=1),
    },
    "bernstein": {},
}
