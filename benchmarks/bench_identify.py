"""Geometric identification of the 7-DoF spray robot: ours vs scipy least_squares with finite differences.

Both solve the same problem (same twin data, same weights, same independent parameters, same start);
the peer gets the pre-alignment and the parameter selection for free and is timed on its solve alone.
Run: .venv/bin/python -m benchmarks.bench_identify
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares as scipy_least_squares

from calib_core import kinematics as K
from calib_core.identifiability import analyse
from calib_core.identify import identify, prealign, tracker_sigma_mm
from calib_core.model import parse_model
from calib_core.robots import spray7
from calib_core.twin import Twin


def _best_time(fn, repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def peer_problem(model, meas):
    """The residual function, start and selection scipy gets (computed outside its timing)."""
    x0, R0 = prealign(model, meas)
    J = K.Chain(model, x0, meas.joints, R0).jacobian().reshape(-1, len(x0))
    idx = np.array(sorted(analyse(J, K.parameter_names(model)).identifiable))
    sigma = tracker_sigma_mm(meas.points)

    def fun(xs):
        x = x0.copy()
        x[idx] = xs
        return ((meas.points - K.forward(model, x, meas.joints, R0)) / sigma[:, None]).ravel()

    return fun, x0[idx]


def run(sizes=(150, 2000), repeats=5) -> list[dict]:
    model = parse_model(spray7())
    rows = []
    for n in sizes:
        twin = Twin(model, seed=2023)
        meas = twin.measure(n=n)
        t_ours, cal = _best_time(lambda: identify(model, meas, folds=0, regularize=False), repeats)
        fun, xs0 = peer_problem(model, meas)
        peers = {}
        for method in ("trf", "lm"):
            peers[method] = _best_time(lambda: scipy_least_squares(fun, xs0, jac="2-point", method=method,
                                                                    x_scale="jac"), max(1, repeats // 2))
        cost_ours = float((cal.solution.residual / tracker_sigma_mm(meas.points)[:, None]).ravel() @
                          (cal.solution.residual / tracker_sigma_mm(meas.points)[:, None]).ravel())
        for method, (t_peer, res) in peers.items():
            rows.append({"poses": n, "peer": f"scipy least_squares {method}, 2-point FD", "ours_ms": 1e3 * t_ours,
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
