"""Calibration harness settings: the config, its loader and the column contracts of its tables."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from twinfalsify.inference.sequential import COMBINES, PRODUCT_REMOVED
from twinfalsify.schema import OUTCOMES, ContractError

ADAPTIVE = "betting_sequential"  # inference.sequential.adaptive_test (anytime-valid, exact)
EXACT_METHODS = ("hoeffding", "betting", "bernstein", ADAPTIVE)
NAIVE = "naive_welch"
HOURS_TARGET = 0.1  # target: at most 1/10 of the fixed scheme's twin-hours ...
KEPT_TARGET = 0.9  # ... while keeping >= 90 % of its rejections

# Column contracts of the per-replicate tables.
TEST_COLUMNS = (
    "replicate", "bias", "method", "kind", "n_tests", "n_testable", "n_rejected", "any_rejected",
)  # fmt: skip
COVERAGE_COLUMNS = (
    "replicate", "hyp_id", "kind", "outcome", "t", "y_lo", "y_up", "n_pop", "q_lo_pop",
    "q_up_pop", "se_bounds", "n_inside", "q_true", "se_true", "covered", "covered_mc",
)  # fmt: skip
WIDTH_COLUMNS = ("replicate", "kind", "n_hyps", "mean_width_ratio", "median_width_ratio")
ADAPTIVE_COLUMNS = (
    "replicate", "bias", "batch_size", "budget", "n_nodes", "twin_hours_adaptive",
    "twin_hours_fixed", "hours_ratio", "n_rejected", "n_rejected_betting", "n_kept_betting",
    "n_rejected_hoeffding", "n_kept_hoeffding", "undecided_sides", "mean_stop_fraction",
    "twin_hours_all_x0", "twin_hours_paper",
)  # fmt: skip


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of a calibration run (``config/calibration.yaml``).

    See docs/explanation/calibration.md.
    """

    replicates: int = 200
    seed: int = 2026
    n_stays: int = 2500
    confounding: float = 1.0
    d0_fraction: float = 0.15
    min_support: int = 10
    quantiles: tuple[float, float] = (0.2, 0.8)
    runs_per_sequence: int = 400
    alpha: float = 0.05
    correction: str = "holm"
    methods: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {
            "hoeffding": {},
            "bootstrap": {"n_resamples": 100},
            "betting": {},
            "bernstein": {},
        }
    )
    bias_sizes: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 2.0)  # in SD units; 0 = oracle
    bias_features: tuple[str, ...] = OUTCOMES
    naive: bool = True
    coverage_per_replicate: int = 4  # hypotheses checked per replicate (half causal, half Manski)
    coverage_population: int = 60_000  # stays of each population cohort (bounds, truth)
    coverage_min_inside: int = 200  # skip a check when fewer population members are in B
    coverage_z: float = 4.0  # MC slack in combined SEs for the "up to MC error" coverage
    chunks: int = 4  # Snakemake jobs the replicates are spread over (r % chunks)
    adaptive: bool = True  # also run inference.sequential.adaptive_test (betting_sequential)
    adaptive_batch_size: int = 25  # X_0 revealed per batch (budget = runs_per_sequence)
    adaptive_curtail: float = 0.0  # opt-in curtailment epsilon of the adaptive test (0: off)
    adaptive_combine: str = "union"  # union only (product withdrawn: sequential.PRODUCT_REMOVED)

    @classmethod
    def from_dict(cls, cfg: dict[str, Any] | None, source: str = "calibration config"):
        """Validated config; unknown keys and bad values raise ContractError naming them."""
        cfg = dict(cfg or {})
        names = {f.name for f in fields(cls)}
        unknown = set(cfg) - names
        if unknown:
            raise ContractError(
                f"{source}: unknown key(s) {sorted(unknown)}; allowed: {sorted(names)}"
            )
        for key in ("quantiles", "bias_sizes", "bias_features"):
            if key in cfg:
                cfg[key] = tuple(cfg[key])
        out = replace(cls(), **cfg)
        out.validate(source)
        return out

    def validate(self, source: str = "calibration config") -> None:
        def bad(key: str, why: str) -> ContractError:
            return ContractError(f"{source}: {key} {why}")

        if self.replicates < 1:
            raise bad("replicates", f"must be >= 1, got {self.replicates}")
        if not 0 < self.d0_fraction < 1:
            raise bad("d0_fraction", f"must be in (0, 1), got {self.d0_fraction}")
        if not 0 < self.alpha < 1:
            raise bad("alpha", f"must be in (0, 1), got {self.alpha}")
        if not self.bias_sizes or 0.0 not in self.bias_sizes:
            raise bad("bias_sizes", "must include 0 (the oracle, for the FWER)")
        if any(b < 0 for b in self.bias_sizes):
            raise bad("bias_sizes", f"must be >= 0, got {list(self.bias_sizes)}")
        wrong = set(self.bias_features) - set(OUTCOMES)
        if wrong:
            raise bad("bias_features", f"holds unknown outcome(s) {sorted(wrong)}")
        if not self.methods:
            raise bad("methods", "must name at least one method")
        if self.chunks < 1:
            raise bad("chunks", f"must be >= 1, got {self.chunks}")
        if self.runs_per_sequence < 2:
            raise bad("runs_per_sequence", f"must be >= 2, got {self.runs_per_sequence}")
        if not isinstance(self.adaptive, bool):
            raise bad("adaptive", f"must be true or false, got {self.adaptive!r}")
        if not 1 <= self.adaptive_batch_size <= self.runs_per_sequence:
            raise bad(
                "adaptive_batch_size",
                f"must be in [1, runs_per_sequence = {self.runs_per_sequence}], "
                f"got {self.adaptive_batch_size}",
            )
        c = self.adaptive_curtail
        if isinstance(c, bool) or not isinstance(c, int | float) or not 0 <= c < 1:
            raise bad("adaptive_curtail", f"must be in [0, 1), got {self.adaptive_curtail}")
        if self.adaptive_combine == "product":
            raise bad("adaptive_combine", PRODUCT_REMOVED)
        if self.adaptive_combine not in COMBINES:
            raise bad("adaptive_combine",
                      f"must be one of {', '.join(COMBINES)}, got {self.adaptive_combine!r}")

    def replicate_seed(self, r: int) -> int:
        """Seed of replicate r: independent streams per r, reproducible whatever the chunking."""
        return int(np.random.SeedSequence([self.seed, r]).generate_state(1)[0])



def chunk_replicates(cfg: CalibrationConfig, chunk: int) -> list[int]:
    """Replicates of Snakemake job ``chunk``: r = chunk, chunk + chunks, ... (< replicates)."""
    if not 0 <= chunk < cfg.chunks:
        raise ContractError(f"calibration: chunk {chunk} out of range (chunks: {cfg.chunks})")
    return list(range(chunk, cfg.replicates, cfg.chunks))


def load_config(path: str) -> CalibrationConfig:
    """Read and validate a calibration YAML file (errors name the file and key)."""
    import yaml

    try:
        with open(path) as fh:
            data = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ContractError(f"{path}: cannot read calibration config ({exc})") from None
    if data is not None and not isinstance(data, dict):
        raise ContractError(f"{path}: calibration config must be a mapping of keys to values")
    return CalibrationConfig.from_dict(data, source=str(path))


