"""Agile Justin as one tree: what each elastic form of the product is worth on poses it never saw (issue 9).

The product's own effects, fitted as the `auto` job would fit them once chosen (geometry chosen on held-out
folds, then the causes jointly): joint compliance on the converter's guessed masses, + the lateral (bearing)
compliance of every joint, + the mass data identified under both (diagnosis.masses._identify_masses), + the motion
the hands share at a pose weighted as noise of that pose (diagnosis.residual._with_pose_noise, kept on held-out folds).
Split s is `split_70_30(poses, seed=s)` over recorded poses (both hands of a pose on the same side): s = 0 is
benchmarks/real_cells.py's split, 1000 + k the k-th split of benchmarks/real_diagnosis.py. --blind adds the
blind diagnosis (`diagnose` on the calibration part, 5-10 CPU minutes per split) as the last row. --probes asks
what the fixed forms leave: would the loads taken at the deflected pose (the published model's implicit torque
equilibrium) or a joint offset that follows the direction each joint last moved in (friction, hysteresis) help?
Each is fitted linearly beside every parameter of the model, on the calibration part, and judged held out; and
would weighting the motion both hands share at a pose (shared_motion) as noise of that pose (GLS) help?

    .venv/bin/python -m benchmarks.justin_elastic [--splits 0 1000 1001] [--blind] [--probes]
    .venv/bin/python -m benchmarks.justin_elastic --kfold 10   # each pose held out once, 90 % calibrate
    .venv/bin/python -m benchmarks.justin_elastic --insample   # fitted and judged on all 500 (the paper's protocol)
    .venv/bin/python -m benchmarks.justin_elastic --shared     # what both hands share at a pose, held out
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from benchmarks.accuracy import split_70_30  # noqa: E402
from benchmarks.real_cells import load  # noqa: E402
from calib_core import kinematics as K  # noqa: E402
from calib_core import shared_motion as SM  # noqa: E402
from calib_core.datasets import SHARED_DATASETS  # noqa: E402
from calib_core.diagnosis import ALPHA, diagnose  # noqa: E402
from calib_core.diagnosis.fitter import _Fitter  # noqa: E402
from calib_core.diagnosis.masses import _identify_masses  # noqa: E402
from calib_core.diagnosis.residual import _shared_motion, _with_pose_noise  # noqa: E402
from calib_core.effects import JointCompliance, LateralJointCompliance, candidates  # noqa: E402
from calib_core.identify import evaluate  # noqa: E402
from calib_core.select import select_geometry  # noqa: E402


def _mean_mm(r: np.ndarray) -> float:
    return float(np.linalg.norm(r.reshape(-1, 3), axis=1).mean())


def probes(cal, meas, train: np.ndarray) -> list[tuple[str, float, float]]:
    """(probe, held-out mean of the fixed forms refitted linearly, the same with the probe's columns) in mm: the
    model's columns are finite differences of its prediction in every parameter; rows `train` fit, the rest judge."""
    rob = cal.robot
    q = meas.joints

    def predict(r, equilibrium: int = 0) -> np.ndarray:
        dq, dp = r.effect_offsets(q, meas)
        for _ in range(equilibrium):  # the loads taken at the deflected pose
            dq, dp = r.effect_offsets(q + dq, meas)
        return K.forward(r.model, r.x, q + dq, r.R0, meas.labels) + dp

    p0 = predict(rob)
    cols = []
    for i in range(len(rob.x)):
        x = rob.x.copy()
        x[i] += 1e-6
        cols.append((predict(dataclasses.replace(rob, x=x, x_basis=rob.x_basis)) - p0) / 1e-6)
    for k, v in enumerate(rob.effect_values):
        for i in range(len(v)):
            vals = [w.copy() for w in rob.effect_values]
            h = max(abs(v[i]), 1e-12) * 1e-4
            vals[k][i] += h
            cols.append((predict(dataclasses.replace(rob, effect_values=tuple(vals))) - p0) / h)
    J = np.stack([c.ravel() for c in cols if np.abs(c).max() > 1e-12], axis=1)
    J /= np.linalg.norm(J, axis=0)
    rows = np.repeat(train, 3)
    y = (meas.points - p0).ravel()
    prev = np.vstack([q[:2], q[:-2]])  # the pose recorded before (two rows, one per hand, per pose)
    moving = [j for j in range(q.shape[1]) if np.ptp(q[:, j]) > 1e-9]
    Jq = cal.robot.chain(q, meas)[0].joint_jacobian()
    extra = {"loads at the deflected pose (3 fixed-point steps)": (predict(rob, 3) - p0).reshape(-1, 1),
             "a joint offset by the direction it last moved": np.stack(
                 [(Jq[:, :, j] * np.sign(q[:, j] - prev[:, j])[:, None]).ravel() for j in moving], axis=1)}
    out = []
    for label, X in extra.items():
        held = []
        for A in (J, np.hstack([J, X])):
            c = np.linalg.lstsq(A[rows], y[rows], rcond=1e-10)[0]
            held.append(_mean_mm((y - A @ c).reshape(-1, 3)[~train]))
        out.append((label, *held))
    weigh = _shared_as_noise(cal, meas, train)
    fits = [np.linalg.lstsq(w(J)[rows], w(y[:, None])[rows, 0], rcond=1e-10)[0] for w in (lambda A: A, weigh)]
    out.append(("the hands' shared motion weighted as noise of each pose (GLS)",
                *[_mean_mm((y - J @ c).reshape(-1, 3)[~train]) for c in fits]))
    return out


def _shared_as_noise(cal, meas, train: np.ndarray):
    """The whitening of the rows of every pose when the motion the hands share (shared_motion on the calibration
    rows' residual: its direction u at each hand, its RMS tau per pose) is noise of that pose beside independent
    noise s^2 per coordinate (the rest of the residual): Sigma = s^2 I + tau^2 u u' per pose, W = Sigma^-1/2 s.
    Returns a function applying W to (3N, k) rows."""
    chain, dp = cal.robot.chain(meas.joints, meas)
    res = meas.points - chain.p - dp
    rows = np.flatnonzero(train)
    sub = meas.subset(rows)
    found = SM.shared_motion(cal.robot.chain(sub.joints, sub)[0], sub, res[rows], sub.noise_sigma_mm(),
                             np.zeros((3 * len(rows), 0)))
    top = next((f for f in found if f.p_value < 0.01), found[0])  # the largest significant
    u = {what: v for what, _, v in SM.motions(chain)}[top.motion]
    s2 = float(np.mean(np.sum(res[rows] ** 2, axis=1))) * (1 - top.share) / 3
    pairs = np.array([g[:2] for g in SM.pose_groups(meas, cal.model)])
    idx = np.concatenate([3 * pairs[:, :1] + np.arange(3), 3 * pairs[:, 1:] + np.arange(3)], axis=1)  # (P, 6)
    U = u.reshape(-1)[idx]
    a2 = (U**2).sum(1)
    c = 1 - 1 / np.sqrt(1 + top.size**2 * a2 / s2)

    def whiten(A: np.ndarray) -> np.ndarray:
        out = A.copy()
        proj = np.einsum("pi,pik->pk", U, A[idx]) / a2[:, None]
        out[idx] = A[idx] - c[:, None, None] * U[:, :, None] * proj[:, None, :]
        return out
    return whiten


def fixed_forms(model, train, held) -> list[tuple[str, dict, float, object]]:
    """The geometry chosen on held-out folds, then the product's elastic forms in turn, fitted on `train` and
    evaluated on `held`: (label, evaluation, seconds, calibration) per row."""
    t0 = time.time()
    sel = select_geometry(model, train, loss=None, folds=5)
    out = [("geometric (chosen on held-out folds)", evaluate(sel.calibration, held), time.time() - t0, sel.calibration)]
    fit = _Fitter(model, train, None, 5, sel.free, sel.prior_scale)
    named, _ = candidates(model, train)
    joint = next(e for e in named if type(e) is JointCompliance and len(e.joints) > 1)
    lateral = next(e for e in named if isinstance(e, LateralJointCompliance))
    for label, chosen in (("+ joint compliance of every joint (guessed masses)", [joint]),
                          ("+ lateral compliance of every joint (guessed masses)", [joint, lateral])):
        t0 = time.time()
        cur = fit(chosen, sel.calibration.x)
        out.append((label, evaluate(cur, held), time.time() - t0, cur))
    t0 = time.time()
    notes: list[str] = []
    masses = _identify_masses(cur, list(chosen), [], model, train, fit, notes)
    out.append(("+ mass data identified under both" + ("" if notes else " (not kept: held-out folds object)"),
                evaluate(masses, held), time.time() - t0, masses))
    t0 = time.time()
    found = _shared_motion(masses, train, masses.sigma_mm, masses.x_basis) or []
    weighted = _with_pose_noise(masses, fit, train, [f for f in found if f.p_value < ALPHA])
    last = masses if weighted is None else weighted[0]
    if weighted is None:
        print("the hands' shared motion as noise of each pose: not kept (held-out folds object)", flush=True)
    out.append(("+ the hands' shared motion weighted as noise of each pose (GLS, where held-out folds confirm it)",
                evaluate(last, held), time.time() - t0, last))
    return out


def kfold(k: int) -> None:
    """Each recorded pose held out once, by k folds of the 500 (so (k-1)/k of them calibrate): the fixed forms'
    held-out mean and RMS over all poses, per row, beside the 70/30 splits' figures."""
    _, model, meas, groups = load("dlr_agile_justin", SHARED_DATASETS)
    ids = np.random.default_rng(0).permutation(np.unique(groups))
    sums: dict[str, np.ndarray] = {}  # per row: held-out points, sum of distances, sum of squares
    for f, test in enumerate(np.array_split(ids, k)):
        rows = np.isin(groups, test)
        held = meas.subset(np.flatnonzero(rows))
        for label, ev, sec, _ in fixed_forms(model, meas.subset(np.flatnonzero(~rows)), held):
            n = held.n_poses
            sums[label] = sums.get(label, 0) + np.array([n, n * ev["mean_mm"], n * ev["rms_mm"] ** 2])
            print(f"fold {f + 1}/{k}: {label}: held-out mean {ev['mean_mm']:.2f} mm ({sec:.0f} s)", flush=True)
    print(f"\n| model ({k}-fold, each pose held out once) | held-out mean (mm) | RMS (mm) |\n|---|---|---|")
    for label, (n, total, squares) in sums.items():
        print(f"| {label} | {total / n:.2f} | {np.sqrt(squares / n):.2f} |")


def insample() -> None:
    """The paper's protocol: the fixed forms fitted on all recorded poses and judged on the same poses."""
    _, model, meas, _ = load("dlr_agile_justin", SHARED_DATASETS)
    print("| model (fitted on all 500 poses, judged on them) | mean (mm) | RMS (mm) | max (mm) |")
    print("|---|---|---|---|")
    for label, ev, _, _ in fixed_forms(model, meas, meas):
        print(f"| {label} | {ev['mean_mm']:.2f} | {ev['rms_mm']:.2f} | {ev['max_mm']:.2f} |", flush=True)


def shared(splits: list[int]) -> None:
    """What the two hands share at a pose, on poses the fixed forms never saw: shared_motion on each split's
    held-out residual of the last fixed form (no fit couples held-out rows, so the hat-matrix term is zero)."""
    _, model, meas, groups = load("dlr_agile_justin", SHARED_DATASETS)
    ids = np.unique(groups)
    print("| split | held-out mean (mm) | motion shared by the hands (largest significant) | its RMS per pose | "
          "share of a hand's mean square | p (Bonferroni) | all poses' common share |\n|---|---|---|---|---|---|---|")
    for s in splits:
        cal, test = split_70_30(len(ids), seed=s)
        train = meas.subset(np.flatnonzero(np.isin(groups, ids[cal])))
        held = meas.subset(np.flatnonzero(np.isin(groups, ids[test])))
        label, ev, _, last = fixed_forms(model, train, held)[-1]
        chain, dp = last.robot.chain(held.joints, held)
        res = held.points - chain.p - dp
        found = SM.shared_motion(chain, held, res, held.noise_sigma_mm(), np.zeros((res.size, 0)))
        top = next((f for f in found if f.p_value < 0.01), found[0])
        size = f"{1e3 * top.size:.2f} mrad" if top.unit == "rad" else f"{top.size:.2f} mm"
        right, left = res[held.target == 0], res[held.target == 1]
        common = float(np.sum(right * left) / (0.5 * np.sum(right**2 + left**2)))
        print(f"| {s} | {ev['mean_mm']:.2f} | {top.motion} | {size} | {100 * top.share:.0f} % | {top.p_value:.0e} | "
              f"{100 * common:.0f} % |", flush=True)


def run(split: int, blind: bool = False, probe: bool = False) -> list[tuple[str, dict, float]]:
    _, model, meas, groups = load("dlr_agile_justin", SHARED_DATASETS)
    ids = np.unique(groups)
    cal, test = split_70_30(len(ids), seed=split)
    train = meas.subset(np.flatnonzero(np.isin(groups, ids[cal])))
    held = meas.subset(np.flatnonzero(np.isin(groups, ids[test])))
    rows = fixed_forms(model, train, held)
    out, masses = [row[:3] for row in rows], rows[-1][3]
    if probe:
        rows = np.isin(groups, ids[cal])
        print(f"split {split}: + mass data identified under both, on its own calibration poses: mean "
              f"{evaluate(masses, train)['mean_mm']:.2f} mm", flush=True)
        for label, before, after in probes(masses, meas, rows):
            print(f"split {split}: probe {label}: held-out mean {before:.3f} -> {after:.3f} mm (the fixed forms "
                  f"refitted linearly, then with the probe beside them)", flush=True)
    if blind:
        t0 = time.time()
        d = diagnose(model, train)
        named = "; ".join(f"{f['kind']} {','.join(f['joints'])}" for f in d.findings)
        print(f"split {split}: blind diagnosis named: {named}", flush=True)
        for f in d.findings:
            if f["kind"] == "unexplained":
                print(f"split {split}: unexplained: {f['evidence']}", flush=True)
        out.append(("blind diagnosis (`diagnose`, the causes it names)", evaluate(d.calibration, held), time.time() - t0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", type=int, nargs="+", default=[0, 1000, 1001])
    ap.add_argument("--blind", action="store_true", help="also run the blind diagnosis on each split")
    ap.add_argument("--probes", action="store_true", help="also ask what the fixed forms leave (see the docstring)")
    ap.add_argument("--kfold", type=int, metavar="K",
                    help="instead: the fixed forms over K folds, each pose held out once")
    ap.add_argument("--insample", action="store_true",
                    help="instead: the fixed forms fitted and judged on all poses (the paper's protocol)")
    ap.add_argument("--shared", action="store_true",
                    help="instead: what the two hands share at a pose on each split's held-out poses")
    args = ap.parse_args()
    if args.shared:
        return shared(args.splits)
    if args.insample:
        return insample()
    if args.kfold:
        return kfold(args.kfold)
    rows = {}
    for s in args.splits:
        for label, ev, sec in run(s, args.blind, args.probes):
            rows.setdefault(label, []).append((s, ev, sec))
            print(f"split {s}: {label}: held-out mean {ev['mean_mm']:.2f} / RMS {ev['rms_mm']:.2f} / max "
                  f"{ev['max_mm']:.2f} mm ({sec:.0f} s)", flush=True)
    print("\n| model | " + " | ".join(f"split {s} mean / RMS (mm)" for s in args.splits) + " | mean of splits |")
    print("|---|" + "---|" * (len(args.splits) + 1))
    for label, r in rows.items():
        cells = " | ".join(f"{ev['mean_mm']:.2f} / {ev['rms_mm']:.2f}" for _, ev, _ in r)
        print(f"| {label} | {cells} | {np.mean([ev['mean_mm'] for _, ev, _ in r]):.2f} |")


if __name__ == "__main__":
    main()
