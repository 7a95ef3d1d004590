"""Screening: every candidate cause scored by the linearised F-test of adding its columns to the current model,
with the Bonferroni thresholds per family (named causes, steps in time order)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import linalg, special

from ..effects import Context, Effect, SessionStep
from ..effects.base import Basis
from ..effects.residual import PRIOR_STD_MM, ResidualField
from ..identify import Calibration, effect_bases, pose_folds
from ..io import Measurements
from ..parallel import pmap
from .evidence import paired_gain

TIME_SHARE = 0.2
"""Share of ALPHA spent on steps in time order; the rest on the named causes."""
ABSORBED = 1e-3
"""A candidate's unit column keeping less than this norm outside the current model's span is absorbed by it."""


@dataclass
class Candidate:
    effect: Effect
    label: str
    p_value: float
    log_p: float
    F: float
    explained: float  # fraction of the weighted residual sum of squares it explains
    beyond_chance: float  # the same less the share its degrees of freedom would explain of pure noise
    bic: float  # Bayesian information criterion of the model with it: ranks candidates past p underflow
    dof: int  # the F-test's degrees of freedom: its columns the current model cannot absorb (+ search_dof)...
    residual_dof: int  # ...and the rows left with it
    effect_rms_mm: float  # RMS of the part of its displacement the current model cannot absorb
    regressor: np.ndarray
    regressor_label: str
    projected_residual_mm: np.ndarray  # residual along the effect's direction, per pose
    fitted_mm: np.ndarray  # the effect's fitted displacement along the same direction


def f_logsf(F: float, dfn: float, dfd: float) -> float:
    """log P(F' > F) for F' ~ F(dfn, dfd): scipy.stats.f.logsf's arithmetic (log of the upper tail above the median,
    log1p of the lower one below it) without its argument handling, 0.4 ms a call, which screening calls thousands
    of times."""
    with np.errstate(divide="ignore"):
        if F > special.fdtri(dfn, dfd, 0.5):
            return float(np.log(special.fdtrc(dfn, dfd, F)))
        return float(np.log1p(-special.fdtr(dfn, dfd, F)))


def _robust_sigma(cal: Calibration, sigma: np.ndarray) -> np.ndarray:
    """Per-pose sigma with the fit's robust weights folded in: a pose the loss down-weighted as an outlier
    counts as little in the tests as it did in the fit."""
    return sigma / np.sqrt(np.maximum(cal.solution.weights, 1e-6))


_SYSTEMS: list[tuple] = []
"""The last two weighted systems made (a round asks for the current model's up to four times: the screen, the play
search, the plays' screen, the held-out pre-check); each is an SVD of the whole Jacobian."""


def _weighted_system(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray):
    """Weighted residual (m,), orthonormal basis of the current model's Jacobian (m, r), and the chain (read-only:
    the same arrays are handed out again for the same model, poses, weights and reference geometry)."""
    key = (sigma.tobytes(), np.asarray(x_ref).tobytes(), cal.solution.x.tobytes(), cal.x.tobytes(),
           tuple(map(id, cal.effects)))
    for c, m, k, out in _SYSTEMS:
        if c is cal and m is meas and k == key:
            return out
    out = _weighted_system_of(cal, meas, sigma, x_ref)
    _SYSTEMS.append((cal, meas, key, out))
    del _SYSTEMS[:-2]
    return out


def _weighted_system_of(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray):
    model = cal.model
    chain, dp = cal.robot.chain(meas.joints, meas)
    r = (meas.points - chain.p - dp) / sigma[:, None]
    cols = [chain.jacobian_columns(cal.free)]
    if cal.effects:
        Pq, Pp = effect_bases(model, meas, list(cal.effects), x_ref if cal.x_basis is None else cal.x_basis, cal.R0)
        cols.append((chain.joint_jacobian() @ Pq) + Pp)
    J = (np.concatenate(cols, axis=2) / sigma[:, None, None]).reshape(len(r.ravel()), -1)
    return r.ravel(), orthonormal_basis(J), chain


def orthonormal_basis(J: np.ndarray) -> np.ndarray:
    """(m, r): an orthonormal basis of J's columns, its rank unit-free (columns scaled to unit norm first)."""
    norms = np.linalg.norm(J, axis=0)
    U, s, _ = np.linalg.svd(J / np.where(norms > 0, norms, 1.0), full_matrices=False)
    return U[:, s > s[0] * 1e-8]


def weighted_misfit(cal: Calibration, sigma: np.ndarray | None = None) -> float:
    """Sum of cal's squared residual in units of each pose's sigma (default the fit's own), with its robust weights
    (chi-square units)."""
    sigma = cal.sigma_mm if sigma is None else sigma
    return float(np.sum(cal.solution.weights[:, None] * (cal.solution.residual / sigma[:, None]) ** 2))


GRAM_RCOND = 1e-10
"""A fold's normal matrix (Jacobi-scaled) is solved by Cholesky when its reciprocal condition number is above this
(columns well apart: the normal equations lose at most 1e-6 of the solution), else by least squares on the rows."""


def fold_predictions(A: np.ndarray, r: np.ndarray, fold: np.ndarray, folds: int, ridge: np.ndarray | None = None
                     ) -> np.ndarray:
    """Each row of r (m,) predicted by the least-squares fit of A (m, k) on the rows of the other folds (`fold`
    (m,) the fold of each row), with `ridge` (k,) added to the normal matrix's diagonal if given. One Gram matrix,
    each fold's rows taken out of it (the SVD per fold cost Agile Justin 2 s of its diagnosis)."""
    G, b = A.T @ A, A.T @ r
    if ridge is not None:
        G = G + np.diag(ridge)
    pred = np.empty_like(r)
    for k in range(folds):
        te = fold == k
        At = A[te]
        Gk, bk = G - At.T @ At, b - At.T @ r[te]
        d = np.sqrt(np.maximum(Gk.diagonal(), 0.0))
        S = 1.0 / np.where(d > 0, d, 1.0)
        Gs = Gk * S[:, None] * S[None, :]
        L, info = linalg.lapack.dpotrf(Gs, lower=1)
        if info == 0 and linalg.lapack.dpocon(L, np.abs(Gs).sum(0).max(), uplo="L")[0] > GRAM_RCOND:
            theta = S * linalg.cho_solve((L, True), S * bk, check_finite=False)
        elif ridge is None:
            theta = np.linalg.lstsq(A[~te], r[~te], rcond=None)[0]
        else:
            theta = np.linalg.lstsq(Gk, bk, rcond=None)[0]
        pred[te] = At @ theta
    return pred


def _weighted_columns(e: Effect, ctx: Context, Jq: np.ndarray, sigma: np.ndarray):
    """The effect's columns of the coupled Jacobian, weighted, (m, k), and its basis."""
    b = ctx.basis(e)
    k = len(e.parameter_names(ctx.model))
    C = np.zeros((ctx.meas.n_poses, 3, k))
    if b.joint is not None:
        C += Jq @ b.joint
    if b.cart is not None:
        C += b.cart
    return (C / sigma[:, None, None]).reshape(-1, k), b


SCREEN_APART = 16
"""Pools of at least this many candidates are screened in several processes (a fork costs more than a few)."""


def screen(cal: Calibration, meas: Measurements, sigma: np.ndarray, pool: list[Effect], x_ref: np.ndarray,
           workers: int = 1) -> list[Candidate]:
    """Score every candidate by the F-test of adding it to the current model (linearised at its solution), best
    (lowest BIC) first; the candidates shared out to `workers` processes (parallel.pmap)."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ctx = Context.at(model, x_ref, meas, cal.R0)
    Jq = chain.joint_jacobian()
    m, p = len(r), Q.shape[1]
    rss = float(r @ r)
    res_mm = r.reshape(-1, 3) * sigma[:, None]

    def score(e: Effect) -> Candidate | None:
        Cw, b = _weighted_columns(e, ctx, Jq, sigma)
        norms = np.linalg.norm(Cw, axis=0)
        if not np.all(norms > 0):
            return None
        Cp = Cw / norms - Q @ (Q.T @ (Cw / norms))
        U, sv, _ = np.linalg.svd(Cp, full_matrices=False)
        k = int((sv > ABSORBED).sum())  # the directions the current model cannot absorb
        if k == 0:
            return None
        fit = U[:, :k] @ (U[:, :k].T @ r)
        drss = float(fit @ fit)
        k_test = k + int(getattr(e, "search_dof", 0))
        dof2 = m - p - k_test
        if dof2 <= 0:
            return None
        F = (drss / k_test) / max((rss - drss) / dof2, 1e-300)
        log_p = f_logsf(F, k_test, dof2)
        disp = fit.reshape(-1, 3) * sigma[:, None]  # mm
        direction = disp / np.maximum(np.linalg.norm(disp, axis=1, keepdims=True), 1e-300)
        return Candidate(
            effect=e, label=e.label(model), p_value=float(np.exp(log_p)), log_p=log_p, F=float(F),
            explained=drss / rss, beyond_chance=drss / rss - k_test / (m - p),
            bic=m * np.log(max(rss - drss, 1e-300) / m) + k_test * np.log(m), dof=k_test, residual_dof=dof2,
            effect_rms_mm=float(np.sqrt(np.mean((disp**2).sum(1)))),
            regressor=b.regressor, regressor_label=b.regressor_label,
            projected_residual_mm=(res_mm * direction).sum(1), fitted_mm=(disp * direction).sum(1))

    def score_apart(e: Effect) -> tuple[Candidate | None, Basis | None]:
        """score(e) and e's basis if this process made it (a worker's come back to the context: later screens at
        this reference geometry, the plays', the sub-search's, the revisits', reuse them)."""
        fresh = ctx.made(e) is None
        return score(e), ctx.basis(e) if fresh else None

    # a worker's candidates come back holding the pool's own effects (the search tells them apart by identity)
    scored = pmap(score_apart, pool, workers if len(pool) >= SCREEN_APART else 1, shared=pool)
    for e, (_, b) in zip(pool, scored):
        if b is not None and ctx.made(e) is None:
            ctx.keep(e, b)
    return sorted([c for c, _ in scored if c is not None], key=lambda c: c.bic)


def field_share(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray) -> float:
    """The share of the weighted residual a smooth joint-space field (ridge) explains beyond chance (less the share
    it fits of pure noise, trace(H^2) / dof of its hat matrix H): a named cause that explains far less than the
    field beyond chance is only picking up part of a broader structure. Without the correction a field of a few
    hundred effective parameters "explains" 75 % of a residual that is mostly noise, and a real cause half the
    noise's size is thrown away."""
    sigma = _robust_sigma(cal, sigma)
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ctx = Context.at(cal.model, x_ref, meas, cal.R0)
    field = ResidualField((), length_scale=1.0, prior_std=max(PRIOR_STD_MM, 2.0 * cal.metrics()["holdout_rms_mm"]))
    Cw, _ = _weighted_columns(field, ctx, chain.joint_jacobian(), sigma)
    Cp = Cw - Q @ (Q.T @ Cw)
    G = Cp.T @ Cp
    fit = Cp @ np.linalg.solve(G + np.eye(len(G)) / field.prior_std**2, Cp.T @ r)
    s2 = np.clip(np.linalg.eigvalsh(G), 0.0, None)  # Cp's squared singular values (no SVD of the tall Cp)
    chance = float(np.sum((s2 / (s2 + 1.0 / field.prior_std**2)) ** 2))  # E|H e|^2 / sigma^2 = trace(H^2)
    return float(fit @ fit) / float(r @ r) - chance / (len(r) - Q.shape[1])


def log_p_beyond(big: Candidate, small: Candidate) -> float:
    """Log p-value of the F-test that `big` explains more of the same residual than `small` with its extra degrees
    of freedom (exact where small's columns lie in big's span: a last joint's zero in the target's offset on the
    flange); 0 when it has none or explains no more."""
    extra = big.dof - small.dof
    gain = big.explained - small.explained
    if extra <= 0 or gain <= 0:
        return 0.0
    return f_logsf((gain / extra) / max((1.0 - big.explained) / big.residual_dof, 1e-300), extra, big.residual_dof)


def _thresholds(pool: list[Effect], alpha: float) -> dict[int, float]:
    """Log Bonferroni threshold per candidate: ALPHA split between the named causes and the time steps."""
    steps = [e for e in pool if isinstance(e, SessionStep)]
    named = len(pool) - len(steps)
    a_named = alpha * (1.0 - TIME_SHARE) if steps else alpha
    return {id(e): np.log((alpha * TIME_SHARE / len(steps)) if isinstance(e, SessionStep) else a_named / max(named, 1))
            for e in pool}


def linear_holdout(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray, folds: int,
                   refold: Callable[..., Callable[[np.ndarray], Effect] | None] = lambda *a: None,
                   workers: int = 1) -> Callable[[Effect], tuple[float, float]]:
    """At cal's linearisation, for a candidate effect: holdout_gain's (p-value, mean drop in mm^2) of the k-fold
    held-out distances (the folds identify uses) when it is added, the current model's columns free in every fold
    (exact least squares on the weighted system), over cal's inliers. It tracks the full refit's figures (the drop
    within about 20 % on Motoman, Hilti and Agile Justin), so a candidate it puts far from confirmation is not worth
    a full fit with folds (Hilti's steps in time order cost 5-30 s each). `refold(cal, meas, e, ctx)` gives, for a
    candidate whose form is read off this data (a play's switch), its form on a fold's training poses."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ctx = Context.at(model, x_ref, meas, cal.R0)
    Jq = chain.joint_jacobian()
    fold = np.repeat(pose_folds(meas, folds), 3)
    keep = cal.inliers()
    units = None if cal.pose_index is None else cal.pose_index[keep]

    def held_out(A: np.ndarray, fold_columns: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
        if fold_columns is None:
            pred = fold_predictions(A, r, fold, folds)
        else:  # the candidate's columns differ per fold (found again on its training poses: apart, `workers`)
            def one(k: int) -> np.ndarray:
                te = fold == k
                only = np.where(te, 0, 1)  # fold 0: this fold's rows, the only ones predicted
                return fold_predictions(np.hstack([A, fold_columns(~te[::3])]), r, only, 1)[te]

            pred = np.empty_like(r)
            for k, part in enumerate(pmap(one, range(folds), workers)):
                pred[fold == k] = part
        return (((r - pred).reshape(-1, 3) * sigma[:, None]) ** 2).sum(1)

    without = held_out(Q)

    def gain(e: Effect) -> tuple[float, float]:
        again = refold(cal, meas, e, ctx)
        if again is None:
            with_e = held_out(np.hstack([Q, _weighted_columns(e, ctx, Jq, sigma)[0]]))
        else:
            with_e = held_out(Q, lambda train: _weighted_columns(again(train), ctx, Jq, sigma)[0])
        return paired_gain((without - with_e)[keep], units)

    return gain
