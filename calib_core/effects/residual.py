"""Structure no named cause explains: a smooth correction field over joint space, the same plug-in shape.

dp(q) = W phi(q), with phi = per-joint harmonics (cos h q_j, sin h q_j, h = 1, 2; Legendre terms of the
travel for prismatic joints) plus random Fourier features of [cos q, sin q, travel] for interactions:
an additive-plus-kernel (Gaussian-process) regression of the residual, fitted jointly with the geometry
with a ridge prior on W. It is linear in its weights, so the solver, the covariance and the compensation
treat it like any other effect; its length scale is chosen by held-out error. This is the nonparametric
baseline of Wang et al. (back-propagation network over joint-angle regions) done the calibrated way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import Basis, Context, Effect

LENGTH_SCALES = (None, 1.0, 2.0, 3.0)
"""None: additive harmonics only; otherwise also random Fourier features of that length scale."""
N_FEATURES = 96
PRIOR_STD_MM = 0.5


def _travel(model, q, j: int) -> np.ndarray:
    """Prismatic joint j's position over its travel, -1..1 between its limits."""
    lo, hi = model.limits[j]
    return (q[:, j] - 0.5 * (lo + hi)) / (0.5 * (hi - lo))


@dataclass(frozen=True)
class ResidualField(Effect):
    """A smooth Cartesian correction over joint space; weights in mm."""

    kind = "unexplained"
    fixed_columns = True  # its weights move no joint: identify makes their block of the normal matrix once
    length_scale: float | None = None
    n_features: int = N_FEATURES
    seed: int = 0
    prior_std: float = PRIOR_STD_MM

    def _features(self, model, q) -> np.ndarray:
        cols, z = [], []
        for j in model.actuated:  # coupled rows follow them, fixed rows never move
            if model.prismatic[j]:
                s = _travel(model, q, j)
                cols += [s, 1.5 * s**2 - 0.5, 2.5 * s**3 - 1.5 * s]
                z.append(s)
            else:
                cols += [f(h * q[:, j]) for h in (1, 2) for f in (np.cos, np.sin)]
                z += [np.cos(q[:, j]), np.sin(q[:, j])]
        phi = np.column_stack(cols)
        if self.length_scale is not None:
            z = np.column_stack(z)
            rng = np.random.default_rng(self.seed)
            omega = rng.normal(0.0, 1.0 / self.length_scale, (z.shape[1], self.n_features))
            phase = rng.uniform(0, 2 * np.pi, self.n_features)
            phi = np.column_stack([phi, np.sqrt(2.0 / self.n_features) * np.cos(z @ omega + phase)])
        return phi

    def _n(self, model) -> int:
        per_joint = sum(3 if p else 4 for p in model.prismatic[model.actuated])
        return per_joint + (self.n_features if self.length_scale is not None else 0)

    def parameter_names(self, model):
        return [f"field.{a}{k}" for a in "xyz" for k in range(self._n(model))]

    def parameter_units(self, model):
        return ["mm"] * (3 * self._n(model))

    def basis(self, ctx: Context) -> Basis:
        phi = self._features(ctx.model, ctx.meas.joints)  # (N, F)
        N, F = phi.shape
        cart = np.zeros((N, 3, 3 * F))
        for a in range(3):
            cart[:, a, a * F:(a + 1) * F] = phi
        return Basis(None, cart, np.zeros(N), "")

    def describe(self) -> str:
        inter = "" if self.length_scale is None else f" plus {self.n_features} random Fourier features " \
                                                      f"(length scale {self.length_scale:g})"
        return f"per-joint harmonics{inter}"

    def explain(self, model):
        return "a smooth error over joint space that no named cause explains"


def field_prior_std(current) -> float:
    """The field's ridge prior std (mm per unit feature): on the scale of the residual it is to correct."""
    return max(PRIOR_STD_MM, 2.0 * current.metrics()["holdout_rms_mm"])


def fit_residual_field(fit, current, chosen, x_ref, scales=LENGTH_SCALES):
    """Best field by held-out RMS over the length scales `scales`, fitted jointly with geometry and chosen effects
    (`fit(effects, x_ref)` identifies on the diagnosis's data and options)."""
    best = None
    prior = field_prior_std(current)
    for ls in scales:
        rf = ResidualField((), length_scale=ls, prior_std=prior)
        try:
            cal = fit(tuple(chosen) + (rf,), x_ref)
        except ValueError:
            continue  # too few poses for the field's weights
        if best is None or cal.metrics()["holdout_rms_mm"] < best[0].metrics()["holdout_rms_mm"]:
            best = (cal, rf)
    return best
