"""Our extended model against the neural-network baseline (Wang et al.: geometric calibration, then a
back-propagation network from joint angles to the remaining position error), same data, same split.

Baseline: one hidden layer of tanh units, inputs = joint values scaled to [-1, 1] by the limits,
outputs = the geometric model's residual (x, y, z), weight decay and the hidden size chosen by 5-fold CV
on the training poses, trained with L-BFGS. Ours: `diagnose` (named causes + smooth field).
Run: .venv/bin/python -m benchmarks.bench_nn_baseline
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.optimize import minimize  # noqa: E402

from benchmarks.accuracy import split_70_30  # noqa: E402
from calib_core import datasets  # noqa: E402
from calib_core.diagnose import diagnose  # noqa: E402
from calib_core.identify import evaluate, fold_ids  # noqa: E402
from calib_core.io import parse_measurements  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.robots import spray7  # noqa: E402
from calib_core.twin import Twin, draw_hidden_effect  # noqa: E402


class MLP:
    """y = W2 tanh(W1 z + b1) + b2, fitted by L-BFGS on mean squared error + decay |W|^2."""

    def __init__(self, hidden: int, decay: float, seed: int = 0):
        self.h, self.decay, self.seed = hidden, decay, seed

    def _unpack(self, w, d):
        h = self.h
        W1 = w[: d * h].reshape(d, h)
        b1 = w[d * h: d * h + h]
        W2 = w[d * h + h: d * h + h + 3 * h].reshape(h, 3)
        return W1, b1, W2, w[-3:]

    def fit(self, z, y):
        d = z.shape[1]
        self.scale = y.std(0) + 1e-12
        t = y / self.scale

        def loss(w):
            W1, b1, W2, b2 = self._unpack(w, d)
            a = np.tanh(z @ W1 + b1)
            e = a @ W2 + b2 - t
            n = len(z)
            g_out = 2 * e / n
            gW2 = a.T @ g_out + 2 * self.decay * W2
            gb2 = g_out.sum(0)
            g_a = g_out @ W2.T * (1 - a**2)
            gW1 = z.T @ g_a + 2 * self.decay * W1
            gb1 = g_a.sum(0)
            f = (e**2).sum() / n + self.decay * ((W1**2).sum() + (W2**2).sum())
            return f, np.concatenate([gW1.ravel(), gb1, gW2.ravel(), gb2])

        w0 = np.random.default_rng(self.seed).normal(0, 0.3, d * self.h + self.h + 3 * self.h + 3)
        self.w = minimize(loss, w0, jac=True, method="L-BFGS-B", options={"maxiter": 2000}).x
        self.d = d
        return self

    def predict(self, z):
        W1, b1, W2, b2 = self._unpack(self.w, self.d)
        return (np.tanh(z @ W1 + b1) @ W2 + b2) * self.scale


def _inputs(model, q):
    lo, hi = model.limits[:, 0], model.limits[:, 1]
    return (q - 0.5 * (lo + hi)) / (0.5 * (hi - lo))


def nn_baseline(model, train, test, geo) -> dict:
    """Geometric model + the best MLP (by CV on the training poses) on the residual; error on `test`."""
    z, r = _inputs(model, train.joints), train.points - geo.predict(train.joints, train)
    folds = fold_ids(len(z), 5)
    best = None
    for hidden in (8, 16, 32):
        for decay in (1e-4, 1e-3, 1e-2):
            err = []
            for k in range(5):
                tr, te = folds != k, folds == k
                net = MLP(hidden, decay).fit(z[tr], r[tr])
                err.append(((net.predict(z[te]) - r[te]) ** 2).sum(1))
            score = np.mean(np.concatenate(err))
            if best is None or score < best[0]:
                best = (score, hidden, decay)
    net = MLP(best[1], best[2]).fit(z, r)
    pred = geo.predict(test.joints, test) + net.predict(_inputs(model, test.joints))
    d = np.linalg.norm(test.points - pred, axis=1)
    return {"rms_mm": float(np.sqrt(np.mean(d**2))), "max_mm": float(d.max()), "hidden": best[1], "decay": best[2]}


def cases():
    model = parse_model(spray7())
    for kind in ("joint_compliance", "link_deflection", "unexplained"):
        twin = Twin(model, 11)
        q = twin.sample_joints(150)
        effect, _ = draw_hidden_effect(twin, kind, 6.0, q, np.random.default_rng(11))
        yield f"spray7 twin, {effect.label(model)} at 6x noise (150 / 100)", model, twin.measure(q), twin.measure(n=100)
    if datasets.available():
        for ds in (datasets.motoman_leica(), datasets.iiwa7_payload(None)):
            model = parse_model(ds.model)
            meas = parse_measurements(ds.csv_text, model)
            tr, te = split_70_30(meas.n_poses)
            yield f"{ds.name} (70/30)", model, meas.subset(tr), meas.subset(te)


def main():
    print("| data | geometric RMS / max (mm) | geometric + BP network RMS / max (mm) | ours (diagnosis) RMS / max (mm) |")
    print("|---|---|---|---|")
    for label, model, train, test in cases():
        d = diagnose(model, train)
        g, ours = evaluate(d.geometric, test), evaluate(d.calibration, test)
        nn = nn_baseline(model, train, test, d.geometric)
        print(f"| {label} | {g['rms_mm']:.3f} / {g['max_mm']:.3f} | {nn['rms_mm']:.3f} / {nn['max_mm']:.3f} "
              f"(h={nn['hidden']}, decay={nn['decay']:g}) | {ours['rms_mm']:.3f} / {ours['max_mm']:.3f} |")


if __name__ == "__main__":
    main()
