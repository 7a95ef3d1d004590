"""Physical causes of error, each written from its own mechanics with its own parameters and units.

A cause may (1) change the geometry per pose (thermal growth), (2) move joints away from what their
encoders report (springs, gear play, transmission error, encoder scale, re-homing, cable pull),
(3) deform the structure at a place in the chain (bending links, a crooked rail, a tilting base) or
(4) move the measured point directly (tracker drift).  `simulate` applies them in that order.
Joints are given by index or name.  `scaled(f)` gives the same cause f times as strong (f = 0: none).
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .robot import PhysicalRobot, Pose, about_point, cross, inverse, rigid, rotvec


@dataclass
class Context:
    """What a cause may look at: the robot, reported joints q (N, n), time (s since the epoch), the
    physical temperature (deg C, whether logged or not), payload (kg) and the world's ambient (deg C)."""

    robot: PhysicalRobot
    q: np.ndarray
    time: np.ndarray
    temperature: np.ndarray
    payload: np.ndarray
    ambient_degC: float = 20.0
    geometry: np.ndarray | None = None  # (N, n, 5) after geometry causes
    tool: np.ndarray | None = None  # (N, 3)
    _loads: np.ndarray | None = field(default=None, repr=False)

    @property
    def N(self) -> int:
        return self.q.shape[0]

    @property
    def loads(self) -> np.ndarray:
        """True gravity + payload loads at the reported joints, (N, n) N*m or N."""
        if self._loads is None:
            self._loads = self.robot.joint_loads(self.q, self.payload, geometry=self.geometry, tool=self.tool)
        return self._loads


def joint_index(robot: PhysicalRobot, joint) -> int:
    """A joint given by index or name, as an index."""
    return robot.names.index(joint) if isinstance(joint, str) else int(joint)


@dataclass(frozen=True)
class Cause:
    """Base class: a hidden physical cause. `magnitude` names the fields that scale its strength."""

    kind = "cause"
    magnitude: ClassVar[tuple] = ()

    def geometry(self, ctx: Context, geometry: np.ndarray, tool: np.ndarray):
        return geometry, tool

    def joint_offset(self, ctx: Context) -> np.ndarray | None:
        return None

    def structure(self, ctx: Context, pose: Pose) -> list:
        """Deformations as (slot 'pre' or 'post', link index, (N, 4, 4) transform in the local frame)."""
        return []

    def cartesian(self, ctx: Context, pose: Pose) -> np.ndarray | None:
        return None

    def scaled(self, f: float) -> "Cause":
        return dataclasses.replace(self, **{k: _scale(getattr(self, k), f) for k in self.magnitude})

    def describe(self, robot: PhysicalRobot) -> dict:
        d = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in dataclasses.asdict(self).items()}
        for key in ("joint", "other"):
            if key in d and d[key] is not None:
                d[key] = robot.names[joint_index(robot, d[key])]
        return {"cause": type(self).__name__, "world_kind": self.kind, **d}

    def joints(self, robot: PhysicalRobot) -> list[str]:
        return [robot.names[joint_index(robot, getattr(self, k))] for k in ("joint", "other")
                if getattr(self, k, None) is not None]


def _scale(v, f):
    return tuple(np.asarray(v, float) * f) if isinstance(v, (tuple, list, np.ndarray)) else v * f


def _offset(ctx: Context, j: int, values: np.ndarray) -> np.ndarray:
    dq = np.zeros_like(ctx.q)
    dq[:, j] = values
    return dq


# ------------------------------------------------------------------------------------------- joints
@dataclass(frozen=True)
class JointSpring(Cause):
    """A joint's drive is a hardening spring: the load tau (N*m or N) winds it by dq (rad or mm) with
    tau = k1 dq + k3 dq^3, k1 = 1/compliance (compliance in rad/(N*m) or mm/N), k3 = stiffening * k1
    (stiffening in 1/rad^2 or 1/mm^2).  Solved per pose by Newton's method from the linear guess."""

    joint: int | str = 0
    compliance: float = 0.0
    stiffening: float = 0.0
    kind = "joint_spring"

    def scaled(self, f):
        """f times the deflection at every load: compliance x f, stiffening / f^2 (same curve shape)."""
        return dataclasses.replace(self, compliance=self.compliance * f,
                                   stiffening=self.stiffening / f**2 if f != 0 else self.stiffening)

    def deflection(self, tau) -> np.ndarray:
        """dq solving k1 dq + k3 dq^3 = tau."""
        tau = np.asarray(tau, float)
        if self.compliance == 0:
            return np.zeros_like(tau)
        k1 = 1.0 / self.compliance
        k3 = self.stiffening * k1
        x = tau / k1  # overshoots on the convex side: Newton then converges monotonically
        if k3 == 0:
            return x
        for _ in range(100):
            step = (k1 * x + k3 * x**3 - tau) / (k1 + 3 * k3 * x**2)
            x = x - step
            if np.all(np.abs(step) <= 1e-15 * np.maximum(np.abs(x), 1e-300)):
                break
        return x

    def joint_offset(self, ctx):
        j = joint_index(ctx.robot, self.joint)
        return _offset(ctx, j, self.deflection(ctx.loads[:, j]))


@dataclass(frozen=True)
class GearPlay(Cause):
    """Backlash of `play` (rad or mm, total) in a joint's gear train: gravity pushes the output against one
    flank, dq = play/2 sign(tau).  With softness > 0 (N*m or N) the joint rolls through its play
    elastically near zero load (preloaded or worn gears): dq = play/2 tanh(tau / softness)."""

    joint: int | str = 0
    play: float = 0.0
    softness: float = 0.0
    magnitude: ClassVar[tuple] = ("play",)
    kind = "gear_play"

    def joint_offset(self, ctx):
        j = joint_index(ctx.robot, self.joint)
        tau = ctx.loads[:, j]
        s = np.tanh(tau / self.softness) if self.softness > 0 else np.sign(tau)
        return _offset(ctx, j, 0.5 * self.play * s)


@dataclass(frozen=True)
class GearError(Cause):
    """Transmission error of a gear stage: dq = amplitude sin(harmonic q + phase) (rad or mm), harmonic in
    cycles per joint revolution (may be fractional, e.g. a stage's ratio); for a linear joint the cycle is
    `pitch_mm` of travel (default: the whole stroke)."""

    joint: int | str = 0
    amplitude: float = 0.0
    harmonic: float = 1.0
    phase: float = 0.0
    pitch_mm: float | None = None
    magnitude: ClassVar[tuple] = ("amplitude",)
    kind = "gear_error"

    def joint_offset(self, ctx):
        j = joint_index(ctx.robot, self.joint)
        q = ctx.q[:, j]
        if ctx.robot.prismatic[j]:
            pitch = self.pitch_mm or float(np.ptp(ctx.robot.limits[j]))
            ang = 2 * np.pi * self.harmonic * q / pitch
        else:
            ang = self.harmonic * q
        return _offset(ctx, j, self.amplitude * np.sin(ang + self.phase))


@dataclass(frozen=True)
class EncoderScale(Cause):
    """Wrong gear ratio or encoder resolution: the joint moves (1 + ratio_error) times what it reports,
    counted from where it was homed (`reference`, default the robot's home position), dimensionless."""

    joint: int | str = 0
    ratio_error: float = 0.0
    reference: float | None = None
    magnitude: ClassVar[tuple] = ("ratio_error",)
    kind = "encoder_scale"

    def joint_offset(self, ctx):
        j = joint_index(ctx.robot, self.joint)
        ref = ctx.robot.home[j] if self.reference is None else self.reference
        return _offset(ctx, j, self.ratio_error * (ctx.q[:, j] - ref))


@dataclass(frozen=True)
class ReHoming(Cause):
    """The joint was re-homed during the session: from `at_time` (s since the epoch) on, its zero is off by `step`
    (rad or mm). The time is the world's, not a share of whatever is measured: poses measured later (validation,
    compensation) see the step where the calibration saw it."""

    joint: int | str = 0
    step: float = 0.0
    at_time: float = 0.0
    magnitude: ClassVar[tuple] = ("step",)
    kind = "rehoming_step"

    @classmethod
    def within(cls, joint, step: float, share: float, times) -> "ReHoming":
        """Re-homed at `share` (0..1) of the session whose timestamps (s) are `times`."""
        t = np.asarray(times, float)
        return cls(joint, step, float(t[0] + share * (t[-1] - t[0])))

    def joint_offset(self, ctx):
        j = joint_index(ctx.robot, self.joint)
        return _offset(ctx, j, np.where(np.asarray(ctx.time, float) >= self.at_time, self.step, 0.0))


@dataclass(frozen=True)
class CableForce(Cause):
    """A dress pack routed over joint `other` at radius_mm stretches by radius |q_other - rest| beyond
    slack_mm; its tension k (N/mm) x stretch pulls on joint `joint` with lever_mm, winding it by
    compliance (rad/(N*m), or mm/N for a linear joint) times that torque (or force), always the same way."""

    joint: int | str = 0
    k: float = 0.0
    other: int | str = 1
    radius_mm: float = 60.0
    slack_mm: float = 0.0
    rest: float = 0.0
    lever_mm: float = 150.0
    compliance: float = 1e-5
    magnitude: ClassVar[tuple] = ("k",)
    kind = "cable_force"

    def joint_offset(self, ctx):
        j, o = joint_index(ctx.robot, self.joint), joint_index(ctx.robot, self.other)
        dq_o = ctx.q[:, o] - self.rest
        path = np.abs(dq_o) * (1.0 if ctx.robot.prismatic[o] else self.radius_mm)
        tension = self.k * np.maximum(path - self.slack_mm, 0.0)  # N
        load = tension if ctx.robot.prismatic[j] else tension * self.lever_mm / 1000.0
        return _offset(ctx, j, self.compliance * load)


# ------------------------------------------------------------------------------------------- structure
@dataclass(frozen=True)
class Cantilever(Cause):
    """The link from joint `joint`-1's frame to joint `joint`'s frame (its CURRENT length: a telescopic stage
    grows with its prismatic joint) is an Euler-Bernoulli cantilever of stiffness EI (N*mm^2), clamped at
    its root.  Loads: the weight of every body beyond (each at its COM's station along the beam, with the
    moment of its offset), the payload at the tool point, and own_mass_kg spread evenly (default: the
    mass of the body carrying the segment, none for a telescopic stage whose tube is a distal body).
    Point force P at station s: tip deflection P s^2 (3L - s) / 6EI, rotation P s^2 / 2EI; point moment M
    at s: M s (2L - s) / 2EI and M s / EI; uniform weight W: W L^3 / 8EI and W L^2 / 6EI.  Everything
    beyond the tip moves rigidly with it, so the tool's lever arm turns the tip rotation into displacement."""

    joint: int | str = 1
    EI: float = np.inf
    own_mass_kg: float | None = None
    kind = "cantilever"

    def scaled(self, f):
        return dataclasses.replace(self, EI=self.EI / f if f != 0 else np.inf)

    def tip(self, ctx: Context, pose: Pose):
        """Tip deflection (N, 3) mm and tip rotation vector (N, 3) rad in the tracker frame, tip point, root."""
        r = ctx.robot
        k = joint_index(r, self.joint)
        if k < 1:
            raise ValueError("a cantilever needs a link before its joint (joint index >= 1)")
        root = pose.origins[:, k - 1]
        tip = pose.origins[:, k]
        L = np.linalg.norm(tip - root, axis=1)
        u = (tip - root) / np.maximum(L, 1e-12)[:, None]
        c = 1.0 / self.EI
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], r.gravity)
        perp = lambda v: v - (v * u).sum(-1, keepdims=True) * u  # noqa: E731
        com = r.body_coms(pose)
        pts = np.concatenate([com[:, k:], pose.point[:, None]], axis=1)  # (N, m, 3)
        mass = np.concatenate([np.broadcast_to(r.mass[k:], (ctx.N, r.n - k)), ctx.payload[:, None]], axis=1)
        F = mass[..., None] * g[:, None]  # N
        s = np.clip(((pts - root[:, None]) * u[:, None]).sum(-1), 0.0, L[:, None])  # station along the beam
        M = cross(pts - (root[:, None] + s[..., None] * u[:, None]), F)  # N*mm, the offset's moment
        uu = u[:, None]
        Fp = F - (F * uu).sum(-1, keepdims=True) * uu
        Mp = M - (M * uu).sum(-1, keepdims=True) * uu
        L1, s1 = L[:, None, None], s[..., None]
        defl = (Fp * s1**2 * (3 * L1 - s1) / 6 + cross(Mp, uu) * s1 * (2 * L1 - s1) / 2).sum(1) * c
        turn = (cross(uu, Fp) * s1**2 / 2 + Mp * s1).sum(1) * c
        own = self.own_weight_kg(r, k, L)  # a number, or (N,) per pose
        W = perp((own[:, None] if np.ndim(own) else own) * np.broadcast_to(g, (ctx.N, 3)))
        defl = defl + W * L[:, None] ** 3 / 8 * c
        turn = turn + cross(u, W) * L[:, None] ** 2 / 6 * c
        return defl, turn, tip, root

    def own_weight_kg(self, robot: PhysicalRobot, k: int, length_mm: np.ndarray):
        """The beam's own mass (kg) spread evenly along it: own_mass_kg, by default the body carrying it."""
        if self.own_mass_kg is not None:
            return self.own_mass_kg
        return 0.0 if robot.prismatic[k] else robot.mass[k - 1]

    def structure(self, ctx, pose):
        if not np.isfinite(self.EI):
            return []
        k = joint_index(ctx.robot, self.joint)
        defl, turn, tip, _ = self.tip(ctx, pose)
        D = about_point(turn, tip, defl)  # tracker frame: turn about the tip, then shift by the deflection
        F = pose.frames[:, k - 1]
        return [("pre", k, inverse(F) @ D @ F)]


@dataclass(frozen=True)
class BaseTilt(Cause):
    """The mounting gives under the robot's overturning moment: the base turns about its origin by
    compliance (rad/(N*m)) x the horizontal part of sum m (com - base) x g (robot bodies and payload),
    counted from the moment with the robot parked at home without payload (when the base was levelled).
    A platform on wheels or springs is stiffer one way: about the horizontal axis `axis_deg` from the base's x
    (turned about gravity) the compliance is `compliance`, about the one across it `compliance / ratio`."""

    compliance: float = 0.0
    ratio: float = 1.0
    axis_deg: float = 0.0
    magnitude: ClassVar[tuple] = ("compliance",)
    kind = "base_tilt"

    def turn(self, robot: PhysicalRobot, pose: Pose, M: np.ndarray) -> np.ndarray:
        """(N, 3) rad, tracker frame: the mount's turn under the horizontal moment M (N, 3) N*m."""
        if self.ratio == 1.0:
            return self.compliance * M
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], robot.gravity / np.linalg.norm(robot.gravity))
        u = pose.base[:, :3, 0] - (pose.base[:, :3, 0] * g).sum(1, keepdims=True) * g
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        w = cross(g, u)
        a = np.radians(self.axis_deg)
        soft, stiff = np.cos(a) * u + np.sin(a) * w, -np.sin(a) * u + np.cos(a) * w
        return self.compliance * ((M * soft).sum(1, keepdims=True) * soft
                                  + (M * stiff).sum(1, keepdims=True) * stiff / self.ratio)

    @staticmethod
    def moment(robot: PhysicalRobot, pose: Pose, payload) -> np.ndarray:
        """Horizontal overturning moment (N, 3) N*m about the base origin, tracker frame."""
        o = pose.base[:, :3, 3]
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], robot.gravity)
        com = robot.body_coms(pose)
        M = (robot.mass[None, :, None] * cross(com - o[:, None], g[:, None])).sum(1)
        M += np.asarray(payload, float)[:, None] * cross(pose.point - o, g)
        M /= 1000.0
        gh = g / np.linalg.norm(g, axis=1, keepdims=True)
        return M - (M * gh).sum(1, keepdims=True) * gh

    def structure(self, ctx, pose):
        if self.compliance == 0:
            return []
        r = ctx.robot
        M = self.moment(r, pose, ctx.payload) - self.moment(r, r.frames(r.home), [0.0])
        D = about_point(self.turn(r, pose, M), pose.base[:, :3, 3])
        return [("pre", 0, inverse(pose.base) @ D @ pose.base)]


@dataclass(frozen=True)
class ElasticBearings(Cause):
    """The bearings of several joints give under the bending moment across their axes (an elastic arm, like
    DLR's Agile Justin): at each joint in `bearings` everything beyond turns about the joint's axis point by
    the rotation vector compliance (rad/(N*m)) x the part of the gravity + payload moment there (N*m, the
    world's true masses) that is perpendicular to the joint axis."""

    bearings: tuple = ()
    compliance: tuple = ()
    magnitude: ClassVar[tuple] = ("compliance",)
    kind = "elastic_bearings"

    def joints(self, robot):
        return [robot.names[joint_index(robot, j)] for j in self.bearings]

    def describe(self, robot):
        return {"cause": type(self).__name__, "world_kind": self.kind, "bearings": self.joints(robot),
                "compliance": list(self.compliance)}

    def structure(self, ctx, pose):
        r = ctx.robot
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], r.gravity)
        com = r.body_coms(pose)
        out = []
        for j, c in zip(self.bearings, self.compliance):
            k = joint_index(r, j)
            at, z = pose.axis_points[:, k], pose.axes[:, k]
            M = (r.mass[None, k:, None] * cross(com[:, k:] - at[:, None], g[:, None])).sum(1)
            M = (M + np.asarray(ctx.payload, float)[:, None] * cross(pose.point - at, g)) / 1000.0
            across = M - (M * z).sum(1, keepdims=True) * z
            D = about_point(c * across, at)
            F = pose.frames[:, k - 1] if k > 0 else pose.base
            out.append(("pre", k, inverse(F) @ D @ F))
        return out


@dataclass(frozen=True)
class RailStraightness(Cause):
    """A linear axis whose guide is not straight: the carriage of prismatic joint `joint` sits
    sag_mm sin(pi waves s + phase) sideways (s = 0..1 along the stroke), in the direction `direction`
    (rad, in the joint frame's x-y plane), and, riding on it, turns by the guide's slope (rad) when
    follow=True (carriage wheels on a curved rail)."""

    joint: int | str = 0
    sag_mm: float = 0.0
    waves: float = 1.0
    phase: float = 0.0
    direction: float = 0.0
    follow: bool = True
    magnitude: ClassVar[tuple] = ("sag_mm",)
    kind = "rail_straightness"

    def structure(self, ctx, pose):
        r = ctx.robot
        j = joint_index(r, self.joint)
        if not r.prismatic[j]:
            raise ValueError(f"{r.names[j]} is not a linear axis")
        lo, hi = r.limits[j]
        span = hi - lo
        s = (ctx.q[:, j] - lo) / span
        w = np.pi * self.waves
        e = self.sag_mm * np.sin(w * s + self.phase)  # mm sideways
        slope = self.sag_mm * w / span * np.cos(w * s + self.phase)  # rad
        lat = np.array([np.cos(self.direction), np.sin(self.direction), 0.0])
        t = e[:, None] * lat
        turn = (slope if self.follow else 0.0 * slope)[:, None] * np.cross([0.0, 0.0, 1.0], lat)
        return [("post", j, rigid(rotvec(turn), t))]


# ------------------------------------------------------------------------------------------- geometry / cartesian
@dataclass(frozen=True)
class ThermalGrowth(Cause):
    """Warming steel: every link length (a and d) and the tool grow by coeff_per_degC (1/deg C) x the rise
    of the physical temperature above `reference_degC` (default the world's ambient at the start), and the
    tracker stand drifts by drift_mm_per_degC (3,) mm/deg C in the tracker frame."""

    coeff_per_degC: float = 0.0
    drift_mm_per_degC: tuple = (0.0, 0.0, 0.0)
    reference_degC: float | None = None
    magnitude: ClassVar[tuple] = ("coeff_per_degC", "drift_mm_per_degC")
    kind = "thermal_growth"

    def _rise(self, ctx):
        return ctx.temperature - (ctx.ambient_degC if self.reference_degC is None else self.reference_degC)

    def geometry(self, ctx, geometry, tool):
        grow = 1.0 + self.coeff_per_degC * self._rise(ctx)
        geometry = geometry.copy()
        geometry[..., 0] *= grow[:, None]
        geometry[..., 2] *= grow[:, None]
        return geometry, tool * grow[:, None]

    def cartesian(self, ctx, pose):
        return self._rise(ctx)[:, None] * np.asarray(self.drift_mm_per_degC, float)


@dataclass(frozen=True)
class GrossOutliers:
    """Wrong readings on `count` poses (an SMR re-seated badly, a beam break caught mid-move): each
    is off by size_mm (uniform in the range) in a random direction.  Poses and errors follow `seed`."""

    count: int = 0
    size_mm: tuple = (0.5, 3.0)
    seed: int = 0

    def draw(self, N: int) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the bad poses, (N, 3) mm error to add)."""
        rng = np.random.default_rng(self.seed)
        idx = np.sort(rng.choice(N, min(self.count, N), replace=False))
        d = rng.normal(size=(len(idx), 3))
        d *= rng.uniform(*self.size_mm, len(idx))[:, None] / np.linalg.norm(d, axis=1, keepdims=True)
        out = np.zeros((N, 3))
        out[idx] = d
        return idx, out


# ------------------------------------------------------------------------------------------- issue 34's mechanisms
@dataclass(frozen=True)
class JointSprings(Cause):
    """Several joints' drives are linear springs, the others stiff: each joint in `springs` winds by its
    compliance (rad/(N*m) or mm/N) x the true gravity + payload load it carries (the world's statics)."""

    springs: tuple = ()
    compliance: tuple = ()
    magnitude: ClassVar[tuple] = ("compliance",)
    kind = "joint_springs"

    def joints(self, robot):
        return [robot.names[joint_index(robot, j)] for j in self.springs]

    def describe(self, robot):
        return {"cause": type(self).__name__, "world_kind": self.kind, "springs": self.joints(robot),
                "compliance": [float(c) for c in self.compliance]}

    def joint_offset(self, ctx):
        dq = np.zeros_like(ctx.q)
        for j, c in zip(self.springs, self.compliance):
            k = joint_index(ctx.robot, j)
            dq[:, k] += c * ctx.loads[:, k]
        return dq


@dataclass(frozen=True)
class LinkGrowth(Cause):
    """One link warms and grows along its length only: the segment from joint `joint`-1's frame to joint `joint`'s
    frame (its MD-H a and d, the frame's turn untouched) lengthens by coeff_per_degC (1/deg C) x the rise of the
    physical temperature above `reference_degC` (default the world's ambient at the start).  No other link,
    the tool or the tracker moves with the temperature."""

    joint: int | str = 1
    coeff_per_degC: float = 0.0
    reference_degC: float | None = None
    magnitude: ClassVar[tuple] = ("coeff_per_degC",)
    kind = "link_growth"

    def joints(self, robot):
        return []  # a thermal cause: the contract's thermal_drift names no joint (the link is in `describe`)

    def describe(self, robot):
        return {**super().describe(robot), "link": robot.names[joint_index(robot, self.joint)]}

    def geometry(self, ctx, geometry, tool):
        k = joint_index(ctx.robot, self.joint)
        rise = ctx.temperature - (ctx.ambient_degC if self.reference_degC is None else self.reference_degC)
        grow = 1.0 + self.coeff_per_degC * rise
        geometry = geometry.copy()
        geometry[:, k, 0] *= grow
        geometry[:, k, 2] *= grow
        return geometry, tool


@dataclass(frozen=True)
class TargetStep(Cause):
    """The target (SMR nest or tool) was taken off and re-mounted during the campaign: from `at_time` (s since the
    epoch; the time of pose `at_pose` in time order) on, the measured point sits `offset_mm` (3,) further in the
    last joint's frame.  Nothing else changes."""

    offset_mm: tuple = (0.0, 0.0, 0.0)
    at_time: float = 0.0
    at_pose: int = 0
    magnitude: ClassVar[tuple] = ("offset_mm",)
    kind = "target_step"

    def after(self, ctx) -> np.ndarray:
        """(N,) True at poses measured at or after the re-mount."""
        return np.asarray(ctx.time, float) >= self.at_time

    def geometry(self, ctx, geometry, tool):
        return geometry, tool + self.after(ctx)[:, None] * np.asarray(self.offset_mm, float)


@dataclass(frozen=True)
class TiltedBase(Cause):
    """The robot stands on a base that is not level (or is mounted inclined while its model says upright):
    gravity's true direction is turned by the rotation vector `tilt_rad` (3,) in the base frame against the
    robot's.  Kinematically invisible (the tracker frame absorbs a rigid tilt); it shows only through the
    compliant causes it `carries` (springs, bending links), which then work under the tilted gravity."""

    tilt_rad: tuple = (0.0, 0.0, 0.0)
    carries: tuple = ()
    kind = "tilted_base"

    def scaled(self, f):
        """The carried compliance f times as large; the tilt stays (it is geometry, not a magnitude)."""
        return dataclasses.replace(self, carries=tuple(c.scaled(f) for c in self.carries))

    def tilted(self, ctx: Context) -> Context:
        """The same context on the robot with gravity turned by the tilt (loads recomputed)."""
        r = copy.copy(ctx.robot)
        r.gravity = rotvec(np.asarray(self.tilt_rad, float)) @ ctx.robot.gravity
        return dataclasses.replace(ctx, robot=r, _loads=None)

    def joints(self, robot):
        return [j for c in self.carries for j in c.joints(robot)]

    def describe(self, robot):
        return {"cause": type(self).__name__, "world_kind": self.kind, "tilt_rad": [float(t) for t in self.tilt_rad],
                "tilt_deg": float(np.degrees(np.linalg.norm(self.tilt_rad))),
                "carries": [c.describe(robot) for c in self.carries]}

    def joint_offset(self, ctx):
        offs = [o for o in (c.joint_offset(self.tilted(ctx)) for c in self.carries) if o is not None]
        return sum(offs) if offs else None

    def structure(self, ctx, pose):
        t = self.tilted(ctx)
        return [s for c in self.carries for s in c.structure(t, pose)]


@dataclass(frozen=True)
class TelescopicSag(Cantilever):
    """A telescopic stage (prismatic joint `joint`): its inner tube, out by the joint's CURRENT length, is a
    cantilever of stiffness EI (N*mm^2) clamped in the outer tube's guide, weighing tube_kg_per_mm along the
    length that is out (heavier the further out), loaded by the bodies beyond and the payload at the tool.  The
    guide's bearings give too: the tube turns about its root by guide_compliance (rad/(N*m)) x the bending
    moment there (the part across the tube), carrying the bent beam with it."""

    tube_kg_per_mm: float = 0.0
    guide_compliance: float = 0.0
    kind = "telescopic_sag"

    def scaled(self, f):
        return dataclasses.replace(self, EI=self.EI / f if f != 0 else np.inf,
                                   guide_compliance=self.guide_compliance * f)

    def own_weight_kg(self, robot, k, length_mm):
        return self.tube_kg_per_mm * np.asarray(length_mm, float)

    def root_moment(self, ctx: Context, pose: Pose) -> np.ndarray:
        """Bending moment (N, 3) N*m across the tube at its root, tracker frame: every body beyond, the payload
        and the tube's own weight (at the middle of the length that is out)."""
        r = ctx.robot
        k = joint_index(r, self.joint)
        root, tip = pose.origins[:, k - 1], pose.origins[:, k]
        L = np.linalg.norm(tip - root, axis=1)
        u = (tip - root) / np.maximum(L, 1e-12)[:, None]
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], r.gravity)
        com = r.body_coms(pose)
        M = (r.mass[None, k:, None] * cross(com[:, k:] - root[:, None], g[:, None])).sum(1)
        M += np.asarray(ctx.payload, float)[:, None] * cross(pose.point - root, g)
        M += (self.tube_kg_per_mm * L)[:, None] * cross(0.5 * L[:, None] * u, g)
        M /= 1000.0
        return M - (M * u).sum(1, keepdims=True) * u

    def structure(self, ctx, pose):
        if not np.isfinite(self.EI) and self.guide_compliance == 0:
            return []
        k = joint_index(ctx.robot, self.joint)
        defl, turn, tip, root = self.tip(ctx, pose)
        D = about_point(turn, tip, defl)
        if self.guide_compliance:
            D = about_point(self.guide_compliance * self.root_moment(ctx, pose), root) @ D
        F = pose.frames[:, k - 1]
        return [("pre", k, inverse(F) @ D @ F)]


# ------------------------------------------------------------------------------------------- apply
def simulate(robot: PhysicalRobot, causes, ctx: Context) -> np.ndarray:
    """Where the physical robot puts the tool point (N, 3) mm, tracker frame, with the given causes."""
    N, n = ctx.q.shape
    geo = np.broadcast_to(robot.geometry, (N, n, 5)).copy()
    tool = np.broadcast_to(robot.tool, (N, 3)).copy()
    for c in causes:
        geo, tool = c.geometry(ctx, geo, tool)
    ctx.geometry, ctx.tool = geo, tool
    dq = np.zeros((N, n))
    for c in causes:
        off = c.joint_offset(ctx)
        if off is not None:
            dq = dq + off
    pose = robot.frames(ctx.q, dq, geometry=geo, tool=tool)
    slots = {"pre": {}, "post": {}}
    for c in causes:
        for slot, k, T in c.structure(ctx, pose):
            d = slots[slot]
            d[k] = d[k] @ T if k in d else T
    if slots["pre"] or slots["post"]:
        pose = robot.frames(ctx.q, dq, geometry=geo, tool=tool, pre=slots["pre"], post=slots["post"])
    p = pose.point.copy()
    for c in causes:
        dp = c.cartesian(ctx, pose)
        if dp is not None:
            p = p + dp
    return p
