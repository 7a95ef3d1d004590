"""Geometric identification of the 7-DoF spray robot: ours vs scipy least_squares with finite differences.

All solve the same problem (same twin data, same weights, same independent parameters, same start);
the peers get the pre-alignment and the parameter selection for free and are timed on their solve alone.
Two peers: scipy FD on *our* vectorised forward kinematics (the analytic Jacobian's gain alone), and
scipy FD on a textbook per-pose 4x4 forward kinematics (what a residual for scipy usually looks like).
BLAS runs single-threaded for everyone, as in the service's worker processes.
Run: .venv/bin/python -m benchmarks.bench_identify
"""
from __future__ import annotations

import math
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


import numpy as np
from scipy.optimize import least_squares as scipy_least_squares

from benchmarks import best_time  # noqa: E402
from calib_core import kinematics as K
from calib_core.identifiability import analyse
from calib_core.identify import identify, prealign
from calib_core.instruments import INSTRUMENTS

tracker_sigma_mm = INSTRUMENTS["laser_tracker"].sigma_mm
from calib_core.model import parse_model
from calib_core.robots import spray7
from calib_core.twin import Twin


def _homogeneous(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def per_pose_forward(model, x, q, R0):
    """Textbook forward kinematics: one 4x4 product per joint and pose, in Python loops."""
    n = model.n_joints
    g = x[: K.G * n].reshape(n, K.G)[:, :5]  # a plain MD-H chain: gamma and b stay 0
    base = _homogeneous(K.base_rotation(x[K.G * n: K.G * n + 6], R0), x[K.G * n: K.G * n + 3])
    tool = np.r_[x[K.G * n + 6:], 1.0]
    out = np.empty((len(q), 3))
    for k, qk in enumerate(q):
        T = base
        for j in range(n):
            a, alpha, d, theta, beta = g[j]
            th, dd = (theta, d + qk[j]) if model.prismatic[j] else (theta + qk[j], d)
            ca, sa, ct, st, cb, sb = (math.cos(alpha), math.sin(alpha), math.cos(th), math.sin(th),
                                      math.cos(beta), math.sin(beta))
            A = np.array([[ct, -st, 0, a], [st * ca, ct * ca, -sa, -sa * dd], [st * sa, ct * sa, ca, ca * dd],
                          [0, 0, 0, 1.0]])  # Craig: Rx(alpha) Tx(a) Rz(theta) Tz(d)
            Ry = np.array([[cb, 0, sb, 0], [0, 1.0, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
            T = T @ A @ Ry
        out[k] = (T @ tool)[:3]
    return out


def peer_problem(model, meas, forward=K.forward):
    """The residual function, start and selection scipy gets (computed outside its timing)."""
    x0, R0 = prealign(model, meas)
    J = K.Chain(model, x0, meas.joints, R0).jacobian().reshape(-1, len(x0))
    idx = np.array(sorted(analyse(J, K.parameter_names(model)).identifiable))
    sigma = tracker_sigma_mm(meas.points)

    def fun(xs):
        x = x0.copy()
        x[idx] = xs
        return ((meas.points - forward(model, x, meas.joints, R0)) / sigma[:, None]).ravel()

    return fun, x0[idx]


def run(sizes=(150, 2000), repeats=5) -> list[dict]:
    model = parse_model(spray7())
    rows = []
    for n in sizes:
        twin = Twin(model, seed=2023)
        meas = twin.measure(n=n)
        t_ours, cal = best_time(lambda: identify(model, meas, folds=0, regularize=False), repeats)
        fun, xs0 = peer_problem(model, meas)
        peers = {}
        for method in ("trf", "lm"):
            peers[f"{method}, 2-point FD, our vectorised FK"] = best_time(
                lambda: scipy_least_squares(fun, xs0, jac="2-point", method=method, x_scale="jac"), max(1, repeats // 2))
        slow, xs0 = peer_problem(model, meas, per_pose_forward)
        assert np.allclose(slow(xs0), fun(xs0), atol=1e-6)
        peers["lm, 2-point FD, per-pose 4x4 FK"] = best_time(
            lambda: scipy_least_squares(slow, xs0, jac="2-point", method="lm", x_scale="jac"), 1)
        cost_ours = float((cal.solution.residual / tracker_sigma_mm(meas.points)[:, None]).ravel() @
                          (cal.solution.residual / tracker_sigma_mm(meas.points)[:, None]).ravel())
        for method, (t_peer, res) in peers.items():
            rows.append({"poses": n, "peer": f"scipy least_squares {method}", "ours_ms": 1e3 * t_ours,
                         "peer_ms": 1e3 * t_peer, "ratio": t_peer / t_ours, "peer_nfev": res.nfev,
                         "ours_iter": cal.solution.iterations, "cost_ours": cost_ours, "cost_peer": 2 * res.cost})
    return rows


def main():
    rows = run()
    print("| poses | peer | ours (ms) | peer (ms) | speed-up | peer nfev | our LM iterations | cost ours / peer |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['poses']} | {r['peer']} | {r['ours_ms']:.1f} | {r['peer_ms']:.0f} | {r['ratio']:.0f}x | "
              f"{r['peer_nfev']} | {r['ours_iter']} | {r['cost_ours']:.1f} / {r['cost_peer']:.1f} |")


if __name__ == "__main__":
    main()
