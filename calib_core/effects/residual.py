"""Structure no named cause explains: a smooth correction field over joint space, the same plug-in shape.

dp(q) = W phi(q), phi = random Fourier features of [cos q, sin q] (revolute) and scaled travel (prismatic),
i.e. a kernel (Gaussian-process) regression of the residual, fitted jointly with the geometry with a ridge
prior on W. It beats a back-propagation network (the baseline of Wang et al., 8-DoF robot) on the same
footing: it is linear in its weights, so the solver, the covariance and the compensation treat it like
any other effect, and its length scale and ridge are chosen by held-out error.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import Basis, Context, Effect

N_FEATURES = 48
LENGTH_SCALES = (0.5, 1.0, 2.0)
PRIOR_STD_MM = 0.5


@dataclass(frozen=True)
class ResidualField(Effect):
    """A smooth Cartesian correction over joint space (3 x n_features weights, mm)."""

    kind = "unexplained"
    length_scale: float = 1.0
    n_features: int = N_FEATURES
    seed: int = 0
    prior_std: float = PRIOR_STD_MM

    def parameter_names(self, model):
        return [f"field.{a}{k}" for a in "xyz" for k in range(self.n_features)]

    def parameter_units(self, model):
        return ["mm"] * (3 * self.n_features)

    def _features(self, model, q):
        lo, hi = model.limits[:, 0], model.limits[:, 1]
        z = []
        for j in range(model.n_joints):
            if model.prismatic[j]:
                z.append((q[:, j] - 0.5 * (lo[j] + hi[j])) / (0.5 * (hi[j] - lo[j])))
            else:
                z += [np.cos(q[:, j]), np.sin(q[:, j])]
        z = np.column_stack(z)
        rng = np.random.default_rng(self.seed)
        omega = rng.normal(0.0, 1.0 / self.length_scale, (z.shape[1], self.n_features))
        phase = rng.uniform(0, 2 * np.pi, self.n_features)
        return np.sqrt(2.0 / self.n_features) * np.cos(z @ omega + phase)

    def basis(self, ctx: Context) -> Basis:
        phi = self._features(ctx.model, ctx.meas.joints)  # (N, F)
        N, F = phi.shape
        cart = np.zeros((N, 3, 3 * F))
        for a in range(3):
            cart[:, a, a * F:(a + 1) * F] = phi
        return Basis(None, cart, np.zeros(N), "")

    def explain(self, model):
        return "a smooth error over joint space that no named cause explains"


def fit_residual_field(model, meas, current, chosen, x_ref, *, loss=None, folds=5):
    """Best field by held-out RMS over the length scales, fitted jointly with geometry and chosen effects."""
    from ..identify import identify

    best = None
    for ls in LENGTH_SCALES:
        rf = ResidualField((), length_scale=ls)
        try:
            cal = identify(model, meas, effects=tuple(chosen) + (rf,), loss=loss, folds=folds, x_ref=x_ref)
        except ValueError:
            continue  # too few poses for the field's weights
        if best is None or cal.metrics()["holdout_rms_mm"] < best[0].metrics()["holdout_rms_mm"]:
            best = (cal, rf)
    return best
