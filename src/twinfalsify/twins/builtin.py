"""Builtin twins: the oracle, deliberately biased variants, and a naively fitted twin."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from twinfalsify import noise
from twinfalsify.schema import (
    FEATURES,
    INIT_FEATURES,
    IV_FLUID,
    T_MAX,
    VASOPRESSOR,
    ContractError,
    to_array,
)
from twinfalsify.sources.synthetic import SyntheticWorld, g_iv, g_v
from twinfalsify.twins.base import SimResult

DEMOGRAPHICS = ("age", "sex", "weight")
PHYSIOLOGY = tuple(f for f in FEATURES if f not in DEMOGRAPHICS)


def _ok(features: np.ndarray) -> SimResult:
    return SimResult(features=features, status=np.full(features.shape[0], "ok", dtype=object))


@dataclass
class OracleTwin:
    """The synthetic world's exact interventional simulator: interventionally correct."""

    world: SyntheticWorld
    name: str = "oracle"

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        return _ok(self.world.simulate_interventional(x0, doses, seeds))


@dataclass
class BiasedTwin:
    """The oracle with distortions: wrong dose responses and/or shifted/scaled outcomes.

    dose_effect: multiplies the true effect of each drug (0 = the twin ignores it).
    shift: added to a feature at every simulated hour (feature units).
    scale: multiplies a feature's deviation from its value at t = 0.
    """

    world: SyntheticWorld
    dose_effect: dict[str, float] = field(default_factory=dict)
    shift: dict[str, float] = field(default_factory=dict)
    scale: dict[str, float] = field(default_factory=dict)
    name: str = "biased"

    def __post_init__(self) -> None:
        for key in self.dose_effect:
            if key not in (IV_FLUID, VASOPRESSOR):
                raise ContractError(
                    f"twins.{self.name}.dose_effect: unknown dose {key!r} "
                    f"({IV_FLUID} | {VASOPRESSOR})"
                )
        for part in ("shift", "scale"):
            for key in getattr(self, part):
                if key not in PHYSIOLOGY:
                    raise ContractError(
                        f"twins.{self.name}.{part}: unknown feature {key!r}; "
                        f"choose from {', '.join(PHYSIOLOGY)}"
                    )

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        scale = (self.dose_effect.get(IV_FLUID, 1.0), self.dose_effect.get(VASOPRESSOR, 1.0))
        out = self.world.simulate_interventional(x0, doses, seeds, dose_effect_scale=scale)
        for feat, factor in self.scale.items():
            j = FEATURES.index(feat)
            start = x0[feat].to_numpy(float)[:, None]
            out[:, :, j] = start + factor * (out[:, :, j] - start)
        for feat, delta in self.shift.items():
            out[:, :, FEATURES.index(feat)] += delta
        return _ok(out)


@dataclass
class FittedTwin:
    """A data-driven twin fitted naively to observational data (ignores the confounder).

    Like Pulse, it is initialised from the 7 features of schema.INIT_FEATURES
    only (``inputs='init'``, default) or from all 18 (``inputs='all'``). Per
    physiological feature k, ordinary least squares over the training
    trajectories (D0: held out from the test set D, so twin and test data stay
    independent) of

        hour 1:       X_1[k] on (1, X_0[inputs], g_iv(IV_1), g_v(vaso_1))
        hour t >= 2:  X_t[k] on (1, X_{t-1} [all 18], g_iv(IV_t), g_v(vaso_t))

    rolled out as point predictions (the usual way a regression model is used
    as a simulator), optionally with Gaussian residual noise. Because sicker
    patients are treated more, its fitted dose coefficients are confounded;
    because it is deterministic and (by default) blind to the initial labs, its
    conditional distributions within B-sets are wrong: a realistic flawed twin.
    """

    coef_first: np.ndarray  # (len(inputs) + 3, len(PHYSIOLOGY))
    coef_next: np.ndarray  # (len(FEATURES) + 3, len(PHYSIOLOGY))
    resid_sd: np.ndarray  # (2, len(PHYSIOLOGY)): hour 1, later hours
    inputs: tuple[str, ...] = INIT_FEATURES
    residual_noise: bool = False
    name: str = "fitted"

    @classmethod
    def fit(
        cls,
        train: pd.DataFrame,
        *,
        inputs: str = "init",
        residual_noise: bool = False,
        name: str = "fitted",
        t_max: int = T_MAX,
    ) -> FittedTwin:
        if inputs not in ("init", "all"):
            raise ContractError(f"twins.{name}.inputs must be 'init' or 'all', got {inputs!r}")
        first_inputs = INIT_FEATURES if inputs == "init" else FEATURES
        x = to_array(train, FEATURES, t_max)
        d = to_array(train, (IV_FLUID, VASOPRESSOR), t_max)
        cols = [FEATURES.index(f) for f in PHYSIOLOGY]
        fi = [FEATURES.index(f) for f in first_inputs]
        parts = []
        for design, target in (
            (cls._design(x[:, 0, fi], d[:, 0, :]), x[:, 1, cols]),
            (
                cls._design(x[:, 1:-1, :].reshape(-1, len(FEATURES)), d[:, 1:-1, :].reshape(-1, 2)),
                x[:, 2:, cols].reshape(-1, len(cols)),
            ),
        ):
            coef, *_ = np.linalg.lstsq(design, target, rcond=None)
            resid = target - design @ coef
            parts.append((coef, resid.std(axis=0, ddof=design.shape[1])))
        return cls(
            coef_first=parts[0][0],
            coef_next=parts[1][0],
            resid_sd=np.vstack([parts[0][1], parts[1][1]]),
            inputs=tuple(first_inputs),
            residual_noise=residual_noise,
            name=name,
        )

    @staticmethod
    def _design(x: np.ndarray, doses: np.ndarray) -> np.ndarray:
        return np.column_stack([np.ones(len(x)), x, g_iv(doses[:, 0]), g_v(doses[:, 1])])

    def simulate(self, x0: pd.DataFrame, doses: np.ndarray, seeds: np.ndarray) -> SimResult:
        def predict(design: np.ndarray, coef: np.ndarray) -> np.ndarray:
            # design @ coef summed term by term in a fixed order: BLAS may
            # split and order a matrix product's sums differently with the
            # number of rows, so a run's numbers could change in the last bits
            # with its batch; this sum is the same for a row in any batch (the
            # Twin interface: results do not depend on how runs are batched).
            pred = design[:, :1] * coef[0]
            for j in range(1, design.shape[1]):
                pred = pred + design[:, j : j + 1] * coef[j]
            return pred

        n, hours, _ = doses.shape
        cur = x0[list(FEATURES)].to_numpy(float).copy()
        cols = [FEATURES.index(f) for f in PHYSIOLOGY]
        keys = noise.dose_prefix_keys(doses)
        out = np.empty((n, hours, len(FEATURES)))
        for s in range(hours):
            if s == 0:
                pred = predict(
                    self._design(x0[list(self.inputs)].to_numpy(float), doses[:, 0, :]),
                    self.coef_first,
                )
            else:
                pred = predict(self._design(cur, doses[:, s, :]), self.coef_next)
            if self.residual_noise:
                eps = noise.normal(
                    noise.combine(
                        np.asarray(seeds, np.uint64)[:, None],
                        keys[:, s, None],
                        s + 1,
                        np.arange(len(cols), dtype=np.uint64),
                    )
                )
                pred = pred + self.resid_sd[min(s, 1)] * eps
            nxt = cur.copy()
            nxt[:, cols] = pred
            out[:, s, :] = nxt
            cur = nxt
        return _ok(out)
