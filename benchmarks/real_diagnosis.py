"""What the blind diagnosis finds on real measured robots, and the held-out gain of the extended model.

Fixed 70/30 split (the same seeded permutation as benchmarks.accuracy): diagnose on 70 %, then compare
the geometric and the extended model on the 30 % it never saw.
Run: .venv/bin/python -m benchmarks.real_diagnosis
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


from benchmarks.accuracy import split_70_30  # noqa: E402
from calib_core import datasets  # noqa: E402
from calib_core.diagnose import diagnose  # noqa: E402
from calib_core.identify import evaluate, identify  # noqa: E402
from calib_core.io import parse_measurements  # noqa: E402
from calib_core.model import parse_model  # noqa: E402


def run(ds) -> dict:
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model)
    tr, te = split_70_30(meas.n_poses)
    train, test = meas.subset(tr), meas.subset(te)
    d = diagnose(model, train)
    return {"name": ds.name, "n_train": len(tr), "n_test": len(te), "diagnosis": d,
            "geometric": evaluate(d.geometric, test), "extended": evaluate(d.calibration, test)}


def payload_trend() -> list[tuple[float, float]]:
    """Geometric-model RMS per payload run of the iiwa (each fitted on its own)."""
    out = []
    for kg in sorted(datasets.IIWA_RUNS):
        ds = datasets.iiwa7_payload(kg)
        model = parse_model(ds.model)
        out.append((kg, identify(model, parse_measurements(ds.csv_text, model), folds=0).metrics()["rms_mm"]))
    return out


def main():
    if not datasets.available():
        print("../shared/datasets is absent: nothing to run")
        return
    rows = [run(datasets.motoman_leica()), run(datasets.iiwa7_payload(None))]
    print("| data | cal / held-out poses | noise floor (mm) | geometric held-out RMS / max (mm) | "
          "extended held-out RMS / max (mm) | findings (held-out gain on the 70 % by CV) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        d, g, e = r["diagnosis"], r["geometric"], r["extended"]
        found = "; ".join(f"{f['kind']}{' ' + ','.join(f['joints']) if f['joints'] else ''}"
                          f"{' h' + str(f['harmonic']) if 'harmonic' in f else ''} ({f['gain_pct']:.0f} %)"
                          for f in d.findings) or "none"
        print(f"| {r['name']} | {r['n_train']} / {r['n_test']} | {d.noise_floor_mm:.3f} | "
              f"{g['rms_mm']:.3f} / {g['max_mm']:.3f} | {e['rms_mm']:.3f} / {e['max_mm']:.3f} | {found} |")
    print()
    for r in rows:
        print(f"**{r['name']}**: {r['diagnosis'].explanation}\n")
        for f in r["diagnosis"].findings:
            print(f"- {f['kind']}: {f['evidence']}")
        print()
    print("| iiwa payload (kg) | geometric RMS (mm), each run fitted alone |")
    print("|---|---|")
    for kg, rms in payload_trend():
        print(f"| {kg:g} | {rms:.3f} |")


if __name__ == "__main__":
    main()
