"""What is left to learn from the joint values once a model is fitted: a kernel ridge regression (RBF on the
standardised cos and sin of each revolute joint, each prismatic joint's travel, each joint's gravity load from the
model's statics, and the target's index) of a calibration's residual on its calibration poses, its length scale and
ridge chosen by 5-fold cross-validation over those poses alone, applied as a correction on the held-out poses. A
flexible function of the pose, as every physical cause is: what it predicts on new poses, a model could still learn
(issue 34's Agile Justin bar).

Per dataset and split (held-out mean / RMS, mm): the geometric model and the diagnosed one, each alone and with the
kernel correction, and the diagnosed model's mean on its own calibration poses. The geometric row is the control:
the kernel ridge must find there what the diagnosis found (Agile Justin's elasticity), or its failure on the
diagnosed residual would say nothing.

Run:  .venv/bin/python -m benchmarks.left_to_learn [--datasets NAME ...] [--splits 3] [--workers 2] [--root DIR]
Needs ../shared/datasets (or --root / CALIB_SHARED_DATASETS); both datasets' three splits take ~4 minutes.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.real_cells import load, split  # noqa: E402
from calib_core import kinematics as K  # noqa: E402
from calib_core.diagnosis import diagnose  # noqa: E402
from calib_core.effects import loads  # noqa: E402
from calib_core.identify import Calibration, identify  # noqa: E402
from calib_core.io import Measurements  # noqa: E402
from calib_core.model import RobotModel  # noqa: E402

LENGTH_SCALES = (0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0)
"""RBF length scales tried, in standard deviations of each feature on the calibration poses."""
RIDGES = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
"""Ridges tried, relative to the kernel's unit diagonal."""
FOLDS = 5


def raw_features(model: RobotModel, geo: Calibration, meas: Measurements) -> np.ndarray:
    """Per pose: cos and sin of each revolute joint, each prismatic joint's travel (mm), each joint's load (N m or N)
    on `geo`'s geometry (zero columns without mass data)."""
    q = meas.joints
    turns = ~np.asarray(model.prismatic, bool)
    load = loads(K.Chain(model, geo.x, q, geo.R0, meas.labels), meas)
    return np.column_stack([np.cos(q[:, turns]), np.sin(q[:, turns]), q[:, ~turns], load])


def features(raw: np.ndarray, meas: Measurements, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """raw_features standardised, and the target's index 3 std apart (two markers: two nearly separate functions)."""
    target = np.zeros(meas.n_poses) if meas.target is None else meas.target
    return np.c_[(raw - mean) / std, 3.0 * target]


def kernel_ridge(X: np.ndarray, Y: np.ndarray, Xt: np.ndarray, scale: float, ridge: float) -> np.ndarray:
    """Kernel ridge prediction at Xt of Y (N, 3) mm fitted at X, RBF kernel of length `scale`."""
    def k(a, b):
        return np.exp(-0.5 * ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / scale**2)
    return k(Xt, X) @ np.linalg.solve(k(X, X) + ridge * np.eye(len(X)), Y)


def correction(X: np.ndarray, r: np.ndarray, groups: np.ndarray, seed: int) -> tuple[float, float, float]:
    """(length scale, ridge, cross-validated mean distance mm) with the least k-fold mean distance on the
    calibration poses (folds by recorded pose)."""
    ids = np.unique(groups)
    fold = dict(zip(ids, np.random.default_rng(seed).permutation(len(ids)) % FOLDS))
    f = np.array([fold[g] for g in groups])
    best = (np.inf, 0.0, 0.0)
    for scale in LENGTH_SCALES:
        for ridge in RIDGES:
            err = np.empty(len(X))
            for k in range(FOLDS):
                err[f == k] = np.linalg.norm(r[f == k] - kernel_ridge(X[f != k], r[f != k], X[f == k], scale, ridge),
                                             axis=1)
            if err.mean() < best[0]:
                best = (float(err.mean()), scale, ridge)
    return best[1], best[2], best[0]


def run(name: str, root: Path, split_no: int, workers: int) -> dict:
    """One split: the geometric and the diagnosed model, each with and without the kernel correction."""
    warnings.simplefilter("ignore", RuntimeWarning)
    _, model, meas, groups = load(name, root)
    cal_rows, test_rows = split(groups, 1000 + split_no if split_no else 0)
    train, test = meas.subset(cal_rows), meas.subset(test_rows)
    geo = identify(model, train, folds=0)
    raw, raw_test = raw_features(model, geo, train), raw_features(model, geo, test)
    mean, std = raw.mean(0), raw.std(0)
    std[std < 1e-12] = 1.0
    X, Xt = features(raw, train, mean, std), features(raw_test, test, mean, std)
    out = {"name": name, "split": split_no}
    for label, cal in (("geometric", geo), ("diagnosed", diagnose(model, train, workers=workers).calibration)):
        r = train.points - cal.predict(train.joints, train)
        rt = test.points - cal.predict(test.joints, test)
        scale, ridge, cv = correction(X, r, groups[cal_rows], split_no)
        corrected = rt - kernel_ridge(X, r, Xt, scale, ridge)
        d0, d1 = np.linalg.norm(rt, axis=1), np.linalg.norm(corrected, axis=1)
        out[label] = {"held_out_mean_mm": float(d0.mean()), "held_out_rms_mm": float(np.sqrt(np.mean(d0**2))),
                      "corrected_mean_mm": float(d1.mean()), "corrected_rms_mm": float(np.sqrt(np.mean(d1**2))),
                      "calibration_mean_mm": float(np.linalg.norm(r, axis=1).mean()), "cv_mean_mm": cv,
                      "length_scale": scale, "ridge": ridge}
    return out


def table(results: list[dict]) -> str:
    lines = ["| dataset | split | model | on its calibration poses, mean | held out mean / RMS | with the kernel "
             "correction, mean / RMS | gain of the correction, mean | scale, ridge |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        for label in ("geometric", "diagnosed"):
            m = r[label]
            lines.append(f"| {r['name']} | {r['split']} | {label} | {m['calibration_mean_mm']:.3f} | "
                         f"{m['held_out_mean_mm']:.3f} / {m['held_out_rms_mm']:.3f} | {m['corrected_mean_mm']:.3f} / "
                         f"{m['corrected_rms_mm']:.3f} | {m['held_out_mean_mm'] - m['corrected_mean_mm']:+.3f} | "
                         f"{m['length_scale']:g}, {m['ridge']:g} |")
    for name in dict.fromkeys(r["name"] for r in results):
        rows = [r for r in results if r["name"] == name]
        for label in ("geometric", "diagnosed"):
            a = np.mean([[r[label]["calibration_mean_mm"], r[label]["held_out_mean_mm"],
                          r[label]["corrected_mean_mm"]] for r in rows], axis=0)
            lines.append(f"| {name} | mean of {len(rows)} | {label} | {a[0]:.3f} | {a[1]:.3f} | {a[2]:.3f} | "
                         f"{a[1] - a[2]:+.3f} | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.left_to_learn", description=__doc__.split("\n\n")[0])
    p.add_argument("--datasets", nargs="+", default=["dlr_agile_justin", "motoman_leica"])
    p.add_argument("--splits", type=int, default=3, help="splits 0..S-1 (0: seed 0; s: seed 1000 + s)")
    p.add_argument("--workers", type=int, default=2, help="the diagnosis's processes")
    p.add_argument("--root", default=os.environ.get("CALIB_SHARED_DATASETS", "../shared/datasets"))
    args = p.parse_args(argv)
    results = [run(name, Path(args.root), s, args.workers) for name in args.datasets for s in range(args.splits)]
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
