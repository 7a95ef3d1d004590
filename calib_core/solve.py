"""Weighted, regularised, robust Levenberg-Marquardt for point residuals, with an honest covariance.

The problem is `r(x) = (measured - predicted) / sigma`, three rows per pose, with an analytic Jacobian.
Tikhonov rows `(x - x_prior) / prior_std` pull toward the nominal model; a robust loss (Huber or Cauchy)
down-weights whole poses by iteratively re-weighted least squares on the pose's residual norm.
Covariance: the posterior s^2 (J'WJ + L)^-1 with s^2 = |r|^2 / (m - p), not scipy's half cost (p: the number
of directions the data and prior determine). A prior pulls the estimate toward it; the sandwich
s^2 H^-1 J'WJ H^-1 (H = J'WJ + L) is that biased estimate's spread alone, and a parameter the prior holds would get
almost no variance. H^-1 is the sandwich plus the pull's mean square when the truth lies within the prior, so it
covers the estimate's error against the truth.

Units: parameters of very different size live side by side (mm, rad, an effect in 1/(N*mm^2) ~ 1e-11), so
the damped step and the covariance are computed in Jacobi-scaled variables z = D x, D = the column norms of
the weighted Jacobian plus prior (the root of diag(J'WJ + L)), and mapped back. Results are then invariant to
the units of the parameters: multiplying a column by c and dividing its parameter by c changes that
parameter's std by 1/c and nothing else. A direction that data and prior do not determine (eigenvalue of the
scaled normal matrix below UNDETERMINED_TOL of the largest) gets no variance in `cov` and an infinite `std`
for every parameter that takes part in it, flagged in `Solution.undetermined`: never a NaN, never a
falsely tiny std.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Generator

import numpy as np

ROBUST_K = {"huber": 2.0, "cauchy": 2.4}
"""Tuning constants on the pose residual norm in units of its robust scale (3-D residuals)."""
OUTLIER_U = 5.0
"""With a robust loss, a pose whose residual exceeds 5 robust sigmas (chi(3): p < 2e-5) is an outlier."""
UNDETERMINED_TOL = 1e-12
"""Eigenvalues of the scaled (unit-diagonal) normal matrix below this fraction of the largest are numerically
zero: a condition number past 1e12, far beyond any direction the data could determine in double precision."""
UNDETERMINED_SHARE = 1e-6
"""A parameter whose scaled unit vector has more than this squared share in the undetermined directions is
itself undetermined (std = inf)."""


@dataclass
class Solution:
    x: np.ndarray  # the solved parameters (same length as x0)
    cov: np.ndarray  # (p, p) covariance of the solved parameters
    residual: np.ndarray  # (N, 3) unweighted residual measured - predicted at the solution
    weights: np.ndarray  # (N,) final robust weights (1 without a robust loss)
    u: np.ndarray | None  # (N,) residual norm in robust sigmas (only with a robust loss)
    s2: float  # a-posteriori variance factor |r|^2 / (m - p), p = the number of determined directions
    iterations: int
    converged: bool
    undetermined: np.ndarray | None = None  # (p,) bool: data and prior leave the parameter undetermined

    @property
    def std(self) -> np.ndarray:
        """1-sigma of every parameter, conditional on the model; inf where the parameter is undetermined."""
        s = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        if self.undetermined is not None:
            s = np.where(self.undetermined, np.inf, s)
        return s

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


def least_squares(residual_jac: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x0: np.ndarray,
                  sigma: np.ndarray, **options) -> Solution:
    """Minimise sum_i w_i |r_i / sigma_i|^2 + |(x - prior) / prior_std|^2.

    residual_jac(x) -> (r (N, 3) measured - predicted, J (N, 3, p) = d predicted / dx).
    sigma (N,) is the 1-sigma per-coordinate uncertainty of each pose, same length unit as r.
    options: those of `lm_steps` (prior, robust loss, tolerances, covariance, damping)."""
    return solve_together([lm_steps(x0, sigma, **options)], lambda asks: [residual_jac(x) for _, x in asks])[0]


def solve_together(runs: list[Generator], evaluate: Callable[[list], list]) -> list[Solution]:
    """Independent `lm_steps` runs driven in lockstep: each round, the points all unfinished runs ask for are
    evaluated by one call evaluate([(run index, x), ...]) -> [(r, J), ...] (a caller can evaluate them in one
    vectorised pass); every run takes exactly the steps it would take alone."""
    out: list = [None] * len(runs)
    asks = {k: next(run) for k, run in enumerate(runs)}
    while asks:
        answers = evaluate(list(asks.items()))
        nxt = {}
        for k, rj in zip(list(asks), answers):
            try:
                nxt[k] = runs[k].send(rj)
            except StopIteration as done:
                out[k] = done.value
        asks = nxt
    return out


def lm_steps(
    x0: np.ndarray,
    sigma: np.ndarray,
    *,
    prior: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
    loss: str | None = None,
    max_iter: int = 100,
    ftol: float = 1e-10,
    atol: float = 1e-14,
    covariance: bool = True,
    damping: float = 1e-4,
    constant_from: int | None = None,
) -> Generator[np.ndarray, tuple[np.ndarray, np.ndarray], Solution]:
    """Levenberg-Marquardt as a generator: yields each point x it needs evaluated, is sent (r, J) there (as
    least_squares' residual_jac returns them), and returns the Solution (StopIteration.value).

    Converged when the next step would lower the weighted cost by less than ftol * cost + atol.
    `damping` is the initial Marquardt damping (relative to the unit diagonal of the scaled normal matrix): a
    start already near the optimum (a warm start) takes Gauss-Newton steps at once with a small one.
    covariance=False skips the covariance (cov NaN, s2 on m - p degrees of freedom): for fits whose estimate
    alone is used, such as cross-validation folds. `constant_from`: the Jacobian's columns from this parameter on do
    not depend on x (a smooth field's weights), so their block of the normal matrix is made once per set of weights.
    """
    if loss not in (None, "huber", "cauchy"):
        raise ValueError(f"unknown robust loss {loss!r}; use 'huber', 'cauchy' or none")
    x = np.array(x0, dtype=float)
    p = len(x)
    inv_s = 1.0 / np.asarray(sigma, dtype=float)
    reg = prior is not None and prior_std is not None
    lam_diag = (1.0 / np.asarray(prior_std) ** 2) if reg else np.zeros(p)
    prior = x0 if prior is None else prior

    def root_weights(w):
        """sqrt(w) per pose (N, 1) and the Jacobian's row weights sqrt(w) / sigma (N, 1, 1): made once per w."""
        sq = np.sqrt(w)
        return sq[:, None], sq[:, None, None] * inv_s[:, None, None]

    fixed: list = []  # (sw, the constant columns' block of the normal matrix at those weights)

    def gram(JwT):
        """J'WJ; with constant_from, its constant columns' block made once per set of weights (sw)."""
        if constant_from is None:
            return JwT @ JwT.T
        k = constant_from
        Jv, Jc = JwT[:k], JwT[k:]
        if not fixed or fixed[0][0] is not sw:
            fixed[:] = [(sw, Jc @ Jc.T)]
        A = np.empty((p, p))
        A[:k, :k] = Jv @ Jv.T
        A[:k, k:] = Jv @ Jc.T
        A[k:, :k] = A[:k, k:].T
        A[k:, k:] = fixed[0][1]
        return A

    def normal_eq(x, r, J):
        rw = r * inv_s[:, None]
        rww = (rw * sqw).ravel()
        if J.transpose(2, 0, 1).flags.c_contiguous:  # laid out parameters first (Chain.jacobian): no transpose copy
            JwT = (J.transpose(2, 0, 1) * sw[:, :, 0]).reshape(p, -1)
        else:
            JwT = (J * sw).reshape(-1, p).T
        dx = x - prior
        cost = rww @ rww + (dx**2 * lam_diag).sum()
        A = gram(JwT)
        g = JwT @ rww - lam_diag * dx
        return rw, A, g, cost

    w = np.ones(len(inv_s))
    sqw, sw = root_weights(w)
    r, J = yield x
    rw, A, g, cost = normal_eq(x, r, J)
    mu = damping  # Marquardt damping, relative to the unit diagonal of the scaled normal matrix
    grow = 2.0  # Nielsen's factor for the next rejected step
    converged, it = False, 0
    L, eye = np.diag(lam_diag), np.eye(p)
    for it in range(1, max_iter + 1):
        H = A + L
        Hs, S = _scaled(H)
        try:  # step in the scaled variables z = D x: (S H S + mu I) dz = S g, dx = S dz
            step = S * np.linalg.solve(Hs + mu * eye, S * g)
        except np.linalg.LinAlgError:
            mu, grow = mu * grow, 2.0 * grow
            continue
        if not np.isfinite(step).all():
            mu, grow = mu * grow, 2.0 * grow
            continue
        if step @ g <= ftol * cost + atol:  # predicted chi-square decrease: nothing left to gain
            converged = True
            break
        x_new = x + step
        r_new, J_new = yield x_new
        rw_new, A_new, g_new, cost_new = normal_eq(x_new, r_new, J_new)
        if not cost_new <= cost:
            mu, grow = mu * grow, 2.0 * grow
            continue
        # Nielsen's update from the gain ratio rho (actual over the linear model's decrease 2 s.g - s.H.s): a step
        # the model predicted well lowers the damping, a poor one keeps it (/10 on any success, x10 on a failure
        # swung between the two: the Motoman's diagnosis evaluated the chain 349 times, 309 with this)
        model_drop = 2.0 * (step @ g) - step @ (H @ step)
        rho = (cost - cost_new) / model_drop if model_drop > 0 else 1.0
        x, r, J, rw, A, g, cost = x_new, r_new, J_new, rw_new, A_new, g_new, cost_new
        mu, grow = max(mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-15), 2.0
        if loss is not None:
            w_new = _robust_weights(_standardised(rw), loss)
            if not np.allclose(w_new, w, atol=1e-6):
                w = w_new
                sqw, sw = root_weights(w)
                rw, A, g, cost = normal_eq(x, r, J)
    if covariance:
        cov1, undetermined, rank = _covariance(A, lam_diag)
    else:
        cov1, undetermined, rank = np.full((p, p), np.nan), None, p
    m = rw.size
    dof = max(m - rank, 1)  # an undetermined direction uses up no degree of freedom
    s2 = float((w[:, None] * rw**2).sum() / dof)
    cov = s2 * cov1
    u = _standardised(rw) if loss is not None else None
    return Solution(x=x, cov=cov, residual=r, weights=w, u=u, s2=s2, iterations=it, converged=converged,
                    undetermined=undetermined)


def _scaled(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """S H S with S = 1 / sqrt(diag H) (1 where a column is empty): unit diagonal, unit-free."""
    d = np.sqrt(np.maximum(H.diagonal(), 0.0))
    S = 1.0 / np.where(d > 0, d, 1.0)
    return H * S[:, None] * S[None, :], S


def _covariance(A: np.ndarray, lam_diag: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Posterior covariance per unit variance factor, the mask of undetermined parameters, and the rank.

    A = J'WJ, L = diag(lam_diag), H = A + L: H^-1 (A^-1 without a prior). Computed on the Jacobi-scaled H by an
    eigen-decomposition: directions with eigenvalue below UNDETERMINED_TOL of the largest carry no variance
    here, and the parameters in them are flagged (their std is inf)."""
    p = len(lam_diag)
    if p == 0:
        return np.zeros((0, 0)), np.zeros(0, bool), 0
    H = A + np.diag(lam_diag)
    Hs, S = _scaled(H)
    e, U = np.linalg.eigh(0.5 * (Hs + Hs.T))
    top = max(float(e.max()), 0.0)
    keep = e > UNDETERMINED_TOL * top if top > 0 else np.zeros(p, bool)
    Uk = U[:, keep]
    Hinv_s = (Uk / e[keep]) @ Uk.T  # pseudo-inverse on the determined subspace
    cov = Hinv_s * S[:, None] * S[None, :]
    cov = 0.5 * (cov + cov.T)
    undetermined = (U[:, ~keep] ** 2).sum(1) > UNDETERMINED_SHARE
    return cov, undetermined, int(keep.sum())
