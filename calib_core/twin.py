"""The digital twin: a physical robot that differs from its nominal model, measured by a laser tracker.

Geometric errors are drawn at the magnitudes of Wang et al. 2023, Table 4 (lengths ~10 mm, angles
~8 mrad RMS), the tracker frame is an arbitrary rigid pose, the tool point is off by millimetres,
and every measurement carries repeatability noise and tracker noise (15 um + 6 um/m).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from . import kinematics as K
from .effects import Basis, Context, Effect, apply
from .identifiability import analyse
from .identify import tracker_sigma_mm
from .io import Measurements
from .model import RobotModel

LENGTH_ERROR_MM = 10.0
ANGLE_ERROR_RAD = 0.008
"""RMS of the geometric errors in Wang et al. 2023, Table 4 (12.8 mm, 8.5 mrad), rounded."""


def identifiable_mask(model: RobotModel, n_poses: int = 400, seed: int = 0) -> np.ndarray:
    """Which parameters are independent on a rich random pose set (the twin's minimal parameterisation)."""
    q = sample_uniform(model, n_poses, np.random.default_rng(seed))
    x = K.nominal_vector(model)
    J = K.Chain(model, x, q).jacobian().reshape(-1, len(x))
    mask = np.zeros(len(x), bool)
    mask[analyse(J, K.parameter_names(model)).identifiable] = True
    return mask


def sample_uniform(model: RobotModel, n: int, rng: np.random.Generator, margin: float = 0.05) -> np.ndarray:
    """n joint vectors (internal units) uniform within the limits, `margin` of each range kept clear."""
    lo, hi = model.limits[:, 0].copy(), model.limits[:, 1].copy()
    inf = ~np.isfinite(lo) | ~np.isfinite(hi)
    lo[inf], hi[inf] = -np.pi, np.pi
    span = hi - lo
    return lo + span * (margin + (1 - 2 * margin) * rng.random((n, model.n_joints)))


class Twin:
    """A simulated physical robot and tracker; `measure` returns contract-ready Measurements."""

    def __init__(
        self,
        model: RobotModel,
        seed: int | None = None,
        *,
        error_scale: float = 1.0,
        tool_error_mm: float = 5.0,
        repeatability_mm: float = 0.02,
        tracker_noise: bool = True,
        all_parameters: bool = False,
    ):
        """error_scale multiplies the Table 4 magnitudes; all_parameters puts errors on redundant
        parameters too (physically more honest, but then only predictions, not values, can be compared)."""
        self.model = model
        self.rng = np.random.default_rng(seed)
        rng = self.rng
        x = K.nominal_vector(model)
        P = len(x)
        n = model.n_joints
        mask = np.ones(P, bool) if all_parameters else identifiable_mask(model)
        mask[5 * n:] = False  # base and tool are drawn below
        err = np.where(K.angular_mask(model), ANGLE_ERROR_RAD, LENGTH_ERROR_MM) * error_scale
        x[mask] += rng.normal(0.0, err[mask])
        x[5 * n + 6:] += rng.normal(0.0, tool_error_mm, 3)
        x[5 * n: 5 * n + 3] = rng.uniform(-3000.0, 3000.0, 3)  # tracker a few metres from the robot
        self.R0 = Rotation.random(random_state=rng).as_matrix()
        self.x_true = x
        self.repeatability_mm = repeatability_mm
        self.tracker_noise = tracker_noise
        self.effects: list[tuple[Effect, np.ndarray]] = []
        self.start_time = 1_793_700_000.0  # a campaign start (2026-11-02), 20 s per pose

    def hide(self, effect: Effect, values) -> None:
        """Give the physical robot an effect the calibration does not know about."""
        self.effects.append((effect, np.asarray(values, float)))

    def columns(self, joints: np.ndarray, payload_kg=None, temperature: bool = False) -> Measurements:
        """The non-positional columns of a measurement campaign: time, optional warming and payload."""
        N = len(joints)
        t = self.start_time + 20.0 * np.arange(N)
        payload = None if payload_kg is None else np.asarray(
            self.rng.choice(np.atleast_1d(payload_kg), N) if np.ndim(payload_kg) else np.full(N, payload_kg), float)
        temp = 20.0 + 6.0 * (1 - np.exp(-(t - t[0]) / 5400.0)) if temperature else None
        return Measurements(joints=joints, points=np.zeros((N, 3)), timestamp=t, temperature=temp, payload=payload)

    def displacement(self, joints: np.ndarray, columns: Measurements | None = None) -> np.ndarray:
        """What the hidden effects add to the tool point at these poses, (N, 3) mm."""
        meas = columns or self.columns(joints)
        return self._true(meas) - self.true_points(joints)

    def _true(self, meas: Measurements) -> np.ndarray:
        q = meas.joints
        if not self.effects:
            return K.forward(self.model, self.x_true, q, self.R0)
        ctx = Context(self.model, K.Chain(self.model, self.x_true, q, self.R0), meas)
        dq, dp = apply([e for e, _ in self.effects], [v for _, v in self.effects], ctx)
        return K.forward(self.model, self.x_true, q + dq, self.R0) + dp

    def unexplained_rms(self, effect: Effect, values, meas: Measurements, absorb: bool = True) -> float:
        """RMS (mm) of the part of an effect's displacement that no geometric parameter can absorb
        (all of it with absorb=False)."""
        ctx = Context(self.model, K.Chain(self.model, self.x_true, meas.joints, self.R0), meas)
        dq, dp = apply([effect], [np.asarray(values, float)], ctx)
        d = (np.einsum("nij,nj->ni", ctx.chain.joint_jacobian(), dq) + dp).ravel()
        J = ctx.chain.jacobian().reshape(len(d), -1)
        rest = d - J @ np.linalg.lstsq(J, d, rcond=None)[0] if absorb else d
        return float(np.sqrt(np.mean((rest.reshape(-1, 3) ** 2).sum(1))))

    def hide_scaled(self, effect: Effect, direction, n_noise: float, meas: Measurements) -> np.ndarray:
        """Hide `effect` along `direction` sized so its unexplainable RMS is n_noise times the noise RMS."""
        direction = np.asarray(direction, float)
        unit = self.unexplained_rms(effect, direction, meas)
        values = direction * n_noise * self.noise_rms_mm(meas.points if meas.points.any() else
                                                         self.true_points(meas.joints)) / unit
        self.hide(effect, values)
        return values
    def true_points(self, joints: np.ndarray) -> np.ndarray:
        """Where the physical robot puts the tool point, mm in the tracker frame, without noise."""
        return K.forward(self.model, self.x_true, joints, self.R0)

    def sample_joints(self, n: int) -> np.ndarray:
        return sample_uniform(self.model, n, self.rng)

    def measure(self, joints: np.ndarray | None = None, n: int = 150, payload_kg=None,
                temperature: bool = False) -> Measurements:
        """Measure the physical robot at `joints` (internal units) or at n random poses.

        payload_kg: None (no column), a value, or a list to draw from per pose; temperature adds a
        warming-up temperature column. Every campaign has timestamps."""
        q = self.sample_joints(n) if joints is None else np.asarray(joints, float)
        meas = self.columns(q, payload_kg, temperature)
        p = self._true(meas)
        N = len(q)
        p = p + self.rng.normal(0.0, self.repeatability_mm, (N, 3))
        if self.tracker_noise:
            p = p + self.rng.normal(0.0, 1.0, (N, 3)) * tracker_sigma_mm(p)[:, None]
        meas.points = p
        meas.point_ids = [f"P{i + 1:04d}" for i in range(N)]
        return meas

    def noise_rms_mm(self, points_mm: np.ndarray) -> float:
        """Expected RMS 3-D distance of a perfect model to measurements at these points (noise only)."""
        tracker = tracker_sigma_mm(points_mm) ** 2 if self.tracker_noise else 0.0
        return float(np.sqrt(3 * np.mean(self.repeatability_mm**2 + tracker)))


@dataclass(frozen=True)
class BaseSway(Effect):
    """Off-vocabulary cause for blind tests: the tool point sways with one joint's angle (cable drag, a
    soft foundation), 1st and 2nd harmonic in two fixed directions. No named cause of the diagnosis has
    this shape, so it must come out as `unexplained`."""

    kind = "base_sway"

    def parameter_names(self, model):
        return ["sway.a1", "sway.a2"]

    def parameter_units(self, model):
        return ["mm", "mm"]

    def basis(self, ctx: Context) -> Basis:
        q = ctx.meas.joints[:, self.joints[0]]
        cart = np.zeros((len(q), 3, 2))
        cart[:, :, 0] = np.sin(q + 0.3)[:, None] * np.array([1.0, 0.0, 0.5])
        cart[:, :, 1] = np.cos(2 * q - 0.5)[:, None] * np.array([0.0, 1.0, -0.3])
        return Basis(None, cart, q, "joint angle (rad)")


HIDDEN_KINDS = ("joint_compliance", "link_deflection", "cyclic_joint_error", "backlash", "joint_scale",
                "axis_straightness", "thermal_drift", "unexplained")


def draw_hidden_effect(twin: "Twin", kind: str, n_noise: float, joints: np.ndarray, rng: np.random.Generator,
                       min_observable: float = 0.2) -> tuple[Effect, np.ndarray]:
    """Hide one effect of `kind` on a randomly drawn eligible joint, in a random direction, sized so that
    its part no geometric parameter can absorb is n_noise x the noise RMS. Returns (effect, values)."""
    from .effects import candidates

    meas = twin.columns(joints, temperature=kind == "thermal_drift")
    if kind == "unexplained":
        pool = [BaseSway((j,)) for j in range(twin.model.n_joints) if not twin.model.prismatic[j]]
    else:
        pool = [e for e in candidates(twin.model, meas)[0] if e.kind == kind]
    rng.shuffle(pool)
    for effect in pool:
        k = len(effect.parameter_names(twin.model))
        direction = rng.normal(size=k)
        if kind == "thermal_drift":
            direction[3] *= 1e-3  # strain per degree against mm per degree: comparable sizes
        direction /= np.linalg.norm(direction)
        total = twin.unexplained_rms(effect, direction, meas, absorb=False)
        if total > 0 and twin.unexplained_rms(effect, direction, meas) > min_observable * total:
            return effect, twin.hide_scaled(effect, direction, n_noise, meas)
    raise ValueError(f"no joint of {twin.model.name} can show {kind}")
