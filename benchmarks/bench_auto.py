"""A full `auto` run (geometric fit, diagnosis, extension, cross-validation) on the 7-DoF twin.

Run: .venv/bin/python -m benchmarks.bench_auto
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from calib_core.model import parse_model  # noqa: E402
from calib_core.pipeline import calibrate  # noqa: E402
from calib_core.robots import spray7  # noqa: E402
from calib_world import World  # noqa: E402
from calib_world.scenarios import hide  # noqa: E402


def main(sizes=(150, 2000)):
    model = parse_model(spray7())
    print("| poses | hidden effect | auto run (s) | findings | held-out RMS geometric -> extended (mm) |")
    print("|---|---|---|---|---|")
    for n in sizes:
        for kind in (None, "joint_spring", "gear_error", "cable_force"):
            world = World(model, 7)
            q = world.sample_joints(n, np.random.default_rng(7))
            label = "none"
            if kind:
                info = hide(world, kind, 5.0, np.random.default_rng(7), q=q)
                label = f"{kind} {','.join(info['joints'])}"
            meas = world.measure(q)
            t = time.perf_counter()
            out = calibrate(model, meas, "auto")
            dt = time.perf_counter() - t
            d = out["diagnosis"]
            found = ", ".join(f"{f['kind']} {','.join(f['joints'])}" for f in d["findings"]) or "none"
            print(f"| {n} | {label} | {dt:.1f} | {found} | {d['geometric']['holdout_rms_mm']:.3f} -> "
                  f"{out['metrics']['holdout_rms_mm']:.3f} |")


if __name__ == "__main__":
    main()
