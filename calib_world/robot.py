"""The physical robot of the simulated world: its true geometry and masses, its own kinematics and statics.

Nothing here comes from the diagnosis.  Forward kinematics multiplies per-pose (N, 4, 4) homogeneous
matrices of the MD-H elementary motions; gravity loads sum m (com - axis point) x g over the bodies
beyond each joint.  Units: lengths mm, angles rad, masses kg, gravity m/s^2, torques N*m, forces N.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from calib_core.model import RobotModel

LENGTH_ERROR_MM = 10.0
"""RMS of a true MD-H length against its nominal value (mm)."""
ANGLE_ERROR_RAD = 0.008
"""RMS of a true MD-H angle against its nominal value (rad)."""
MASS_ERROR = 0.15
"""Relative 1-sigma error of the model's masses (the true mass is m (1 + 0.15 z))."""
COM_SHIFT_MM = 30.0
"""How far (mm) each true centre of mass sits from the model's, in a random direction."""
INVENTED_KG_PER_MM = 0.04
INVENTED_KG_PER_JOINT = 5.0
"""Masses invented for a model without any: 40 kg per metre of link plus a 5 kg drive per joint."""


# ---------------------------------------------------------------------------------------- 4x4 algebra
def eye4(shape=()) -> np.ndarray:
    """Identity homogeneous transforms of the given batch shape, (..., 4, 4)."""
    return np.broadcast_to(np.eye(4), tuple(shape) + (4, 4)).copy()


def rot(axis: int, angle) -> np.ndarray:
    """Rotation by `angle` (rad, any shape) about x (0), y (1) or z (2) as (..., 4, 4)."""
    angle = np.asarray(angle, float)
    T = eye4(angle.shape)
    c, s = np.cos(angle), np.sin(angle)
    i, k = [(1, 2), (2, 0), (0, 1)][axis]
    T[..., i, i] = c
    T[..., k, k] = c
    T[..., i, k] = -s
    T[..., k, i] = s
    return T


def trans(axis: int, dist) -> np.ndarray:
    """Translation by `dist` (mm, any shape) along x (0), y (1) or z (2) as (..., 4, 4)."""
    dist = np.asarray(dist, float)
    T = eye4(dist.shape)
    T[..., axis, 3] = dist
    return T


def rotvec(v) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors v (..., 3) (axis times angle, rad), Rodrigues."""
    v = np.asarray(v, float)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    small = th < 1e-8
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(th_safe) / th_safe)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(th_safe)) / th_safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def rigid(R=None, t=None, shape=()) -> np.ndarray:
    """Homogeneous transform(s) from rotation (..., 3, 3) and translation (..., 3)."""
    if R is not None:
        shape = np.shape(R)[:-2]
    elif t is not None:
        shape = np.shape(t)[:-1]
    T = eye4(shape)
    if R is not None:
        T[..., :3, :3] = R
    if t is not None:
        T[..., :3, 3] = t
    return T


def about_point(rv, point, shift=None) -> np.ndarray:
    """Rigid motion (..., 4, 4) rotating by rotation vector rv about `point` (mm), then translating by shift."""
    R = rotvec(rv)
    point = np.asarray(point, float)
    t = point - np.einsum("...ab,...b->...a", R, point)
    if shift is not None:
        t = t + shift
    return rigid(R, t)


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    return rigid(R, -np.einsum("...ab,...b->...a", R, T[..., :3, 3]))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix drawn uniformly (Haar) from the QR of a Gaussian matrix."""
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def cross(a, b) -> np.ndarray:
    """Cross product over the last axis with broadcasting."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


# ---------------------------------------------------------------------------------------- the robot
@dataclass
class Pose:
    """The physical chain at N poses: base (N,4,4), joint frames (N,n,4,4), each joint's axis direction and a
    point on it (N,n,3), the tool point (N,3) mm, all in the tracker frame."""

    base: np.ndarray
    frames: np.ndarray
    axes: np.ndarray
    axis_points: np.ndarray
    point: np.ndarray

    @property
    def origins(self) -> np.ndarray:
        """Origin of every joint frame, (N, n, 3) mm."""
        return self.frames[..., :3, 3]


class PhysicalRobot:
    """A robot as built: nominal model + geometric errors, an unknown tracker frame, true masses.

    `geometry` (n, 5) true [a_{i-1}, alpha_{i-1}, d_i, theta_i, beta_i] mm/rad; `tool` (3,) mm in the last
    frame; `base` (4, 4) robot base in the tracker frame; `gravity` (3,) m/s^2 in the base frame;
    `mass` (n,) kg and `com` (n, 3) mm in each joint frame: always present, invented if the model has none.
    """

    def __init__(self, model: RobotModel, rng: np.random.Generator, *, geometry_error: float = 1.0,
                 tool_error_mm: float = 5.0, mass_error: float = 1.0, tracker_range_mm: float = 3000.0,
                 level_error_rad: float = 5e-4):
        """geometry_error scales the 10 mm / 8 mrad errors (0: nominal geometry); mass_error scales the 15 % /
        30 mm mass and COM errors (0: the model's masses exactly); level_error_rad tilts true gravity
        against the model's (the floor is never quite level)."""
        self.model = model
        n = model.n_joints
        self.n = n
        self.names = tuple(model.joint_names)
        self.prismatic = np.asarray(model.prismatic, bool)
        self.limits = np.asarray(model.limits, float).copy()
        if np.any(np.asarray(model.geometry, float)[:, 5:]):
            raise ValueError("the simulated world builds MD-H rows (a, alpha, d, theta, beta); this model's rows carry "
                             "gamma or b")
        g = np.asarray(model.geometry, float)[:, :5].copy()
        scale = np.array([LENGTH_ERROR_MM, ANGLE_ERROR_RAD, LENGTH_ERROR_MM, ANGLE_ERROR_RAD, ANGLE_ERROR_RAD])
        err = rng.normal(size=(n, 5)) * scale * geometry_error
        err[~self.parallel_to_previous(), 4] = 0.0  # beta exists physically only between parallel axes
        self.geometry = g + err
        self.tool = np.asarray(model.tool, float) + rng.normal(0.0, tool_error_mm, 3)
        self.base = rigid(random_rotation(rng), rng.uniform(-tracker_range_mm, tracker_range_mm, 3))
        g0 = np.asarray(model.gravity, float)
        tilt = rng.normal(0.0, level_error_rad, 3) if level_error_rad > 0 else np.zeros(3)
        self.gravity = rotvec(tilt) @ g0
        self.mass, self.com = self._true_masses(model, rng, mass_error)
        lo, hi = self.limits[:, 0], self.limits[:, 1]
        # where each encoder was zeroed: the index mark (0) of a revolute joint, the lower end of a linear one
        self.home = np.where(self.prismatic, np.where(np.isfinite(lo), lo, 0.0), np.clip(0.0, lo, hi))

    def parallel_to_previous(self) -> np.ndarray:
        """(n,) True where joint i's axis is nominally parallel to joint i-1's (alpha_{i-1} = 0 or pi)."""
        out = np.zeros(self.n, bool)
        out[1:] = np.abs(np.sin(np.asarray(self.model.geometry)[1:, 1])) < 1e-9
        return out

    def _true_masses(self, model: RobotModel, rng, mass_error: float):
        n = self.n
        if model.mass is not None:
            m = np.asarray(model.mass, float) * np.clip(1.0 + MASS_ERROR * mass_error * rng.normal(size=n), 0.3, None)
            u = rng.normal(size=(n, 3))
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            return m, np.asarray(model.com, float) + COM_SHIFT_MM * mass_error * u
        # no masses in the model: a body is a tube from its joint to the next joint (or the tool) plus a drive
        seg = np.empty((n, 3))
        for j in range(n):
            if j + 1 < n:
                a, al, d = self.geometry[j + 1, :3]
                if self.prismatic[j + 1]:
                    d = d + max(self.limits[j + 1, 0], 0.0) if np.isfinite(self.limits[j + 1, 0]) else d
                seg[j] = np.array([a, -np.sin(al) * d, np.cos(al) * d])
            else:
                seg[j] = self.tool
        L = np.linalg.norm(seg, axis=1)
        return INVENTED_KG_PER_JOINT + INVENTED_KG_PER_MM * L, 0.5 * seg

    def true_model(self) -> RobotModel:
        """The model a perfect calibration would find: true geometry, tool, masses (base not included)."""
        geometry = np.asarray(self.model.geometry, float).copy()
        geometry[:, :5] = self.geometry  # calib_core's rows carry gamma and b too: 0 in the world's MD-H rows
        return dataclasses.replace(self.model, geometry=geometry, tool=self.tool.copy(),
                                   mass=self.mass.copy(), com=self.com.copy(), gravity=self.gravity.copy())

    def gravity_tracker(self) -> np.ndarray:
        """Gravity (3,) m/s^2 in the tracker frame."""
        return self.base[:3, :3] @ self.gravity

    # ------------------------------------------------------------------------------------ kinematics
    def frames(self, q, dq=None, *, geometry=None, tool=None, base=None, pre=None, post=None) -> Pose:
        """Frames of the physical chain at joints q (N, n) rad/mm, moved by joint deflections dq.

        geometry (n,5) or (N,n,5), tool (3,) or (N,3) and base (4,4) or (N,4,4) override the true ones;
        pre[k] (N,4,4) is a deformation inserted before link k (in frame k-1, k=0: the base frame),
        post[k] one after link k (in frame k).  Link k = Rx(alpha) Tx(a) Rz(theta [+q]) Tz(d [+q]) Ry(beta).
        """
        q = np.atleast_2d(np.asarray(q, float))
        N, n = q.shape[0], self.n
        qt = q if dq is None else q + dq
        geo = np.broadcast_to(self.geometry if geometry is None else geometry, (N, n, 5))
        a, al, d, th, be = (geo[..., k] for k in range(5))
        theta = th + np.where(self.prismatic, 0.0, qt)
        length = d + np.where(self.prismatic, qt, 0.0)
        B = np.broadcast_to(self.base if base is None else base, (N, 4, 4))
        tl = np.broadcast_to(self.tool if tool is None else tool, (N, 3))
        F = B
        frames = np.empty((N, n, 4, 4))
        axes = np.empty((N, n, 3))
        pts = np.empty((N, n, 3))
        for k in range(n):
            if pre and k in pre:
                F = F @ pre[k]
            M = F @ rot(0, al[:, k]) @ trans(0, a[:, k])
            axes[:, k] = M[:, :3, 2]
            pts[:, k] = M[:, :3, 3]
            F = M @ rot(2, theta[:, k]) @ trans(2, length[:, k]) @ rot(1, be[:, k])
            if post and k in post:
                F = F @ post[k]
            frames[:, k] = F
        point = np.einsum("nab,nb->na", F[:, :3, :3], tl) + F[:, :3, 3]
        return Pose(B, frames, axes, pts, point)

    def point(self, q, dq=None, **kw) -> np.ndarray:
        """The tool point (N, 3) mm in the tracker frame."""
        return self.frames(q, dq, **kw).point

    # ------------------------------------------------------------------------------------ statics
    def body_coms(self, pose: Pose) -> np.ndarray:
        """Centre of mass of every body in the tracker frame, (N, n, 3) mm."""
        return np.einsum("nkab,kb->nka", pose.frames[..., :3, :3], self.com) + pose.origins

    def joint_loads(self, q, payload_kg=None, *, pose: Pose | None = None, **frames_kw) -> np.ndarray:
        """True gravity torque about each revolute axis (N*m) / force along each prismatic axis (N), (N, n).

        The load on joint j sums m (com - axis point) x g over bodies j..n and the payload (at the tool point),
        projected on the joint axis; positive where gravity pushes the joint in its positive direction.
        """
        pose = self.frames(q, **frames_kw) if pose is None else pose
        N = pose.point.shape[0]
        pl = np.zeros(N) if payload_kg is None else np.broadcast_to(np.asarray(payload_kg, float), (N,))
        g = np.einsum("nab,b->na", pose.base[:, :3, :3], self.gravity)  # (N, 3) m/s^2
        com = self.body_coms(pose)
        n = self.n
        torque = np.empty((N, n))
        for j in range(n):
            lever = com[:, j:] - pose.axis_points[:, j, None]  # (N, n-j, 3) mm
            moment = (self.mass[j:, None] * cross(lever, g[:, None])).sum(1)
            moment += pl[:, None] * cross(pose.point - pose.axis_points[:, j], g)
            if self.prismatic[j]:
                torque[:, j] = (self.mass[j:].sum() + pl) * (g * pose.axes[:, j]).sum(1)
            else:
                torque[:, j] = (moment * pose.axes[:, j]).sum(1) / 1000.0
        return torque
