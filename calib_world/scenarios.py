"""Blind-test scenarios: hide one physical cause of a kind, sized against the world's own noise.

A cause is sized so that the part of its displacement that NO geometric parameter can absorb (the
world's own finite-difference Jacobian w.r.t. every MD-H parameter, the base and the tool, projected
out at the calibration poses) has RMS = size_x_noise x the 3-D noise RMS per pose.  `EXPECTED` says
which kind of the diagnosis's contract should report each world kind.
"""
from __future__ import annotations

import numpy as np

from calib_core.model import RobotModel

from .campaign import REPEATABILITY_RANGE_MM, World
from .mechanics import (BaseTilt, CableForce, Cantilever, ElasticBearings, EncoderScale, GearError, GearPlay, JointSpring,
                        RailStraightness, ReHoming, ThermalGrowth)

EXPECTED = {
    "joint_spring": "joint_compliance",
    "stiffening_spring": "joint_compliance",
    "hard_backlash": "backlash",
    "soft_backlash": "backlash",
    "gear_error": "cyclic_joint_error",
    "encoder_scale": "joint_scale",
    "rail_straightness": "axis_straightness",
    "cantilever": "link_deflection",
    "elastic_bearings": "link_deflection",
    "telescopic_bending": "link_deflection",
    "thermal_growth": "thermal_drift",
    "base_tilt": "unexplained",
    "rehoming_step": "unexplained",
    "cable_force": "unexplained",
}
"""World kind -> the contract kind a correct diagnosis reports."""
KINDS = tuple(EXPECTED)
LOADED_SHARE = 0.05
"""A load-driven cause is hidden only on a joint whose load varies by at least this share of the most
loaded joint's: a vertical axis carries only the levelling error's load, and a spring sized to show
there would be absurdly soft."""


def _unit(r, j: int, rev: float, lin: float) -> float:
    """A natural starting size for joint j: `rev` for a revolute joint (rad), `lin` for a linear one (mm)."""
    return lin if r.prismatic[j] else rev


def _candidates(world: World, kind: str, q, cols, rng) -> list:
    """Plausible causes of `kind` on every eligible joint/link, each at a natural (to be rescaled) size."""
    r = world.robot
    n = r.n
    moving = [j for j in range(n) if np.ptp(q[:, j]) > 1e-3]
    revolute = [j for j in moving if not r.prismatic[j]]
    linear = [j for j in moving if r.prismatic[j]]
    sign = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
    out = []
    if kind in ("joint_spring", "stiffening_spring", "hard_backlash", "soft_backlash"):
        tau = r.joint_loads(q, cols.payload_kg())
        big = np.abs(tau).max(0)
        for j in range(n):
            if np.ptp(tau[:, j]) <= LOADED_SHARE * max(np.ptp(tau, axis=0).max(), 1e-300):
                continue  # a (nearly) vertical axis: its load is a levelling error, no spring shows there
            tmax = big[j]
            if kind == "joint_spring":
                out.append(JointSpring(j, _unit(r, j, 1e-4, 1e-2) / tmax))
            elif kind == "stiffening_spring":
                c = _unit(r, j, 1e-4, 1e-2) / tmax
                # the cubic term carries 1..3 times the linear one at the largest load
                out.append(JointSpring(j, c, float(rng.uniform(1.0, 3.0)) / (c * tmax) ** 2))
            elif kind == "hard_backlash":
                out.append(GearPlay(j, _unit(r, j, 1e-4, 1e-2)))
            else:
                out.append(GearPlay(j, _unit(r, j, 1e-4, 1e-2), float(rng.uniform(0.1, 0.4)) * tmax))
    elif kind == "gear_error":
        out = [GearError(j, 1e-4, int(rng.integers(1, 4)), float(rng.uniform(0, 2 * np.pi))) for j in revolute]
    elif kind == "encoder_scale":
        out = [EncoderScale(j, 1e-4 * sign()) for j in moving]
    elif kind == "rail_straightness":
        out = [RailStraightness(j, 0.05 * sign(), float(rng.uniform(0.7, 2.5)), float(rng.uniform(0, np.pi)),
                                float(rng.uniform(0, 2 * np.pi))) for j in linear]
    elif kind in ("cantilever", "telescopic_bending"):
        o = r.frames(q).origins
        for k in range(1, n):
            if (kind == "telescopic_bending") != bool(r.prismatic[k]):
                continue
            if np.linalg.norm(o[:, k] - o[:, k - 1], axis=1).max() < 50.0:
                continue  # no link worth bending
            out.append(Cantilever(k, 1e12))
    elif kind == "elastic_bearings":
        # every moving joint's bearing (a rail's carriage, a telescope's guide too) that carries a bending moment,
        # compliances spread over a decade
        pose = r.frames(q)
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], r.gravity)
        com = r.body_coms(pose)
        bent, big = [], []
        for j in moving:
            M = (r.mass[None, j:, None] * np.cross(com[:, j:] - pose.axis_points[:, j, None], g[:, None])).sum(1)
            across = M - (M * pose.axes[:, j]).sum(1, keepdims=True) * pose.axes[:, j]
            size = np.linalg.norm(across, axis=1).max() / 1000.0
            if size > 0:
                bent.append(j)
                big.append(size)
        if len(bent) > 1:
            out = [ElasticBearings(tuple(bent), tuple(float(np.exp(rng.uniform(0, np.log(10)))) * 1e-4 / b
                                                      for b in big))]
    elif kind == "thermal_growth":
        v = rng.normal(size=3)
        out = [ThermalGrowth(1.15e-5, tuple(0.01 * v / np.linalg.norm(v)))]
    elif kind == "base_tilt":
        out = [BaseTilt(1e-7)]
    elif kind == "rehoming_step":
        out = [ReHoming(j, _unit(r, j, 1e-4, 1e-2) * sign(), float(rng.uniform(0.3, 0.7))) for j in moving]
    elif kind == "cable_force":
        for j in revolute:
            for o in revolute:
                if o != j:
                    lo, hi = q[:, o].min(), q[:, o].max()
                    out.append(CableForce(j, 1.0 * sign(), o, rest=float(rng.uniform(lo + 0.3 * (hi - lo),
                                                                                        hi - 0.3 * (hi - lo))),
                                          slack_mm=float(rng.uniform(0.0, 10.0))))
    else:
        raise ValueError(f"unknown kind {kind!r}; use one of {KINDS}")
    return out


def size_cause(world: World, cause, target_rms_mm: float, q, cols, basis=None, tol: float = 1e-10):
    """The cause scaled so its unabsorbable RMS is target_rms_mm (fixed-point iteration on the scale,
    exact in one step for a cause linear in its magnitude). Returns (cause, achieved RMS)."""
    basis = world.absorbable_basis(q) if basis is None else basis
    f = 1.0
    rms = world.unabsorbed_rms(cause, q, cols, basis=basis)
    for _ in range(60):
        if rms <= 0:
            raise ValueError("the cause is absorbed entirely by the geometry")
        f *= target_rms_mm / rms
        rms = world.unabsorbed_rms(cause.scaled(f), q, cols, basis=basis)
        if abs(rms / target_rms_mm - 1.0) < tol:
            break
    return cause.scaled(f), rms


def hide(world: World, kind: str, size_x_noise: float, rng: np.random.Generator, *, q=None, n: int = 150,
         payload_kg=None, temperature: bool | None = None, min_observable: float = 0.1) -> dict:
    """Hide a cause of world `kind` (see EXPECTED) on a random eligible joint, random sign/phase, sized to
    size_x_noise x the noise RMS of its unabsorbable part at poses q (or n fresh random poses).

    Measure at description['q'] with the same payload_kg/temperature (thermal_growth logs temperature by
    default) to see it.  Raises ValueError if no joint of this robot can show the kind observably
    (at least `min_observable` of its displacement left after the geometry absorbs its share).
    """
    q = world.sample_joints(n, rng) if q is None else np.atleast_2d(np.asarray(q, float))
    temperature = kind == "thermal_growth" if temperature is None else temperature
    cols = world.columns(q, payload_kg, temperature)
    pool = _candidates(world, kind, q, cols, rng)
    order = rng.permutation(len(pool))
    basis = world.absorbable_basis(q)
    noise = world.noise_rms_mm(q)
    for i in order:
        cause = pool[i]
        total = world.unabsorbed_rms(cause, q, cols, absorb=False)
        left = world.unabsorbed_rms(cause, q, cols, basis=basis)
        if not (total > 0 and left > min_observable * total):
            continue
        cause, rms = size_cause(world, cause, size_x_noise * noise, q, cols, basis)
        world.hide(cause)
        return {"kind": kind, "expected": EXPECTED[kind], "joints": cause.joints(world.robot),
                "parameters": cause.describe(world.robot), "size": size_x_noise,
                "unabsorbed_rms_mm": rms, "total_rms_mm": world.unabsorbed_rms(cause, q, cols, absorb=False),
                "noise_rms_mm": noise, "cause": cause, "q": q, "payload_kg": payload_kg,
                "temperature": temperature}
    raise ValueError(f"no joint of {world.model.name} can show {kind} observably")


def null_world(model: RobotModel, seed: int | None = None, *, rng: np.random.Generator | None = None,
               outliers: int = 0, repeatability_factor: float = 2.5, **kw) -> World:
    """A world with no hidden cause but wrong masses in the model, a robot repeating 2.5x worse than
    usual (50-75 um per axis) and optionally `outliers` bad readings per campaign: nothing to find."""
    rng = np.random.default_rng(seed) if rng is None else rng
    rep = repeatability_factor * float(rng.uniform(*REPEATABILITY_RANGE_MM))
    return World(model, rng=rng, repeatability_mm=rep, outliers=outliers, **kw)
