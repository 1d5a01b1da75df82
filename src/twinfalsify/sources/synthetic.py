"""A synthetic MIMIC-style ICU sepsis world with an unmeasured confounder and known truth.

Structure (all per stay; hours t = 0..T):

* Latent severity U ~ N(0, 1), never recorded.
* Demographics: age, sex (1 = female), weight; independent of U.
* Physiology: 15 features (vitals, labs, pH) on a working scale z (identity, or
  log for the skewed RR, Glucose and paO2). MeanBP is (SysBP + 2 DiaBP)/3 plus
  independent noise at every hour. For every other physiological feature k:

      z_0[k] = m_k(age, sex) + b0_k U + s0_k e_0k
      z_t[k] = m_k + rho_k (z_{t-1}[k] - m_k) + d_k U
               + c_iv_k g_iv(iv_t) + c_v_k g_v(vaso_t) + s_k e_tk,   t >= 1

  with independent standard normal e, g_iv(d) = log(1 + d/100) for IV fluid in
  mL/h and g_v(d) = d / (d + 0.15) (an Emax curve) for vasopressor in ug/kg/min.
  Fluids raise blood pressure, lower heart rate, raise chloride and lower
  bicarbonate (saline); vasopressors raise blood pressure and heart rate.
* Clinicians (observational policy) choose the dose for hour t -> t+1 from the
  observed MeanBP_t, the previous dose AND U: sicker patients get more fluid and
  vasopressor. U also drives deterioration (d_k), so U confounds treatment and
  outcome: the treated look worse than they would under the same treatment
  given at random.
* Plausible values: every value lies in the trajectory contract's plausible range
  (``schema.FEATURE_TABLE``; the Gaussian tails would leave it once in about a million
  values, e.g. paCO2 below 5 mmHg). X_0 is drawn from its law truncated to the ranges (a
  stay whose X_0 leaves one is drawn again: U, e_0 and the MeanBP noise), and a value of
  hour t >= 1 is clipped to its range, in the observed world and in the oracle alike.

Exact interventional law. Actions do not affect U or X_0, and given U the
dynamics are linear-Gaussian in U with doses fixed, so

    P(X_1:t(a_1:t) | X_0 = x_0) = int P(X_1:t | x_0, U, a_1:t) p(U | x_0) dU,

with p(U | x_0) Gaussian in closed form (conjugate): precision
1 + sum_k b0_k^2 / s0_k^2 and mean sum_k b0_k (z_0[k] - m_k) / s0_k^2 / precision
(MeanBP carries no information on U beyond SysBP and DiaBP). The oracle twin
draws U from this posterior and runs the dynamics forward: an exact sampler of
the interventional distribution, hence an interventionally correct twin. The truncation of
X_0 leaves p(U | x_0) as it is for every x_0 inside the ranges (the truncation depends on x_0
alone), and the oracle clips its hours t >= 1 as the world does, so it stays exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from twinfalsify import noise
from twinfalsify.schema import (
    DOSES,
    FEATURE_TABLE,
    FEATURES,
    IV_FLUID,
    STAY_ID,
    T_MAX,
    TIME,
    VASOPRESSOR,
)

# Physiological features simulated directly (MeanBP is derived).
DYNAMIC = (
    "HR", "SysBP", "DiaBP", "RR", "Temp_C", "Potassium", "Sodium", "Chloride",
    "Glucose", "Calcium", "HCO3", "paO2", "paCO2", "Arterial_pH",
)  # fmt: skip
LOG_SCALE = ("RR", "Glucose", "paO2")

#          mean    s0     b0     rho   drift   s      c_iv   c_v
_PARAMS = {
    "HR": (92.0, 14.0, 9.0, 0.6, 2.5, 5.0, -1.5, 6.0),
    "SysBP": (118.0, 16.0, -9.0, 0.6, -3.5, 7.0, 3.0, 14.0),
    "DiaBP": (61.0, 10.0, -6.0, 0.6, -2.0, 5.0, 2.0, 8.0),
    "RR": (np.log(20.0), 0.2, 0.14, 0.6, 0.035, 0.11, 0.0, 0.0),
    "Temp_C": (37.0, 0.7, 0.3, 0.8, 0.05, 0.3, -0.05, 0.0),
    "Potassium": (4.1, 0.55, 0.25, 0.85, 0.05, 0.2, -0.1, -0.15),
    "Sodium": (139.0, 4.0, 0.0, 0.85, 0.0, 1.2, -0.3, 0.0),
    "Chloride": (105.0, 5.0, 0.5, 0.85, 0.2, 1.5, 1.2, 0.0),
    "Glucose": (np.log(135.0), 0.3, 0.08, 0.8, 0.02, 0.12, -0.02, 0.05),
    "Calcium": (8.3, 0.65, -0.25, 0.85, -0.05, 0.2, -0.1, 0.0),
    "HCO3": (23.0, 3.5, -2.0, 0.85, -0.6, 1.2, -0.6, 0.0),
    "paO2": (np.log(110.0), 0.42, -0.1, 0.8, -0.03, 0.2, 0.0, 0.0),
    "paCO2": (40.0, 7.5, -2.0, 0.8, -0.6, 3.0, 0.0, 0.0),
    "Arterial_pH": (7.38, 0.06, -0.035, 0.8, -0.012, 0.025, -0.01, 0.0),
}


_IDX = {f: i for i, f in enumerate(FEATURES)}
_DYN_IDX = [_IDX[k] for k in DYNAMIC]
_LO = np.array([f.lo for f in FEATURE_TABLE])
_HI = np.array([f.hi for f in FEATURE_TABLE])
_MAX_REDRAWS = 100  # rounds of drawing X_0 again (each round keeps ~1 - 1e-5 of the rows)


def _features(x0: pd.DataFrame | np.ndarray) -> np.ndarray:
    """Rows of X_0 as an (n, len(FEATURES)) array (one pandas call, then numpy only)."""
    if isinstance(x0, np.ndarray):
        return x0
    return x0[list(FEATURES)].to_numpy(float)


def g_iv(dose: np.ndarray) -> np.ndarray:
    """Fluid response curve: log(1 + mL/h / 100)."""
    return np.log1p(np.asarray(dose, float) / 100.0)


def g_v(dose: np.ndarray) -> np.ndarray:
    """Vasopressor response curve (Emax, EC50 0.15 ug/kg/min)."""
    d = np.asarray(dose, float)
    return d / (d + 0.15)


@dataclass(frozen=True)
class SyntheticWorld:
    """Parameters of the world; the defaults are the default study's."""

    n_stays: int = 11677
    t_max: int = T_MAX
    confounding: float = 1.0  # scales U's weight in the clinicians' policy
    meanbp_noise: float = 2.0
    params: dict[str, tuple[float, ...]] = field(default_factory=lambda: dict(_PARAMS))

    @classmethod
    def from_config(cls, cfg: dict[str, Any] | None) -> SyntheticWorld:
        cfg = dict(cfg or {})
        unknown = set(cfg) - {"n_stays", "confounding", "meanbp_noise"}
        if unknown:
            raise ValueError(f"source.synthetic: unknown key(s) {sorted(unknown)}")
        return replace(cls(), **cfg)

    # -- pieces -------------------------------------------------------------
    def _vec(self, i: int) -> np.ndarray:
        return np.array([self.params[k][i] for k in DYNAMIC])

    def baseline_mean(self, age: np.ndarray, sex: np.ndarray) -> np.ndarray:
        """m_k(age, sex), shape (n, len(DYNAMIC)), on the working scale."""
        m = np.broadcast_to(self._vec(0), (len(age), len(DYNAMIC))).copy()
        col = {k: j for j, k in enumerate(DYNAMIC)}
        m[:, col["SysBP"]] += 0.2 * (age - 65.0)
        m[:, col["HR"]] += -0.1 * (age - 65.0) + 3.0 * sex
        m[:, col["Calcium"]] += -0.1 * sex
        return m

    def posterior_u(self, x0: pd.DataFrame | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact Gaussian p(U | X_0 = x0): (mean, sd) per row."""
        x = _features(x0)
        z0 = self.to_working(x)
        m = self.baseline_mean(x[:, _IDX["age"]], x[:, _IDX["sex"]])
        b0, s0 = self._vec(2), self._vec(1)
        precision = 1.0 + np.sum(b0**2 / s0**2)
        mean = ((z0 - m) * (b0 / s0**2)).sum(axis=1) / precision
        return mean, np.full(len(x0), 1.0 / np.sqrt(precision))

    def to_working(self, frame: pd.DataFrame | np.ndarray) -> np.ndarray:
        z = _features(frame)[:, _DYN_IDX].astype(float)
        for j, k in enumerate(DYNAMIC):
            if k in LOG_SCALE:
                z[:, j] = np.log(z[:, j])
        return z

    def from_working(self, z: np.ndarray) -> np.ndarray:
        out = z.copy()
        for j, k in enumerate(DYNAMIC):
            if k in LOG_SCALE:
                out[..., j] = np.exp(out[..., j])
        return out

    def step(
        self,
        z_prev: np.ndarray,
        u: np.ndarray,
        iv: np.ndarray,
        vaso: np.ndarray,
        eps: np.ndarray,
        *,
        dose_effect_scale: tuple[float, float] = (1.0, 1.0),
    ) -> np.ndarray:
        """One hour of the true dynamics on the working scale (vectorised over rows)."""
        mean, rho, drift, s = self._vec(0), self._vec(3), self._vec(4), self._vec(5)
        c_iv, c_v = self._vec(6), self._vec(7)
        return (
            mean
            + rho * (z_prev - mean)
            + drift * u[:, None]
            + dose_effect_scale[0] * c_iv * g_iv(iv)[:, None]
            + dose_effect_scale[1] * c_v * g_v(vaso)[:, None]
            + s * eps
        )

    def features_frame(self, demo: np.ndarray, z: np.ndarray, meanbp_eps: np.ndarray,
                       *, clip: bool = True) -> np.ndarray:
        """Assemble (n, len(FEATURES)) in schema order from demographics and working z,
        each value clipped to its plausible range (``clip``; module doc)."""
        x = self.from_working(z)
        col = {k: j for j, k in enumerate(DYNAMIC)}
        out = np.empty((len(z), len(FEATURES)))
        for j, name in enumerate(FEATURES):
            if name in ("age", "sex", "weight"):
                out[:, j] = demo[:, ("age", "sex", "weight").index(name)]
            elif name == "MeanBP":
                out[:, j] = (
                    x[:, col["SysBP"]] + 2 * x[:, col["DiaBP"]]
                ) / 3 + self.meanbp_noise * meanbp_eps
            else:
                out[:, j] = x[:, col[name]]
        return np.clip(out, _LO, _HI) if clip else out

    def _plausible_x0(self, rng: np.random.Generator, demo: np.ndarray, m: np.ndarray,
                      u: np.ndarray, z: np.ndarray, eps: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(U, z_0, MeanBP noise) with the rows whose X_0 leaves a plausible range drawn
        again until none does: X_0 from its law truncated to the ranges (module doc). No
        draw is made when every row is inside, so such a world is unchanged."""
        b0, s0 = self._vec(2), self._vec(1)
        for _ in range(_MAX_REDRAWS):
            x = self.features_frame(demo, z, eps, clip=False)
            bad = ((x < _LO) | (x > _HI)).any(axis=1)
            if not bad.any():
                return u, z, eps
            k = int(bad.sum())
            u[bad] = rng.standard_normal(k)
            z[bad] = m[bad] + b0 * u[bad, None] + s0 * rng.standard_normal((k, len(DYNAMIC)))
            eps[bad] = rng.standard_normal(k)
        raise RuntimeError(f"synthetic world: X_0 of {int(bad.sum())} stay(s) still outside "
                           f"the plausible ranges after {_MAX_REDRAWS} draws")

    # -- observational data -------------------------------------------------
    def sample_observational(
        self, seed: int, fixed_doses: np.ndarray | None = None
    ) -> pd.DataFrame:
        """Draw the observational cohort (trajectory contract, MIMIC units).

        fixed_doses (t_max, 2): give every patient these doses instead of the
        clinicians' choice (a randomised-trial world, for checking the oracle).
        """
        rng = np.random.default_rng(seed)
        n, t_max = self.n_stays, self.t_max
        age = np.clip(rng.normal(64.0, 16.0, n), 18.0, 95.0).round()
        sex = (rng.random(n) < 0.44).astype(float)
        weight = np.clip(rng.normal(84.0 - 12.0 * sex, 17.0), 40.0, 180.0).round(1)
        demo = np.column_stack([age, sex, weight])
        u = rng.standard_normal(n)
        m = self.baseline_mean(age, sex)
        z = m + self._vec(2) * u[:, None] + self._vec(1) * rng.standard_normal(m.shape)
        rows = []
        iv_prev, vaso_prev = np.zeros(n), np.zeros(n)
        for t in range(t_max + 1):
            eps_bp = rng.standard_normal(n)
            if t == 0:
                u, z, eps_bp = self._plausible_x0(rng, demo, m, u, z, eps_bp)
            x = self.features_frame(demo, z, eps_bp)
            iv, vaso = self._policy(rng, x, u, iv_prev, vaso_prev)
            if fixed_doses is not None and t < t_max:
                iv, vaso = np.full(n, fixed_doses[t, 0]), np.full(n, fixed_doses[t, 1])
            if t == t_max:
                iv, vaso = np.zeros(n), np.zeros(n)
            rows.append((x, iv, vaso))
            if t < t_max:
                z = self.step(z, u, iv, vaso, rng.standard_normal(z.shape))
                iv_prev, vaso_prev = iv, vaso
        stay_ids = np.arange(1, n + 1, dtype=np.int64) + 200000
        frames = []
        for t, (x, iv, vaso) in enumerate(rows):
            f = pd.DataFrame(x, columns=list(FEATURES))
            f.insert(0, TIME, t)
            f.insert(0, STAY_ID, stay_ids)
            f[IV_FLUID], f[VASOPRESSOR] = iv, vaso
            frames.append(f)
        out = pd.concat(frames, ignore_index=True)
        return out.sort_values([STAY_ID, TIME], kind="stable").reset_index(drop=True)

    def _policy(
        self,
        rng: np.random.Generator,
        x: np.ndarray,
        u: np.ndarray,
        iv_prev: np.ndarray,
        vaso_prev: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Clinicians' doses for the next hour: depend on MeanBP, the last dose and U."""
        n = len(u)
        mbp = x[:, FEATURES.index("MeanBP")]
        c = self.confounding
        logit_v = -2.8 + 1.3 * c * u - 0.07 * (mbp - 70.0) + 3.0 * (vaso_prev > 0)
        on_v = rng.random(n) < 1.0 / (1.0 + np.exp(-logit_v))
        new_v = np.exp(np.log(0.12) + 0.35 * c * u + 0.55 * rng.standard_normal(n))
        titrated_v = vaso_prev * np.exp(0.15 * rng.standard_normal(n))
        vaso = np.where(on_v, np.where(vaso_prev > 0, titrated_v, new_v), 0.0)
        vaso = np.round(np.clip(vaso, 0.0, 1.5), 3)
        logit_iv = -0.7 + 0.9 * c * u - 0.03 * (mbp - 70.0) + 1.5 * (iv_prev > 0)
        on_iv = rng.random(n) < 1.0 / (1.0 + np.exp(-logit_iv))
        new_iv = np.exp(np.log(110.0) + 0.4 * c * u + 0.85 * rng.standard_normal(n))
        iv = np.where(
            on_iv,
            np.where(iv_prev > 0, iv_prev * np.exp(0.2 * rng.standard_normal(n)), new_iv),
            0.0,
        )
        iv = np.round(np.clip(iv, 0.0, 2000.0), 1)
        return iv, vaso

    # -- interventional simulation (the oracle) -----------------------------
    def simulate_interventional(
        self,
        x0: pd.DataFrame,
        doses: np.ndarray,
        seeds: np.ndarray,
        *,
        dose_effect_scale: tuple[float, float] = (1.0, 1.0),
    ) -> np.ndarray:
        """Exact draw of X_1:t(a_1:t) given X_0 = x0: (n, t, len(FEATURES)).

        Randomness of run i is keyed by (seeds[i]) for U and by (seeds[i],
        doses of hours 1..s) for hour s, so shared prefixes give equal values.
        """
        n, hours, _ = doses.shape
        seeds = np.asarray(seeds, dtype=np.uint64)
        x0 = _features(x0)
        mean_u, sd_u = self.posterior_u(x0)
        u = mean_u + sd_u * noise.normal(noise.combine(seeds, 0xA11CE))
        demo = x0[:, [_IDX["age"], _IDX["sex"], _IDX["weight"]]]
        z = self.to_working(x0)
        keys = noise.dose_prefix_keys(doses)
        k_idx = np.arange(len(DYNAMIC) + 1, dtype=np.uint64)
        out = np.empty((n, hours, len(FEATURES)))
        for s in range(hours):
            eps_all = noise.normal(noise.combine(seeds[:, None], keys[:, s, None], s + 1, k_idx))
            z = self.step(
                z, u, doses[:, s, 0], doses[:, s, 1], eps_all[:, :-1],
                dose_effect_scale=dose_effect_scale,
            )  # fmt: skip
            out[:, s, :] = self.features_frame(demo, z, eps_all[:, -1])
        return out


def generate(config: dict[str, Any] | None, seed: int) -> pd.DataFrame:
    """The synthetic source's trajectories for a study config (section source.synthetic)."""
    return SyntheticWorld.from_config(config).sample_observational(seed)


__all__ = ["DOSES", "SyntheticWorld", "generate", "g_iv", "g_v"]
