"""The Motoman with and without its measurement order (the `sequence` column, its pose_id): held out on random
70/30 splits (real_cells' splits 0-2) and on forward-in-time splits (calibrate on the first 50 / 70 / 85 % of the
session, judge on the rest: the robot's state after the calibration data, as a cell uses the model), the diagnosis
with the column against the same CSV without it. Held-out mean / RMS / max (mm).

Run: .venv/bin/python -m benchmarks.measurement_order [--jobs 2] [--root DIR]   (about 1 min on 2 cores)
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.real_cells import load, split  # noqa: E402
from calib_core.diagnosis import diagnose  # noqa: E402
from calib_core.identify import evaluate  # noqa: E402

SPLITS = [("random", s) for s in range(3)] + [("forward", f) for f in (0.5, 0.7, 0.85)]


def _one(job: tuple[str, float, str]) -> dict:
    kind, arg, root = job
    _, model, meas, groups = load("motoman_leica", Path(root))
    if kind == "random":
        cal, test = split(groups, 1000 + int(arg) if arg else 0)  # real_cells' split numbering
    else:  # the first share of the session in its measurement order
        first = np.argsort(meas.sequence, kind="stable")[: int(arg * meas.n_poses)]
        cal = np.isin(np.arange(meas.n_poses), first)
        test = ~cal
    out = {"split": f"{kind} {arg:g}", "cal": int(cal.sum()), "test": int(test.sum())}
    for name, m in (("without", dataclasses.replace(meas, sequence=None)), ("with", meas)):
        t = time.perf_counter()
        d = diagnose(model, m.subset(cal))
        e = evaluate(d.calibration, m.subset(test))
        out[name] = (e["mean_mm"], e["rms_mm"], e["max_mm"])
        out[f"{name}_s"] = time.perf_counter() - t
        out[f"{name}_steps"] = [f["form"] for f in d.findings if str(f.get("form", "")).startswith("step[")]
    out["geometric"] = tuple(evaluate(d.geometric, m.subset(test))[k] for k in ("mean_mm", "rms_mm", "max_mm"))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--root", default=os.environ.get("CALIB_SHARED_DATASETS",
                                                    str(Path(__file__).resolve().parents[2] / "shared" / "datasets")))
    a = p.parse_args()
    t = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.jobs) as pool:
        rows = list(pool.map(_one, [(k, arg, a.root) for k, arg in SPLITS]))
    f = lambda v: " / ".join(f"{x:.2f}" for x in v)  # noqa: E731
    print("| split | cal / held-out poses | geometric | diagnosed without `sequence` | diagnosed with `sequence` | "
          "steps found with it |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['split']} | {r['cal']} / {r['test']} | {f(r['geometric'])} | {f(r['without'])} | "
              f"**{f(r['with'])}** | {', '.join(r['with_steps']) or 'none'} |")
    for kind in ("random", "forward"):
        mine = [r for r in rows if r["split"].startswith(kind)]
        mean = lambda k: np.mean([r[k] for r in mine], axis=0)  # noqa: E731
        print(f"| {kind}: mean of {len(mine)} | | {f(mean('geometric'))} | {f(mean('without'))} | "
              f"**{f(mean('with'))}** | |")
    print(f"\nwall time {time.perf_counter() - t:.0f} s, {a.jobs} job(s)")


if __name__ == "__main__":
    main()
