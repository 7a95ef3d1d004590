"""The geometric digital twin: a rigid robot that differs from its nominal model, measured by a laser tracker.

Geometric errors are drawn at the magnitudes of Wang et al. 2023, Table 4 (lengths ~10 mm, angles
~8 mrad RMS), the tracker frame is an arbitrary rigid pose, the tool point is off by millimetres,
and every measurement carries repeatability noise and tracker noise (15 um + 6 um/m).

It has no hidden effects, on purpose: it shares the calibration's own kinematics, so it can only test the
identification and the compensation of the geometry.  Hidden physical causes live in the independent
world `calib_world` (its own kinematics, statics and noise), which is what the diagnosis is tested on.
"""
from __future__ import annotations

import numpy as np

from . import kinematics as K
from .identifiability import analyse, model_order
from .instruments import INSTRUMENTS
from .io import Measurements
from .model import RobotModel

tracker_sigma_mm = INSTRUMENTS["laser_tracker"].sigma_mm

LENGTH_ERROR_MM = 10.0
ANGLE_ERROR_RAD = 0.008
"""RMS of the geometric errors in Wang et al. 2023, Table 4 (12.8 mm, 8.5 mrad), rounded."""


def identifiable_mask(model: RobotModel, n_poses: int = 400, seed: int = 0) -> np.ndarray:
    """Which parameters are independent on a rich random pose set (the twin's minimal parameterisation)."""
    q = sample_uniform(model, n_poses, np.random.default_rng(seed))
    x = K.nominal_vector(model)
    J = K.Chain(model, x, q, labels=all_targets(model, n_poses)).jacobian().reshape(-1, len(x))
    mask = np.zeros(len(x), bool)
    names = K.parameter_names(model)
    mask[analyse(J, names, model_order(model, names)).identifiable] = True
    return mask


def all_targets(model: RobotModel, n_poses: int) -> K.Labels | None:
    """Pose i measures target i mod T (one setup): every target in turn; None for one target."""
    if model.n_targets == 1:
        return None
    return K.Labels(np.arange(n_poses) % model.n_targets, np.zeros(n_poses, int))


def sample_uniform(model: RobotModel, n: int, rng: np.random.Generator, margin: float = 0.05) -> np.ndarray:
    """n row-value vectors (internal units): the actuated joints uniform within their limits (`margin` of each
    range kept clear), coupled rows following them, fixed rows 0."""
    act = model.actuated
    lo, hi = model.limits[act, 0].copy(), model.limits[act, 1].copy()
    inf = ~np.isfinite(lo) | ~np.isfinite(hi)
    lo[inf], hi[inf] = -np.pi, np.pi
    span = hi - lo
    return model.expand_joints(lo + span * (margin + (1 - 2 * margin) * rng.random((n, len(act)))))


class Twin:
    """A simulated rigid robot and tracker; `measure` returns contract-ready Measurements."""

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
        from scipy.spatial.transform import Rotation  # here: 0.15 s of import that the API process skips

        self.model = model
        self.rng = np.random.default_rng(seed)
        rng = self.rng
        x = K.nominal_vector(model)
        P = len(x)
        lay = K.layout(model)
        mask = np.ones(P, bool) if all_parameters else identifiable_mask(model)
        mask[lay.bases.start:] = False  # base and tool are drawn below
        err = np.where(K.angular_mask(model), ANGLE_ERROR_RAD, LENGTH_ERROR_MM) * error_scale
        x[mask] += rng.normal(0.0, err[mask])
        x[lay.tools] += rng.normal(0.0, tool_error_mm, 3 * model.n_targets)
        x[lay.bases.start: lay.bases.start + 3] = rng.uniform(-3000.0, 3000.0, 3)  # tracker a few metres away
        self.R0 = Rotation.random(random_state=rng).as_matrix()
        self.x_true = x
        self.repeatability_mm = repeatability_mm
        self.tracker_noise = tracker_noise
        self.start_time = 1_793_700_000.0  # a campaign start (2026-11-02), 20 s per pose

    def columns(self, joints: np.ndarray, payload_kg=None, temperature: bool = False) -> Measurements:
        """The non-positional columns of a measurement campaign: time, optional warming and payload."""
        N = len(joints)
        t = self.start_time + 20.0 * np.arange(N)
        payload = None if payload_kg is None else np.asarray(
            self.rng.choice(np.atleast_1d(payload_kg), N) if np.ndim(payload_kg) else np.full(N, payload_kg), float)
        temp = 20.0 + 6.0 * (1 - np.exp(-(t - t[0]) / 5400.0)) if temperature else None
        labels = all_targets(self.model, N)
        return Measurements(joints=joints, points=np.zeros((N, 3)), timestamp=t, temperature=temp, payload=payload,
                            target=None if labels is None else labels.target)

    def true_points(self, joints: np.ndarray, labels: K.Labels | None = None) -> np.ndarray:
        """Where the physical robot puts the targets, mm in the tracker frame, without noise."""
        return K.forward(self.model, self.x_true, joints, self.R0, labels)

    def sample_joints(self, n: int) -> np.ndarray:
        return sample_uniform(self.model, n, self.rng)

    def measure(self, joints: np.ndarray | None = None, n: int = 150, payload_kg=None,
                temperature: bool = False) -> Measurements:
        """Measure the physical robot at `joints` (internal units) or at n random poses.

        payload_kg: None (no column), a value, or a list to draw from per pose; temperature adds a
        warming-up temperature column (the rigid twin logs them but is not affected by them). Every
        campaign has timestamps."""
        q = self.sample_joints(n) if joints is None else np.asarray(joints, float)
        meas = self.columns(q, payload_kg, temperature)
        p = self.true_points(q, meas.labels)
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
