"""Pose planning (issue 12) on the independent world (calib_world): accuracy, speed, and look-alike causes split.

1. Speed: time to plan 50 poses out of 20,000 candidates (geometric, best of 3), spray7 and arm6.
2. Geometric accuracy: per seed a World(model, seed) (true geometry, tracker frame, tool, wrong masses, its own
   noise) measured at 50 planned poses (D-optimal with load variety, the default; geometry only; and the
   default without limit-biased candidates and exchange step, the first version), at 50 and 150 random poses
   the tracker can see (uniform candidates kept by the planner's visibility rule) and at 150 random poses
   anywhere within the limits; each set calibrated as the service's `geometric` job does (select_geometry); validation
   error = RMS 3-D distance to the world's noise-free truth at 300 fresh random poses, the condition number
   and observability index O1 of each set (as the calibration answer reports them), and the error linear
   theory predicts from each set's information matrix and the world's noise.
3. Look-alike causes: per draw a world hiding a load-driven cause (sized 3x the noise, as benchmarks.detection
   sizes them), 150 random poses with a 0/10/20 kg payload cycle, the `auto` diagnosis; where a finding lists a
   look-alike that is not merely a richer form of it (plan.nested), 30 poses planned for `diagnosis` and 30
   random poses are measured after the campaign, each added to the set and diagnosed again: is the pair still
   listed as indistinguishable, and what is named.

Run:    .venv/bin/python -m benchmarks.bench_plan [--seeds 5] [--draws 4] [--workers 2]
Quick:  .venv/bin/python -m benchmarks.bench_plan --quick
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from concurrent.futures import ProcessPoolExecutor  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks import best_time  # noqa: E402
from calib_core import kinematics as K  # noqa: E402
from calib_core.diagnosis import diagnose  # noqa: E402
from calib_core.identifiability import structural  # noqa: E402
from calib_core.io import Measurements  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.plan import lookalike_pairs, plan, tracker_of, visible_pool  # noqa: E402
from calib_core.robots import arm6, spray7  # noqa: E402
from calib_core.select import select_geometry  # noqa: E402
from calib_world import World, hide  # noqa: E402

ROBOTS = {"spray7": spray7, "arm6": arm6}
N_PLAN, N_MORE, N_VAL, N_ADD = 50, 150, 300, 30
LOOKALIKE_KINDS = ("stiffening_spring", "joint_spring", "cantilever")
PAYLOAD_CYCLE_KG = [0.0, 10.0, 20.0]
SEED_BASE = 5000


# ------------------------------------------------------------------------------------------ 1. speed
def speed(repeats: int) -> list[dict]:
    out = []
    for name, doc in ROBOTS.items():
        model = parse_model(doc())
        plan(model, N_PLAN)  # warm: imports, the structural identifiability cache
        t, p = best_time(lambda: plan(model, N_PLAN, seed=1), repeats)
        out.append({"robot": name, "seconds": t, "visible": p.observability["visible_candidates"]})
    return out


# ------------------------------------------------------------------------------------------ 2. accuracy
def predicted_rms_mm(model, world, q, q_val) -> float:
    """Linear theory: the RMS 3-D prediction error at q_val of the identifiable geometric parameters fitted to q
    with the world's noise, sqrt(mean trace(J_v M^-1 J_v^T)), M = sum J^T J / sigma^2 (nominal Jacobian)."""
    ident = structural(model).identifiable
    jac = lambda qq: K.Chain(model, K.nominal_vector(model), qq).jacobian()[:, :, ident]  # noqa: E731
    J = jac(q) / world.tracker_sigma_mm(world.geometric_points(q))[:, None, None]
    Jv = jac(q_val)
    Minv = np.linalg.inv(np.einsum("nip,niq->pq", J, J))
    return float(np.sqrt(np.mean(np.einsum("nip,pq,niq->n", Jv, Minv, Jv))))


def best_possible_rms_mm(model, world, q, q_val, n: int, iterations: int = 300) -> tuple[float, float]:
    """Linear theory's best validation RMS (mm) of any n poses taken from the candidates q: the I-optimal
    approximate design (weights w >= 0 summing to 1 over the candidates, criterion tr(M(w)^-1 C) / n with C the
    validation poses' mean J^T J, multiplicative algorithm) and its duality lower bound (2 tr(M^-1 C) - max_i
    tr(J_i M^-1 C M^-1 J_i^T), a convexity bound on the optimum). No n distinct poses (integer weights 1/n)
    can do better than the lower bound; returns (design, lower bound)."""
    ident = structural(model).identifiable
    jac = lambda qq: K.Chain(model, K.nominal_vector(model), qq).jacobian()[:, :, ident]  # noqa: E731
    J = jac(q) / world.tracker_sigma_mm(world.geometric_points(q))[:, None, None]
    Jv = jac(q_val)
    C = np.einsum("nip,niq->pq", Jv, Jv) / len(q_val)
    N, _, p = J.shape
    flat = J.reshape(-1, p)
    w = np.full(N, 1.0 / N)
    for _ in range(iterations):
        Minv = np.linalg.inv(flat.T @ (flat * np.repeat(w, 3)[:, None]))
        crit = float(np.trace(Minv @ C))
        phi = ((flat @ (Minv @ C @ Minv)) * flat).reshape(N, 3, p).sum(axis=(1, 2))
        w *= np.sqrt(phi)
        w /= w.sum()
    return float(np.sqrt(crit / n)), float(np.sqrt(max(2 * crit - phi.max(), 0.0) / n))


def accuracy_trial(robot: str, seed: int) -> list[dict]:
    """One world: every pose set calibrated and validated against the truth."""
    model = parse_model(ROBOTS[robot]())
    world = World(model, SEED_BASE + seed)
    rng = np.random.default_rng((seed, 1))
    pool = visible_pool(model, 20000, np.random.default_rng((seed, 2)), extreme_share=0.0)
    sets = {
        "planned (D-optimal, load variety)": model.expand_joints(plan(model, N_PLAN, seed=seed).joints),
        "planned (D-optimal, geometry only)": model.expand_joints(plan(model, N_PLAN, seed=seed, loads=False).joints),
        "planned (load variety; uniform candidates, greedy only)": model.expand_joints(
            plan(model, N_PLAN, seed=seed, extreme_share=0.0, exchange=0).joints),
        f"random visible, {N_PLAN}": pool.q[rng.choice(len(pool.q), N_PLAN, replace=False)],
        f"random visible, {N_MORE}": pool.q[rng.choice(len(pool.q), N_MORE, replace=False)],
        f"random anywhere, {N_MORE}": world.sample_joints(N_MORE, rng),
    }
    q_val = world.sample_joints(N_VAL, np.random.default_rng((seed, 3)))
    truth, noise = world.true_points(q_val), world.noise_rms_mm(q_val)
    rows = []
    for label, q in sets.items():
        cal = select_geometry(model, world.measure(q)).calibration
        err = np.sqrt(np.mean(np.sum((cal.predict(q_val) - truth) ** 2, axis=1)))
        ident = cal.identifiability
        rows.append({"robot": robot, "seed": seed, "set": label, "n": len(q), "val_rms_mm": float(err),
                     "predicted_rms_mm": predicted_rms_mm(model, world, q, q_val),
                     "val_over_noise": float(err / noise), "condition_number": ident.condition_number,
                     "observability_index": ident.observability_index})
    design, bound = best_possible_rms_mm(model, world, visible_pool(model, 20000, np.random.default_rng(seed)).q,
                                         q_val, N_PLAN)
    rows.append({"robot": robot, "seed": seed, "set": "best possible", "design_mm": design, "bound_mm": bound})
    return rows


# ------------------------------------------------------------------------------------------ 3. look-alikes
def _union(a: Measurements, b: Measurements) -> Measurements:
    cat = lambda x, y: None if x is None else np.concatenate([x, y])  # noqa: E731
    return Measurements(np.vstack([a.joints, b.joints]), np.vstack([a.points, b.points]),
                        list(a.point_ids) + [f"N{i + 1:03d}" for i in range(b.n_poses)],
                        cat(a.timestamp, b.timestamp), cat(a.temperature, b.temperature), cat(a.payload, b.payload))


def _said(findings) -> str:
    out = []
    for f in findings:
        alike = [f"{a['kind']}[{','.join(a['joints'])}]" for a in f.get("indistinguishable_from", [])]
        out.append(f"{f['kind']}[{','.join(f['joints'])}]" + (f" ~ {' ~ '.join(alike)}" if alike else ""))
    return "; ".join(out) or "[]"


def _together(model, findings, a, b) -> bool:
    """Whether one finding still names both effects, as itself or as a look-alike."""
    key = lambda e: (e.kind, [model.joint_names[j] for j in e.joints])  # noqa: E731
    for f in findings:
        named = [(f["kind"], list(f["joints"]))] + [(x["kind"], list(x["joints"]))
                                                    for x in f.get("indistinguishable_from", [])]
        if key(a) in named and key(b) in named:
            return True
    return False


def lookalike_trial(kind: str, draw: int) -> dict:
    model = parse_model(spray7())
    world = World(model, SEED_BASE + draw)
    rng = np.random.default_rng((draw, 7))
    q = world.sample_joints(N_MORE, rng)
    info = hide(world, kind, 3.0, rng, q=q, payload_kg=PAYLOAD_CYCLE_KG)
    meas = world.measure(q, payload_kg=PAYLOAD_CYCLE_KG)
    d = diagnose(model, meas)
    rec = {"kind": kind, "draw": draw, "hidden": info["joints"], "first": _said(d.findings)}
    pairs = lookalike_pairs(model, meas, d.calibration.effects, d.findings)
    if not pairs:
        return {**rec, "pairs": []}
    t = time.perf_counter()
    p = plan(model, N_ADD, "diagnosis", meas=meas, effects=d.calibration.effects, rivals=pairs,
             tracker_mm=tracker_of(d.calibration.robot), seed=draw)
    rec["plan_seconds"] = time.perf_counter() - t
    rec["pairs"] = [f"{a.label(model)} / {b.label(model)}" for a, b in pairs]
    rec["separation"] = [(r["planned"]["separation_chi2"], r["random"]["separation_chi2"], r["separation_needed_chi2"])
                         for r in p.observability["rivals"]]
    start = meas.timestamp[-1] + 20.0
    added = {"planned": world.measure(model.expand_joints(p.joints), payload_kg=p.payload, start_time=start),
             "random": world.measure(world.sample_joints(N_ADD, rng), payload_kg=PAYLOAD_CYCLE_KG, start_time=start)}
    for key, new in added.items():
        d2 = diagnose(model, _union(meas, new))
        rec[key] = _said(d2.findings)
        rec[f"{key}_split"] = [not _together(model, d2.findings, a, b) for a, b in pairs]
    return rec


# ------------------------------------------------------------------------------------------ tables
def _run(job):
    fn, args = job
    return fn(*args)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5, help="worlds per robot for the accuracy table")
    ap.add_argument("--draws", type=int, default=4, help="worlds per hidden kind for the look-alike table")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 worlds per robot, 1 draw of one kind, 1 timing")
    args = ap.parse_args(argv)
    seeds, draws, kinds, repeats = args.seeds, args.draws, LOOKALIKE_KINDS, 3
    if args.quick:
        seeds, draws, kinds, repeats = 2, 1, LOOKALIKE_KINDS[:1], 1
    t0 = time.perf_counter()
    print("## Pose planning (benchmarks/bench_plan.py)\n\n### Speed: 50 poses out of 20,000 candidates\n")
    print("| robot | visible candidates | seconds (best of %d) |\n|---|---|---|" % repeats)
    for r in speed(repeats):
        print(f"| {r['robot']} | {r['visible']} | {r['seconds']:.2f} |")
    jobs = [(accuracy_trial, (rb, s)) for rb in ROBOTS for s in range(seeds)]
    jobs += [(lookalike_trial, (k, i)) for k in kinds for i in range(draws)]
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = list(pool.map(_run, jobs))
    rows = [r for res in results[: len(ROBOTS) * seeds] for r in res]
    looks = results[len(ROBOTS) * seeds:]
    print(f"\n### Geometric accuracy on the independent world (mean of {seeds} worlds per robot)\n")
    print("| robot | pose set | poses | condition number | observability index O1 | validation RMS vs truth (mm) "
          "| / noise RMS | predicted by linear theory (mm) |\n|---|---|---|---|---|---|---|---|")
    for rb in ROBOTS:
        for label in dict.fromkeys(r["set"] for r in rows if r["set"] != "best possible"):
            rs = [r for r in rows if r["robot"] == rb and r["set"] == label]
            m = {k: float(np.mean([r[k] for r in rs])) for k in ("condition_number", "observability_index",
                                                                  "val_rms_mm", "val_over_noise", "predicted_rms_mm")}
            print(f"| {rb} | {label} | {rs[0]['n']} | {m['condition_number']:.1f} | {m['observability_index']:.4f} "
                  f"| {m['val_rms_mm']:.4f} | {m['val_over_noise']:.2f} | {m['predicted_rms_mm']:.4f} |")
    print(f"\nBest possible {N_PLAN} poses of the planner's visible candidates (linear theory, I-optimal approximate "
          "design; no design of distinct poses beats the lower bound):")
    for rb in ROBOTS:
        rs = [r for r in rows if r["robot"] == rb and r["set"] == "best possible"]
        each = ", ".join(f"{r['bound_mm']:.4f}" for r in rs)
        print(f"- {rb}: design {np.mean([r['design_mm'] for r in rs]):.4f} mm, lower bound "
              f"{np.mean([r['bound_mm'] for r in rs]):.4f} mm (per world: {each})")
    print(f"\n### Look-alike causes: {N_ADD} planned vs {N_ADD} random poses added (spray7, 150 random poses first)\n")
    print("| hidden | draw | first diagnosis | pair planned for | separation planned / random / needed (chi2) | "
          f"after +{N_ADD} planned | split | after +{N_ADD} random | split |\n|---|---|---|---|---|---|---|---|---|")
    for r in looks:
        if not r["pairs"]:
            print(f"| {r['kind']} {','.join(r['hidden'])} | {r['draw']} | {r['first']} | (no look-alike to split) "
                  "| | | | | |")
            continue
        sep = "; ".join(f"{a:.0f} / {b:.0f} / {c:.0f}" for a, b, c in r["separation"])
        yes = lambda v: "; ".join("yes" if x else "no" for x in v)  # noqa: E731
        print(f"| {r['kind']} {','.join(r['hidden'])} | {r['draw']} | {r['first']} | {'; '.join(r['pairs'])} | {sep} "
              f"| {r['planned']} | {yes(r['planned_split'])} | {r['random']} | {yes(r['random_split'])} |")
    cases = [r for r in looks if r["pairs"]]
    if cases:
        n_pairs = sum(len(r["pairs"]) for r in cases)
        split = {k: sum(sum(r[f"{k}_split"]) for r in cases) for k in ("planned", "random")}
        print(f"\nPairs split: {split['planned']} of {n_pairs} after the planned poses, {split['random']} of "
              f"{n_pairs} after as many random ones; diagnosis plan time "
              f"{np.mean([r['plan_seconds'] for r in cases]):.1f} s mean.")
    print(f"\nWall time {time.perf_counter() - t0:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
