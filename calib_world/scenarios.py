"""Blind-test scenarios: hide one physical cause of a kind, sized against the world's own noise.

A cause is sized so that the part of its displacement that NO geometric parameter can absorb (the
world's own finite-difference Jacobian w.r.t. every MD-H parameter, the base and the tool, projected
out at the calibration poses) has RMS = size_x_noise x the 3-D noise RMS per pose.  `EXPECTED` says
which kind of the diagnosis's contract should report each world kind.
"""
from __future__ import annotations

import copy

import numpy as np

from calib_core.model import RobotModel

from .campaign import REPEATABILITY_RANGE_MM, World
from .mechanics import (BaseTilt, CableForce, Cantilever, ElasticBearings, EncoderScale, GearError, GearPlay, JointSpring,
                        JointSprings, LinkGrowth, RailStraightness, ReHoming, TargetStep, TelescopicSag, ThermalGrowth,
                        TiltedBase)
from .robot import rotvec

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
    "base_tilt": "base_compliance",
    "rehoming_step": "unexplained",
    "cable_force": "unexplained",
}
"""World kind -> the contract kind a correct diagnosis reports."""
KINDS = tuple(EXPECTED)
"""The kinds of the first blind benchmark (RESULTS 3.2, the demo's --effect): unchanged, so its table reproduces."""
EXPECTED_34 = {
    "play_load_sign": "backlash",
    "link_thermal_growth": "thermal_drift",
    "target_remount": "unexplained",
    "tilted_base_spring": "joint_compliance",
    "tilted_base_sag": "link_deflection",
    "telescopic_sag": "link_deflection",
    "two_joint_springs": "joint_compliance",
    "mount_compliance": "base_compliance",
}
"""Issue 34's mechanisms -> the contract kind a correct diagnosis reports (a target re-mounted mid-campaign has no
kind of its own: a step in time order, `unexplained`)."""
MECHANISMS_34 = tuple(EXPECTED_34)
EXPECTED.update(EXPECTED_34)
THERMAL_KINDS = ("thermal_growth", "link_thermal_growth")
"""Kinds whose campaign logs the temperature by default."""
PLAY_SIGN_SHARE = (0.15, 0.85)
"""play_load_sign: a joint is eligible only where its true load is positive at this share of the poses (the load
changes sign at many poses, not at two)."""
TILT_DEG = (3.0, 10.0)
"""tilted_base_*: gravity's true direction is this many degrees off the model's (uniform), about a random horizontal
axis."""
MOUNT_RATIO = (1.0, 6.0)
"""mount_compliance: the mount is this many times stiffer across its soft axis than about it (uniform; a platform on
wheels: Agile Justin's fit finds about 5), the soft axis at a uniform angle about gravity."""
TILT_MADE_SHARE = 0.25
"""tilted_base_spring: the spring sits on a joint where the tilt changes the load by at least this share (RMS) of
the tilted load: the load the model's gravity cannot compute (a vertical axis), and carries at least half
LOADED_SHARE of the most loaded joint's; where no joint does, any joint loaded under the tilt."""
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
        out = [ReHoming.within(j, _unit(r, j, 1e-4, 1e-2) * sign(), float(rng.uniform(0.3, 0.7)), cols.timestamp)
               for j in moving]
    elif kind == "cable_force":
        for j in revolute:
            for o in revolute:
                if o != j:
                    lo, hi = q[:, o].min(), q[:, o].max()
                    out.append(CableForce(j, 1.0 * sign(), o, rest=float(rng.uniform(lo + 0.3 * (hi - lo),
                                                                                        hi - 0.3 * (hi - lo))),
                                          slack_mm=float(rng.uniform(0.0, 10.0))))
    elif kind in MECHANISMS_34:
        out = _candidates_34(world, kind, q, cols, rng, moving)
    else:
        raise ValueError(f"unknown kind {kind!r}; use one of {KINDS + MECHANISMS_34}")
    return out


def with_gravity(robot, gravity=None, mass=None, com=None):
    """A copy of the physical robot whose statics use other gravity (3,) m/s^2 (base frame) or mass data."""
    r = copy.copy(robot)
    if gravity is not None:
        r.gravity = np.asarray(gravity, float)
    if mass is not None:
        r.mass, r.com = np.asarray(mass, float), np.asarray(com, float)
    return r


def model_loads(world: World, q, payload) -> np.ndarray | None:
    """The loads (N, n) the MODEL's mass data and gravity give on the true geometry (the world's own statics), or
    None when the model has no masses: what a calibration that knew the geometry exactly could compute."""
    m = world.model
    if m.mass is None:
        return None
    return with_gravity(world.robot, m.gravity, m.mass, m.com).joint_loads(q, payload)


def draw_tilt(robot, rng) -> tuple:
    """A rotation vector (rad, base frame) about a random horizontal axis, TILT_DEG degrees."""
    g = robot.gravity / np.linalg.norm(robot.gravity)
    a = rng.normal(size=3)
    a -= (a @ g) * g
    a /= np.linalg.norm(a)
    return tuple(float(x) for x in np.radians(rng.uniform(*TILT_DEG)) * a)


def _candidates_34(world: World, kind: str, q, cols, rng, moving) -> list:
    """Issue 34's mechanisms on every eligible joint/link, each at a natural (to be rescaled) size."""
    r = world.robot
    n = r.n
    out = []
    payload = cols.payload_kg()
    if kind in ("play_load_sign", "two_joint_springs"):
        tau = r.joint_loads(q, payload)
        span = np.ptp(tau, axis=0)
        loaded = [j for j in range(n) if span[j] > LOADED_SHARE * max(span.max(), 1e-300)]
        if kind == "play_load_sign":
            for j in loaded:
                if PLAY_SIGN_SHARE[0] <= np.mean(tau[:, j] > 0) <= PLAY_SIGN_SHARE[1]:
                    out.append(GearPlay(j, _unit(r, j, 1e-4, 1e-2)))
        else:
            big = np.abs(tau).max(0)
            for a in loaded:
                for b in loaded:
                    if a < b:  # natural sizes; hide balances the two (_balance)
                        out.append(JointSprings((a, b), tuple(_unit(r, j, 1e-4, 1e-2) / big[j] for j in (a, b))))
    elif kind == "link_thermal_growth":
        for k in range(n):
            if not r.prismatic[k] and np.hypot(r.geometry[k, 0], r.geometry[k, 2]) >= 100.0:
                out.append(LinkGrowth(k, 1.15e-5))
    elif kind == "target_remount":
        N = len(q)
        at = int(rng.integers(int(0.3 * N), int(0.7 * N) + 1))
        v = rng.normal(size=3)
        out = [TargetStep(tuple(float(x) for x in 0.1 * v / np.linalg.norm(v)), float(cols.timestamp[at]), at)]
    elif kind in ("tilted_base_spring", "tilted_base_sag"):
        tilt = draw_tilt(r, rng)
        if kind == "tilted_base_spring":
            tilted = with_gravity(r, rotvec(np.asarray(tilt)) @ r.gravity)
            tau_t, tau_0 = tilted.joint_loads(q, payload), r.joint_loads(q, payload)
            span = np.ptp(tau_t, axis=0)
            made = np.sqrt(np.mean((tau_t - tau_0) ** 2, axis=0) / np.maximum(np.mean(tau_t**2, axis=0), 1e-300))
            rev = [j for j in moving if not r.prismatic[j]]
            pick = [j for j in rev if made[j] >= TILT_MADE_SHARE and span[j] > 0.5 * LOADED_SHARE * span.max()]
            pick = pick or [j for j in rev if span[j] > LOADED_SHARE * span.max()]
            out = [TiltedBase(tilt, (JointSpring(j, 1e-4 / np.abs(tau_t[:, j]).max()),)) for j in pick]
        else:
            o = r.frames(q).origins
            for k in range(1, n):
                if not r.prismatic[k] and np.linalg.norm(o[:, k] - o[:, k - 1], axis=1).max() >= 50.0:
                    out.append(TiltedBase(tilt, (Cantilever(k, 1e12),)))
    elif kind == "mount_compliance":
        out = [BaseTilt(1e-7, float(rng.uniform(*MOUNT_RATIO)), float(rng.uniform(0.0, 180.0)))]
    elif kind == "telescopic_sag":
        o = r.frames(q).origins
        for k in range(1, n):
            if r.prismatic[k]:
                L = np.linalg.norm(o[:, k] - o[:, k - 1], axis=1)
                if L.max() >= 50.0:
                    EI = 1e12  # the guide gives 0.3..1.5 times what the tube bends at the tip (at the mean length)
                    guide = float(rng.uniform(0.3, 1.5)) * 1000.0 * L.mean() / (3 * EI)
                    out.append(TelescopicSag(k, EI, tube_kg_per_mm=0.01, guide_compliance=guide))
    return out


def world_notes(world: World, cause, q, cols) -> dict:
    """What the drawn mechanism did at these poses, for the benchmark's analysis (issue 34's kinds)."""
    r = world.robot
    payload = cols.payload_kg()
    if isinstance(cause, GearPlay):
        j = r.names.index(cause.joints(r)[0])
        tau = r.joint_loads(q, payload)[:, j]
        tm = model_loads(world, q, payload)
        return {"true_load_positive_share": float(np.mean(tau > 0)),
                "model_side_wrong_share": None if tm is None else float(np.mean(np.sign(tm[:, j]) != np.sign(tau)))}
    if isinstance(cause, TargetStep):
        return {"at_pose": cause.at_pose, "offset_mm": float(np.linalg.norm(cause.offset_mm))}
    if isinstance(cause, TiltedBase):
        return {"tilt_deg": float(np.degrees(np.linalg.norm(cause.tilt_rad)))}
    if isinstance(cause, LinkGrowth):
        t = world.context(q, cols).temperature
        return {"temperature_range_degC": float(np.ptp(t)), "hvac": list(world.hvac or ()),
                "corr_temperature_time": float(np.corrcoef(t, cols.timestamp)[0, 1])}
    return {}


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
    temperature = kind in THERMAL_KINDS if temperature is None else temperature
    if kind == "link_thermal_growth":  # the air conditioning cycles: the temperature is not the time order
        world.hvac = (float(rng.uniform(0.8, 2.0)), float(rng.uniform(900.0, 2400.0)), float(rng.uniform(0, 2 * np.pi)))
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
        if isinstance(cause, JointSprings):  # both springs show: their unabsorbable parts 1:0.5..2 apart
            cause = _balance(world, cause, q, cols, basis, rng)
            if cause is None:
                continue
        if size_x_noise == 0:  # a no-effect draw: the mechanism's setting (tilt, temperature, payload), no size
            cause, rms = cause.scaled(0.0), 0.0
        else:
            cause, rms = size_cause(world, cause, size_x_noise * noise, q, cols, basis)
        world.hide(cause)
        out = {"kind": kind, "expected": EXPECTED[kind], "joints": cause.joints(world.robot),
               "parameters": cause.describe(world.robot), "size": size_x_noise,
               "unabsorbed_rms_mm": rms, "total_rms_mm": world.unabsorbed_rms(cause, q, cols, absorb=False),
               "noise_rms_mm": noise, "cause": cause, "q": q, "payload_kg": payload_kg,
               "temperature": temperature}
        if kind in MECHANISMS_34:
            out["notes"] = world_notes(world, cause, q, cols)
        return out
    raise ValueError(f"no joint of {world.model.name} can show {kind} observably")


def _balance(world: World, springs: JointSprings, q, cols, basis, rng, min_observable: float = 0.1):
    """The springs rescaled so that each one's unabsorbable RMS alone is 0.5..2 times the first's (drawn), or None
    when one of them alone is (nearly) absorbed by the geometry."""
    alone = [JointSprings((j,), (c,)) for j, c in zip(springs.springs, springs.compliance)]
    left = [world.unabsorbed_rms(a, q, cols, basis=basis) for a in alone]
    total = [world.unabsorbed_rms(a, q, cols, absorb=False) for a in alone]
    if not all(t > 0 and lf > min_observable * t for lf, t in zip(left, total)):
        return None
    ratio = [1.0] + [float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))) for _ in left[1:]]
    return JointSprings(springs.springs, tuple(c * r * left[0] / lf for c, r, lf in zip(springs.compliance, ratio, left)))


def null_world(model: RobotModel, seed: int | None = None, *, rng: np.random.Generator | None = None,
               outliers: int = 0, repeatability_factor: float = 2.5, **kw) -> World:
    """A world with no hidden cause but wrong masses in the model, a robot repeating 2.5x worse than
    usual (50-75 um per axis) and optionally `outliers` bad readings per campaign: nothing to find."""
    rng = np.random.default_rng(seed) if rng is None else rng
    rep = repeatability_factor * float(rng.uniform(*REPEATABILITY_RANGE_MM))
    return World(model, rng=rng, repeatability_mm=rep, outliers=outliers, **kw)
