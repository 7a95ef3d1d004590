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
from calib_core.twin import Twin, draw_hidden_effect  # noqa: E402


def main(sizes=(150, 2000)):
    model = parse_model(spray7())
    print("| poses | hidden effect | auto run (s) | findings | held-out RMS geometric -> extended (mm) |")
    print("|---|---|---|---|---|")
    for n in sizes:
        for kind in (None, "joint_compliance", "cyclic_joint_error", "unexplained"):
            twin = Twin(model, 7)
            q = twin.sample_joints(n)
            label = "none"
            if kind:
                effect, _ = draw_hidden_effect(twin, kind, 5.0, q, np.random.default_rng(7))
                label = effect.label(model)
            meas = twin.measure(q)
            t = time.perf_counter()
            out = calibrate(model, meas, "auto")
            dt = time.perf_counter() - t
            d = out["diagnosis"]
            found = ", ".join(f"{f['kind']} {','.join(f['joints'])}" for f in d["findings"]) or "none"
            print(f"| {n} | {label} | {dt:.1f} | {found} | {d['geometric']['holdout_rms_mm']:.3f} -> "
                  f"{out['metrics']['holdout_rms_mm']:.3f} |")


if __name__ == "__main__":
    main()
