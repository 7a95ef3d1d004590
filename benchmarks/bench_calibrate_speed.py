"""Speed of a 150-pose `geometric` calibration (the service's main job): `calibrate(model, meas, 'geometric')`, i.e.
the cross-validated model selection (registration / joint offsets / full geometry x 3 prior strengths, 5-fold
held-out RMS each) plus the answer dict, on one core (BLAS single-threaded, as in the service's job processes).

Peer: the same selection written the usual way with scipy: `scipy.optimize.least_squares` (TRF, 2-point finite
differences, x_scale='jac') on the same weighted residual and prior rows, every candidate and every fold fitted
from nominal; it gets the pre-alignment and the identifiable parameter sets for free (outside its timing). It
skips our model-error reweighting (one fit per candidate less), so it does a little less work than we do.
Prints a markdown table (for docs/RESULTS.md): median of `--runs` calls per data set, and the peer on the first.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.bench_calibrate_speed [--seeds 10] [--runs 10] [--no-peer]

`--same-as DIR` instead checks that a speed-up changed no choice: the selection on 23 cases (10 spray7 and 3 arm6
twins, Huber, 1 mm noise, 8-40 poses) run by this tree and by the tree at DIR (e.g. an earlier commit,
`git archive <commit> | tar -x -C DIR`), each in a process of its own; prints whether the chosen model, best
candidate, free set and prior agree on every case, and the largest differences of every candidate's held-out
RMS (relative) and of the chosen model's parameters.
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import least_squares as scipy_least_squares  # noqa: E402

from calib_core import kinematics as K  # noqa: E402
from calib_core.identify import _prior_std, _select, assess, fold_ids, prealign  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.pipeline import calibrate  # noqa: E402
from calib_core.robots import arm6, spray7  # noqa: E402
from calib_core.select import _fold_stats, candidates  # noqa: E402
from calib_core.twin import Twin  # noqa: E402


CPU_MS: list[float] = []
"""The CPU time of each twin's median run (process_time): on a busy machine the wall time also counts waiting for a
core."""


def median_ms(fn, runs: int) -> tuple[float, object]:
    fn()  # warm: imports, the structural identifiability cache
    times, cpu, out = [], [], None
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    CPU_MS.append(1e3 * statistics.median(cpu))
    return 1e3 * statistics.median(times), out


def scipy_selection(model, meas, folds: int = 5) -> str:
    """The selection with scipy least_squares and finite differences; returns the chosen label."""
    x0, R0 = prealign(model, meas)
    names = K.parameter_names(model)
    ident = assess(model, meas.joints, K.Chain(model, x0, meas.joints, R0).jacobian().reshape(-1, len(x0)), names)
    sigma = meas.noise_sigma_mm()
    assign = fold_ids(meas.n_poses, folds)
    rows = []
    for label, free, scale in candidates(model):
        idx = _select(names, ident, free)
        std = _prior_std(model, scale)[idx]
        has = np.isfinite(std)

        def fit(mask):
            q, y, s = meas.joints[mask], meas.points[mask], sigma[mask]

            def fun(xs):
                x = x0.copy()
                x[idx] = xs
                r = ((y - K.forward(model, x, q, R0)) / s[:, None]).ravel()
                return np.r_[r, (xs - x0[idx])[has] / std[has]]

            x = x0.copy()
            x[idx] = scipy_least_squares(fun, x0[idx], jac="2-point", method="trf", x_scale="jac").x
            return x

        d = np.empty(meas.n_poses)
        fit(np.ones(meas.n_poses, bool))  # the full-data fit (its answer is not needed for the score)
        for k in range(folds):
            x = fit(assign != k)
            test = assign == k
            d[test] = np.linalg.norm(meas.points[test] - K.forward(model, x, meas.joints[test], R0), axis=1)
        rows.append((label, *_fold_stats(d, assign, folds)))
    best = min(rows, key=lambda r: r[1])
    return next(r[0] for r in rows if r[1] <= best[1] + best[2])


def run(seeds: int = 10, runs: int = 10, peer: bool = True) -> list[dict]:
    out = []
    sets = [("spray7", parse_model(spray7()), s) for s in range(seeds)] + [("arm6", parse_model(arm6()), 0)]
    for robot, model, seed in sets:
        meas = Twin(model, seed).measure(n=150)
        ms, ans = median_ms(lambda: calibrate(model, meas, mode="geometric"), runs)
        row = {"robot": robot, "seed": seed, "ms": ms, "cpu_ms": CPU_MS[-1], "chosen": ans["model_selection"]["chosen"]}
        if peer and not out:
            t = time.perf_counter()
            row["peer_chosen"] = scipy_selection(model, meas)
            row["peer_ms"] = 1e3 * (time.perf_counter() - t)
        out.append(row)
    return out


CASES = r"""
import json, sys
import numpy as np
import calib_core
from calib_core import Twin, parse_model
from calib_core.robots import arm6, spray7
from calib_core.select import select_geometry
sp, a6 = parse_model(spray7()), parse_model(arm6())
cases = ([("spray7", sp, s, 150, None, None) for s in range(10)] + [("arm6", a6, s, 150, None, None) for s in range(3)]
         + [("spray7-huber", sp, 100 + s, 150, "huber", None) for s in range(3)]
         + [("spray7-1mm", sp, 200 + s, 150, None, 1.0) for s in range(3)]
         + [(f"spray7-{n}poses", sp, 300 + n, n, None, None) for n in (8, 15, 25, 40)])
out = []
for name, m, seed, n, loss, noise in cases:
    meas = Twin(m, seed).measure(n=n)
    if noise:
        meas.points = meas.points + np.random.default_rng(seed).normal(0, noise, meas.points.shape)
        meas.sigma = np.full(meas.n_poses, noise)
    s = select_geometry(m, meas, loss=loss)
    out.append({"case": f"{name}/{seed}/{n}", "x": s.calibration.x.tolist(),
                "choice": [s.chosen_label, s.best_label, s.prior_scale, s.calibration.free.tolist()],
                "rms": [r["holdout_rms_mm"] for r in s.table]})
assert calib_core.__file__.startswith(sys.argv[1]), calib_core.__file__
json.dump(out, sys.stdout)
"""
"""The 23 cases of the equivalence check, run in a child process with a tree first on its path: JSON per case."""


def selections(tree: Path) -> list[dict]:
    """The 23 cases' selections made by the calib_core of `tree` (in a process of its own)."""
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    return json.loads(subprocess.run([sys.executable, "-c", CASES, str(tree)], env=env, cwd=tree, check=True,
                                     capture_output=True, text=True).stdout)


def same_as(other: Path) -> None:
    """Print whether this tree's selections agree with those of the tree at `other`."""
    ours, theirs = selections(Path(__file__).resolve().parents[1]), selections(other.resolve())
    differ = [a["case"] for a, b in zip(ours, theirs) if a["choice"] != b["choice"]]
    rms = max(abs(u - v) / v for a, b in zip(ours, theirs) for u, v in zip(a["rms"], b["rms"])
              if u is not None and v is not None)
    x = max(abs(u - v) / max(1.0, abs(v)) for a, b in zip(ours, theirs) for u, v in zip(a["x"], b["x"]))
    print(f"{len(ours)} cases against {other}: chosen model, best candidate, free set and prior "
          f"{'identical on all' if not differ else 'DIFFERENT on ' + ', '.join(differ)}; largest relative difference "
          f"of a candidate's held-out RMS {rms:.1e}, of a chosen parameter {x:.1e} (mm, rad; relative above 1)"
          + ("; identical to the bit" if ours == theirs else ""))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--same-as", type=Path, metavar="DIR", help="check the choices against the tree at DIR instead")
    a = ap.parse_args()
    if a.same_as:
        return same_as(a.same_as)
    rows = run(a.seeds, a.runs, not a.no_peer)
    print("| robot | twin seed | poses | calibrate geometric, median (ms) | CPU (ms) | chosen "
          "| scipy FD selection (ms) | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        peer = (f"{r['peer_ms']:.0f} (chose {r['peer_chosen']})", f"{r['peer_ms'] / r['ms']:.0f}x") \
            if "peer_ms" in r else ("", "")
        print(f"| {r['robot']} | {r['seed']} | 150 | {r['ms']:.0f} | {r['cpu_ms']:.0f} | {r['chosen']} | {peer[0]} "
              f"| {peer[1]} |")
    spray = [r["ms"] for r in rows if r["robot"] == "spray7"]
    spray_cpu = [r["cpu_ms"] for r in rows if r["robot"] == "spray7"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\nspray7, {len(spray)} twins: median {statistics.median(spray):.0f} ms, max {max(spray):.0f} ms wall; CPU "
          f"median {statistics.median(spray_cpu):.0f} ms (median of {a.runs} calls each, one core; load average "
          f"{load:.1f} at the end)")


if __name__ == "__main__":
    main()
