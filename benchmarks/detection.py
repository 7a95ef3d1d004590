"""Blind detection of hidden effects on the 7-DoF twin: rate per kind, false positives, smallest size.

Each draw: a fresh twin (geometric errors, tracker frame, tool, noise), one hidden effect of the kind on a
randomly drawn eligible joint in a random direction, sized as n x the noise RMS for the part no geometric
parameter can absorb; 150 calibration poses; the pipeline runs blind (`diagnose`). A draw is detected
when the first finding has the right kind and joint. No-effect twins count any finding as a false positive.
Run: .venv/bin/python -m benchmarks.detection [--draws 20] [--null 50]
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from concurrent.futures import ProcessPoolExecutor  # noqa: E402

import numpy as np  # noqa: E402

from calib_core.diagnose import diagnose  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.robots import spray7  # noqa: E402
from calib_core.twin import HIDDEN_KINDS, Twin, draw_hidden_effect  # noqa: E402

SIZES = (0.5, 1.0, 1.5, 2.0, 4.0, 10.0)


def trial(kind: str | None, n_noise: float, seed: int) -> dict:
    model = parse_model(spray7())
    rng = np.random.default_rng(seed)
    twin = Twin(model, seed)
    q = twin.sample_joints(150)
    truth = None
    if kind is not None:
        effect, _ = draw_hidden_effect(twin, kind, n_noise, q, rng)
        truth = (kind, [model.joint_names[j] for j in effect.joints] if kind != "unexplained" else [])
    meas = twin.measure(q, temperature=kind == "thermal_drift")
    d = diagnose(model, meas)
    found = [(f["kind"], f["joints"]) for f in d.findings]
    final, floor = d.calibration.metrics()["holdout_rms_mm"], twin.noise_rms_mm(meas.points)
    return {"kind": kind, "n_noise": n_noise, "seed": seed, "truth": truth, "found": found,
            "hit": bool(found) and found[0] == truth if truth else not found,
            "final_over_floor": final / floor}


def pair_trial(kinds: tuple[str, str], seed: int) -> dict:
    """Two named causes hidden together at 5x noise each: are both found (or listed as look-alikes)?"""
    model = parse_model(spray7())
    rng = np.random.default_rng(seed)
    twin = Twin(model, seed)
    q = twin.sample_joints(150)
    hidden = {(k, tuple(model.joint_names[j] for j in draw_hidden_effect(twin, k, 5.0, q, rng)[0].joints))
              for k in kinds}
    d = diagnose(model, twin.measure(q))
    named = {(f["kind"], tuple(f["joints"])) for f in d.findings}
    alike = named | {(a["kind"], tuple(a["joints"])) for f in d.findings for a in f.get("indistinguishable_from", [])}
    return {"kinds": kinds, "exact": hidden <= named, "with_lookalikes": hidden <= alike}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--null", type=int, default=50)
    args = ap.parse_args()
    jobs = [(None, 0.0, 10_000 + s) for s in range(args.null)]
    jobs += [(k, n, 1000 * i + s) for i, k in enumerate(HIDDEN_KINDS) for n in SIZES for s in range(args.draws)]
    with ProcessPoolExecutor(os.cpu_count()) as pool:
        results = list(pool.map(trial, *zip(*jobs)))
    null = [r for r in results if r["kind"] is None]
    print(f"False positives on {len(null)} no-effect twins: {sum(not r['hit'] for r in null)} "
          f"({100 * np.mean([not r['hit'] for r in null]):.0f} %)\n")
    print("| kind | " + " | ".join(f"{n:g}x" for n in SIZES) + " | smallest size with >= 90 % | "
          "held-out / floor at 4x |")
    print("|---|" + "---|" * (len(SIZES) + 2))
    for k in HIDDEN_KINDS:
        rates = []
        for n in SIZES:
            rs = [r for r in results if r["kind"] == k and r["n_noise"] == n]
            rates.append(np.mean([r["hit"] for r in rs]))
        smallest = next((f"{n:g}x" for n, rt in zip(SIZES, rates) if rt >= 0.9), "-")
        ratio = np.median([r["final_over_floor"] for r in results if r["kind"] == k and r["n_noise"] == 4.0])
        print(f"| {k} | " + " | ".join(f"{100 * rt:.0f} %" for rt in rates) + f" | {smallest} | {ratio:.2f} |")
    named = [k for k in HIDDEN_KINDS if k not in ("unexplained", "thermal_drift")]
    pairs = [(a, b) for i, a in enumerate(named) for b in named[i + 1:]]
    with ProcessPoolExecutor(os.cpu_count()) as pool:
        pr = list(pool.map(pair_trial, [p for p in pairs for _ in range(args.draws // 4)],
                           [500_000 + s for s in range(len(pairs) * (args.draws // 4))]))
    print(f"\nTwo causes hidden together at 5x noise each ({len(pr)} draws over {len(pairs)} pairs of kinds):"
          f" both named {100 * np.mean([r['exact'] for r in pr]):.0f} %, both named or listed as "
          f"indistinguishable {100 * np.mean([r['with_lookalikes'] for r in pr]):.0f} %.")
    bad = sorted({r["kinds"] for r in pr if not r["exact"]})
    if bad:
        print("Pairs with a miss: " + ", ".join(f"{a} + {b}" for a, b in bad))
    misses = [r for r in results if r["kind"] and not r["hit"] and r["n_noise"] >= 2.0]
    if misses:
        print("\nMisses at 2x and above (kind, size, seed: truth -> found):")
        for r in misses:
            print(f"- {r['kind']}, {r['n_noise']:g}x, seed {r['seed']}: {r['truth']} -> {r['found']}")


if __name__ == "__main__":
    main()
