"""What the blind diagnosis finds on real measured robots, and the held-out gain of the extended model.

Every data set on 5 seeded 70/30 splits (split s permutes with default_rng(1000 + s)): the diagnosis runs on
the 70 % and tunes only there (its own k-fold), then registration only, the geometric and the extended model
are judged on the 30 % they never saw. Reports per split and mean +- std, and the causes named on each split
(a named cause should be stable across splits).
Run: .venv/bin/python -m benchmarks.real_diagnosis [--splits 5] [--sets motoman,iiwa,justin_right,justin_left]
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from concurrent.futures import ProcessPoolExecutor  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.accuracy import split_70_30  # noqa: E402
from calib_core import datasets  # noqa: E402
from calib_core.diagnosis import diagnose  # noqa: E402
from calib_core.identify import evaluate  # noqa: E402
from calib_core.io import parse_measurements  # noqa: E402
from calib_core.model import parse_model  # noqa: E402

SETS = {
    "motoman": lambda: datasets.motoman_leica(),
    "iiwa": lambda: datasets.iiwa7_payload(None),
    "justin_right": lambda: datasets.agile_justin("right"),
    "justin_left": lambda: datasets.agile_justin("left"),
}


def _named(f: dict) -> str:
    joints = ",".join(f["joints"])
    odd = " (not a physical size)" if f.get("physical") is False else ""
    return f"{f['kind']}{' ' + joints if joints else ''}{' h' + str(f['harmonic']) if 'harmonic' in f else ''}{odd}"


def run(name: str, s: int) -> dict:
    ds = SETS[name]()
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model)
    tr, te = split_70_30(meas.n_poses, 1000 + s)
    train, test = meas.subset(tr), meas.subset(te)
    d = diagnose(model, train)
    return {"set": name, "split": s, "n_train": len(tr), "n_test": len(te),
            "registration": evaluate(d.nominal, test), "geometric": evaluate(d.geometric, test),
            "extended": evaluate(d.calibration, test), "findings": [_named(f) for f in d.findings],
            "floor": d.noise_floor_mm, "verdict": d.verdict(), "explanation": d.explanation}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", type=int, default=5)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    if not datasets.available():
        print("../shared/datasets is absent: nothing to run")
        return
    names = [n for n in args.sets.split(",") if n]
    jobs = [(n, s) for n in names for s in range(args.splits)]
    with ProcessPoolExecutor(max_workers=min(args.workers, 2)) as pool:
        rows = list(pool.map(run, *zip(*jobs)))
    print("| data | split | cal / held-out poses | registration RMS / mean (mm) | geometric RMS / mean / max (mm) | "
          "extended RMS / mean / max (mm) | causes named |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        g, e, n = r["geometric"], r["extended"], r["registration"]
        print(f"| {r['set']} | {r['split']} | {r['n_train']} / {r['n_test']} | {n['rms_mm']:.3f} / {n['mean_mm']:.3f} | "
              f"{g['rms_mm']:.3f} / {g['mean_mm']:.3f} / {g['max_mm']:.3f} | "
              f"{e['rms_mm']:.3f} / {e['mean_mm']:.3f} / {e['max_mm']:.3f} | {'; '.join(r['findings']) or 'none'} |")
    print()
    print("| data | registration mean (mm) | geometric RMS (mm) | extended RMS (mm) | extended mean (mm) | "
          "extended better than geometric on | causes named on every split |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        rs = [r for r in rows if r["set"] == name]
        col = lambda model, key: np.array([r[model][key] for r in rs])  # noqa: E731
        ms = lambda a: f"{a.mean():.3f} +- {a.std(ddof=1) if len(a) > 1 else 0.0:.3f}"  # noqa: E731
        wins = int((col("extended", "rms_mm") < col("geometric", "rms_mm")).sum())
        stable = set.intersection(*[set(r["findings"]) for r in rs]) if rs else set()
        print(f"| {name} | {ms(col('registration', 'mean_mm'))} | {ms(col('geometric', 'rms_mm'))} | "
              f"{ms(col('extended', 'rms_mm'))} | {ms(col('extended', 'mean_mm'))} | {wins} of {len(rs)} splits | "
              f"{'; '.join(sorted(stable)) or 'none'} |")
    print()
    for name in names:
        r = next(r for r in rows if r["set"] == name)
        print(f"**{name}, split {r['split']}**: {r['explanation']}\n")


if __name__ == "__main__":
    main()
