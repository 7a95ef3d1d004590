"""Weighted, regularised, robust Levenberg-Marquardt for point residuals, with an honest covariance.

The problem is `r(x) = (measured - predicted) / sigma`, three rows per pose, with an analytic Jacobian.
Tikhonov rows `(x - x_prior) / prior_std` pull toward the nominal model; a robust loss (Huber or Cauchy)
down-weights whole poses by iteratively re-weighted least squares on the pose's residual norm.
Covariance: s^2 (J'WJ + L)^-1 J'WJ (J'WJ + L)^-1 with s^2 = |r|^2 / (m - p), not scipy's half cost.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

ROBUST_K = {"huber": 2.0, "cauchy": 2.4}
"""Tuning constants on the pose residual norm in units of its robust scale (3-D residuals)."""
OUTLIER_U = 5.0
"""With a robust loss, a pose whose residual exceeds 5 robust sigmas (chi(3): p < 2e-5) is an outlier."""


@dataclass
class Solution:
    x: np.ndarray  # the solved parameters (same length as x0)
    cov: np.ndarray  # (p, p) covariance of the solved parameters
    residual: np.ndarray  # (N, 3) unweighted residual measured - predicted at the solution
    weights: np.ndarray  # (N,) final robust weights (1 without a robust loss)
    u: np.ndarray | None  # (N,) residual norm in robust sigmas (only with a robust loss)
    s2: float  # a-posteriori variance factor |r|^2 / (m - p)
    iterations: int
    converged: bool

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def outliers(self) -> np.ndarray:
        """Indices of the poses the robust loss treated as outliers (none without one)."""
        return np.array([], int) if self.u is None else np.flatnonzero(self.u > OUTLIER_U)


def _standardised(rw: np.ndarray) -> np.ndarray:
    """Per-pose residual norm in units of its robust scale, from the (N, 3) sigma-weighted residual."""
    u = np.linalg.norm(rw, axis=1)
    scale = np.sqrt(np.median(u**2) / 2.366)  # median of chi-square(3) is 2.366
    return u / max(scale, 1e-300)


def _robust_weights(u: np.ndarray, loss: str) -> np.ndarray:
    """Per-pose IRLS weights of the Huber or Cauchy loss."""
    k = ROBUST_K[loss]
    if loss == "huber":
        return np.where(u <= k, 1.0, k / u)
    return 1.0 / (1.0 + (u / k) ** 2)


def least_squares(
    residual_jac: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0: np.ndarray,
    sigma: np.ndarray,
    *,
    prior: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
    loss: str | None = None,
    max_iter: int = 100,
    ftol: float = 1e-10,
    atol: float = 1e-14,
) -> Solution:
    """Minimise sum_i w_i |r_i / sigma_i|^2 + |(x - prior) / prior_std|^2.

    residual_jac(x) -> (r (N, 3) measured - predicted, J (N, 3, p) = d predicted / dx).
    sigma (N,) is the 1-sigma per-coordinate uncertainty of each pose, same length unit as r.
    Converged when the next step would lower the weighted cost by less than ftol * cost + atol.
    """
    if loss not in (None, "huber", "cauchy"):
        raise ValueError(f"unknown robust loss {loss!r}; use 'huber', 'cauchy' or none")
    x = np.array(x0, dtype=float)
    p = len(x)
    inv_s = 1.0 / np.asarray(sigma, dtype=float)
    reg = prior is not None and prior_std is not None
    lam_diag = (1.0 / np.asarray(prior_std) ** 2) if reg else np.zeros(p)
    prior = x0 if prior is None else prior

    def normal_eq(x, w):
        r, J = residual_jac(x)
        rw = r * inv_s[:, None]
        sw = np.sqrt(w)[:, None, None] * inv_s[:, None, None]
        Jw = (J * sw).reshape(-1, p)
        rww = (rw * np.sqrt(w)[:, None]).ravel()
        cost = rww @ rww + ((x - prior) ** 2 * lam_diag).sum()
        A = Jw.T @ Jw
        g = Jw.T @ rww - lam_diag * (x - prior)
        return r, rw, A, g, cost

    w = np.ones(len(inv_s))
    r, rw, A, g, cost = normal_eq(x, w)
    mu = 1e-4  # Marquardt damping relative to diag(J'WJ + L)
    converged, it = False, 0
    for it in range(1, max_iter + 1):
        H = A + np.diag(lam_diag)
        D = np.diag(H).copy()
        D[D <= 0] = 1.0
        try:
            step = np.linalg.solve(H + mu * np.diag(D), g)
        except np.linalg.LinAlgError:
            mu *= 10
            continue
        if step @ g <= ftol * cost + atol:  # predicted chi-square decrease: nothing left to gain
            converged = True
            break
        r_new, rw_new, A_new, g_new, cost_new = normal_eq(x + step, w)
        if cost_new > cost:
            mu *= 10.0
            continue
        x, r, rw, A, g, cost = x + step, r_new, rw_new, A_new, g_new, cost_new
        mu = max(mu / 10.0, 1e-15)
        if loss is not None:
            w_new = _robust_weights(_standardised(rw), loss)
            if not np.allclose(w_new, w, atol=1e-6):
                w = w_new
                r, rw, A, g, cost = normal_eq(x, w)
    m = rw.size
    dof = max(m - p, 1)
    s2 = float((w[:, None] * rw**2).sum() / dof)
    H = A + np.diag(lam_diag)
    Hinv = np.linalg.pinv(H)
    cov = s2 * Hinv @ A @ Hinv if reg else s2 * Hinv
    u = _standardised(rw) if loss is not None else None
    return Solution(x=x, cov=cov, residual=r, weights=w, u=u, s2=s2, iterations=it, converged=converged)
