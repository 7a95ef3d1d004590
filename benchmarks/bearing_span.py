"""What keeps the lateral compliance of every joint from the independent world's elastic bearings (issue 9)?

For the detection run's elastic-bearing draws (same seeds as benchmarks/detection.py), the share of the part of the
world's deflection that no geometric parameter absorbs which lies in the span of [the geometric Jacobian, the
lateral compliance of every bent joint], with the form evaluated on the geometry the diagnosis fits and on:
  - the model's mass data (15 % off, centres of mass 30 mm off);
  - the world's true mass data;
  - the true mass data and gravity's true direction in the fitted base frame;
and the angle (mrad) between gravity as the model has it (the model's base z in the fitted base frame) and the
world's. A share below 1 is what the form cannot represent, whatever its compliances.

    .venv/bin/python -m benchmarks.bearing_span [--draws 4] [--sizes 2]
"""
from __future__ import annotations

import argparse
import dataclasses
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from benchmarks.detection import LOAD_CYCLE_KG, N_CAL, ROBOTS, SEED_BASE, _span_share, job_seeds  # noqa: E402
from calib_core import kinematics as K  # noqa: E402
from calib_core.effects import LateralJointCompliance  # noqa: E402
from calib_core.identify import effect_bases, identify  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.statics import gravity_world  # noqa: E402
from calib_world import World, hide  # noqa: E402


def _mrad(a: np.ndarray, b: np.ndarray) -> float:
    return 1e3 * float(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))


def shares(robot: str, size: float, draw: int) -> dict:
    """The shares in span of one detection draw's elastic bearings, and the model's gravity error (mrad)."""
    model = parse_model(ROBOTS[robot]())
    s_world, s_hide, _ = job_seeds(SEED_BASE, robot, "elastic_bearings", f"{size:g}", draw)
    world = World(model, s_world)
    rng = np.random.default_rng(s_hide)
    q = world.sample_joints(N_CAL, rng)
    info = hide(world, "elastic_bearings", size, rng, q=q, payload_kg=LOAD_CYCLE_KG[robot])
    camp = world.campaign(q, payload_kg=LOAD_CYCLE_KG[robot])
    meas = camp.meas
    u = world.unabsorbed(camp.truth.displacement, world.absorbable_basis(q)).ravel()
    geo = identify(model, meas)
    chain = K.Chain(model, geo.x, meas.joints, geo.R0)
    Jg, Jq = chain.jacobian()[:, :, geo.free], chain.joint_jacobian()
    r = world.robot
    true_masses = tuple(map(tuple, np.column_stack([r.mass, r.mass[:, None] * r.com])))
    g_true = np.linalg.solve(chain.Rb, r.gravity_tracker())  # the world's gravity in the fitted base frame
    bent = tuple(model.joint_names.index(n) for n in info["joints"])
    out = {"gravity_off_mrad": _mrad(gravity_world(chain), r.gravity_tracker())}
    for label, e in (("model masses", LateralJointCompliance(bent)),
                     ("true masses", LateralJointCompliance(bent, masses=true_masses)),
                     ("true masses and gravity", LateralJointCompliance(bent, masses=true_masses,
                                                                       gravity=tuple(g_true)))):
        Pq, Pp = effect_bases(model, meas, [e], geo.x, geo.R0)
        out[label] = _span_share(u, [Jg, np.einsum("nij,njk->nik", Jq, Pq) + Pp])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--sizes", default="2")
    args = ap.parse_args()
    cols = ("model masses", "true masses", "true masses and gravity")
    print("| robot | size | draw | model's gravity off (mrad) | " + " | ".join(f"share: {c}" for c in cols) + " |")
    print("|---|---|---|---|" + "---|" * len(cols))
    for robot in ROBOTS:
        for size in (float(s) for s in args.sizes.split(",")):
            for draw in range(args.draws):
                s = shares(robot, size, draw)
                print(f"| {robot} | {size:g}x | {draw} | {s['gravity_off_mrad']:.1f} | "
                      + " | ".join(f"{s[c]:.3f}" for c in cols) + " |", flush=True)


if __name__ == "__main__":
    main()
