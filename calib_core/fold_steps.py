"""k-fold refits as Gauss-Newton steps from the full-data optimum, on one Jacobian shared by the folds.

At the full-data solution x* the gradient of the whole cost vanishes, so a fold's optimum (its poses left out) lies
one small step away: dx_k = (A - A_k + L)^-1 (g - g_k - L (x* - prior)), with A, g the weighted normal equations of
all poses and A_k, g_k the held-out fold's share (a downdate). Every fold then costs one p x p solve instead of an
LM run of its own with a Jacobian per iteration; the error is second order in dx_k (a few poses less move the
optimum little). With a robust loss the fold's weights are iterated on its linearised residual (IRLS at a fixed
Jacobian), as its own LM run re-weights its training poses."""
from __future__ import annotations

import numpy as np

from .solve import _robust_weights, _scaled, _standardised

IRLS_STEPS = 20
"""At most this many re-weightings of a fold's poses under a robust loss (they settle in 3-6)."""


def fold_steps(r: np.ndarray, J: np.ndarray, sigma: np.ndarray, assign: np.ndarray, folds: int, x: np.ndarray, *,
               loss: str | None = None, prior: np.ndarray | None = None,
               prior_std: np.ndarray | None = None) -> list[np.ndarray]:
    """Each fold's parameters: x (P,) plus its Gauss-Newton step on the training poses (assign != k).

    r (N, 3) mm measured - predicted and J (N, 3, P) d predicted / dx at x (a stationary point of the full-data
    cost); sigma (N,) mm per pose; prior and prior_std (P,) the Tikhonov pull lm_steps takes."""
    P = len(x)
    lam = np.zeros(P) if prior_std is None else 1.0 / np.asarray(prior_std, float) ** 2
    pull = lam * (x - (x if prior is None else prior))
    L = np.diag(lam)
    Jw, rw = J / sigma[:, None, None], r / sigma[:, None]
    if loss is None:
        A = Jw.reshape(-1, P).T @ Jw.reshape(-1, P)
        g = Jw.reshape(-1, P).T @ rw.ravel()
    out = []
    for k in range(folds):
        tr = assign != k
        if loss is None:
            Jk = Jw[~tr].reshape(-1, P)
            out.append(x + _solve(A - Jk.T @ Jk + L, g - Jk.T @ rw[~tr].ravel() - pull))
            continue
        Jt, rt = Jw[tr], rw[tr]
        w, step = _robust_weights(_standardised(rt), loss), np.zeros(P)
        Js = Jt.reshape(-1, P) * np.sqrt(np.repeat(w, 3))[:, None]
        A_w = Js.T @ Js
        for _ in range(IRLS_STEPS):
            step = _solve(A_w + L, np.einsum("nkp,nk->p", Jt, rt * w[:, None]) - pull)
            w_new = _robust_weights(_standardised(rt - Jt @ step), loss)
            if np.allclose(w_new, w, atol=1e-6):
                break
            changed = np.flatnonzero(w_new != w)
            # only the poses whose weight changed: Huber's inliers keep weight 1 (Hilti's folds formed the whole
            # weighted normal matrix again per re-weighting: 15 s of its diagnosis)
            Jc = Jt[changed].reshape(-1, P)
            A_w += Jc.T @ (Jc * np.repeat(w_new[changed] - w[changed], 3)[:, None])
            w = w_new
        out.append(x + step)
    return out


def _solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """H^-1 g in Jacobi-scaled variables (a least-squares solution where H is singular)."""
    Hs, S = _scaled(H)
    try:
        return S * np.linalg.solve(Hs, S * g)
    except np.linalg.LinAlgError:
        return S * np.linalg.lstsq(Hs, S * g, rcond=None)[0]
