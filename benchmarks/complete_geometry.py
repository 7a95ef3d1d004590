"""The complete geometry on real trees (issue 30): Agile Justin and the Hilti column, geometric model only, held out.

Each dataset as `calib convert-dataset` writes it, split 70/30 by recorded pose on three seeds (0, 1000, 1001, as
benchmarks.justin_elastic), calibrated on the 70 % with the complete rows (gamma and b where the identifiability
analysis takes them) and with the classic five per row (`free=` every name but gamma and b: the set the analysis
chose before them, to the name), judged on the 30 % never seen.

    .venv/bin/python -m benchmarks.complete_geometry [--datasets dlr_agile_justin hilti_trailblazer]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.accuracy import split_70_30  # noqa: E402
from benchmarks.real_cells import load  # noqa: E402
from calib_core import kinematics as K  # noqa: E402
from calib_core.datasets import SHARED_DATASETS  # noqa: E402
from calib_core.identify import evaluate, identify  # noqa: E402

SPLITS = (0, 1000, 1001)


def run(name: str, seed: int) -> dict:
    _, model, meas, groups = load(name, SHARED_DATASETS)
    ids = np.unique(groups)
    cal, test = split_70_30(len(ids), seed=seed)
    train = meas.subset(np.flatnonzero(np.isin(groups, ids[cal])))
    held = meas.subset(np.flatnonzero(np.isin(groups, ids[test])))
    classic = tuple(s for s in K.parameter_names(model, train.setup_names) if not s.endswith((".gamma", ".b")))
    out = {}
    for label, free in (("classic", classic), ("complete", None)):
        t0 = time.time()
        c = identify(model, train, free=free, folds=0)
        out[label] = {**evaluate(c, held), "n_params": len(c.free), "seconds": time.time() - t0,
                      "pair": [c.names[i] for i in c.free if c.names[i].endswith((".gamma", ".b"))]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["dlr_agile_justin", "hilti_trailblazer"])
    args = ap.parse_args()
    print("| dataset | split | classic: params, held-out mean / RMS / max (mm) | complete: params, held-out mean / "
          "RMS / max (mm) | gamma, b taken |")
    print("|---|---|---|---|---|")
    for name in args.datasets:
        means = {"classic": [], "complete": []}
        for s in SPLITS:
            r = run(name, s)
            cells = []
            for label in ("classic", "complete"):
                e = r[label]
                means[label].append(e["mean_mm"])
                cells.append(f"{e['n_params']}, {e['mean_mm']:.3f} / {e['rms_mm']:.3f} / {e['max_mm']:.2f}")
            print(f"| {name} | {s} | {cells[0]} | {cells[1]} | {', '.join(r['complete']['pair']) or '-'} |",
                  flush=True)
        print(f"| {name} | mean of {len(SPLITS)} | {np.mean(means['classic']):.3f} | "
              f"{np.mean(means['complete']):.3f} | |", flush=True)


if __name__ == "__main__":
    main()
