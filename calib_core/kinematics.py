"""Forward kinematics and the analytic identification Jacobian, vectorised over N poses.

The parameter vector x (mm, rad) is laid out as
    [a, alpha, d, theta, beta] per joint (5n), base [x, y, z, rx, ry, rz] (6), tool [x, y, z] (3).
The base pose of the robot in the measurement frame is Trans(x, y, z) R0 Rz(rz) Ry(ry) Rx(rx):
R0 is a fixed reference rotation (from a rigid pre-alignment) so that the identified angles stay small.
"""
from __future__ import annotations

import math

import numpy as np

from .model import GEOMETRIC, RobotModel

BASE = ("x", "y", "z", "rx", "ry", "rz")
TOOL = ("x", "y", "z")


def parameter_names(model: RobotModel) -> list[str]:
    """Names of the full parameter vector, e.g. 'J4.theta', 'base.rx', 'tool.z'."""
    return ([f"{j}.{p}" for j in model.joint_names for p in GEOMETRIC]
            + [f"base.{p}" for p in BASE] + [f"tool.{p}" for p in TOOL])


def angular_mask(model: RobotModel) -> np.ndarray:
    """True where a parameter is an angle (rad internally), False for lengths (mm)."""
    per_joint = [p in ("alpha", "theta", "beta") for p in GEOMETRIC]
    return np.array(per_joint * model.n_joints + [False] * 3 + [True] * 3 + [False] * 3)


def nominal_vector(model: RobotModel, base: np.ndarray | None = None) -> np.ndarray:
    """The model's own parameters as a vector; base pose zero unless given."""
    b = np.zeros(6) if base is None else base
    return np.concatenate([model.geometry.ravel(), b, model.tool])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (broadcasting), without np.cross's overhead."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def base_rotation(base: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """Rotation of the base in the measurement frame: R0 Rz(rz) Ry(ry) Rx(rx)."""
    return R0 @ _rz(base[5]) @ _ry(base[4]) @ _rx(base[3])


class Chain:
    """Frames of every joint for N poses: the one pass that both FK and Jacobian need.

    Stores per joint the world axes and origins at which each elementary MD-H motion acts.
    """

    def __init__(self, model: RobotModel, x: np.ndarray, q: np.ndarray, R0: np.ndarray | None = None):
        n = model.n_joints
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        g = x[: 5 * n].reshape(n, 5)
        base, tool = x[5 * n: 5 * n + 6], x[5 * n + 6: 5 * n + 9]
        R0 = np.eye(3) if R0 is None else R0
        Rb = base_rotation(base, R0)
        self.model, self.x, self.N, self.R0, self.Rb = model, x, N, R0, Rb
        self.base_origin = base[:3]
        R = np.broadcast_to(Rb, (N, 3, 3))
        o = np.broadcast_to(base[:3], (N, 3))
        # per joint: x axis / origin of frame i-1, z axis / origin after Tx(a), y axis / origin after Tz(d)
        self.x_prev = np.empty((n, N, 3))
        self.o_prev = np.empty((n, N, 3))
        self.z_axis = np.empty((n, N, 3))
        self.o_theta = np.empty((n, N, 3))
        self.y_beta = np.empty((n, N, 3))
        self.o_beta = np.empty((n, N, 3))
        self.R = np.empty((n, N, 3, 3))  # rotation of each joint frame
        for j in range(n):
            a, alpha, d, theta, beta = g[j]
            self.x_prev[j] = R[:, :, 0]
            self.o_prev[j] = o
            R1 = R @ _rx(alpha)
            o1 = o + a * R[:, :, 0]
            th = np.broadcast_to(theta + (0.0 if model.prismatic[j] else q[:, j]), (N,))
            dd = np.broadcast_to(d + (q[:, j] if model.prismatic[j] else 0.0), (N,))
            c, s = np.cos(th)[:, None], np.sin(th)[:, None]
            xa = c * R1[:, :, 0] + s * R1[:, :, 1]
            ya = c * R1[:, :, 1] - s * R1[:, :, 0]
            za = R1[:, :, 2]
            o2 = o1 + dd[:, None] * za
            R2 = np.stack([xa, ya, za], axis=2)
            self.z_axis[j] = za
            self.o_theta[j] = o1
            self.y_beta[j] = ya
            self.o_beta[j] = o2
            R = R2 @ _ry(beta) if beta != 0.0 else R2
            o = o2
            self.R[j] = R
        self.o_end = o
        self.p = o + R @ tool  # (N, 3) the measured point in the measurement frame

    def joint_jacobian(self) -> np.ndarray:
        """dp/dq for every joint, shape (N, 3, n): z x (p - o) for revolute, z for prismatic."""
        rev = _cross(self.z_axis, self.p[None] - self.o_theta)
        pri = self.z_axis
        J = np.where(self.model.prismatic[:, None, None], pri, rev)
        return np.moveaxis(J, 0, 2)

    def jacobian(self) -> np.ndarray:
        """dp/dx for the full parameter vector, shape (N, 3, 5n + 9), x in mm and rad."""
        n, N, p = self.model.n_joints, self.N, self.p
        cols = np.empty((n, 5, N, 3))
        cols[:, 0] = self.x_prev  # a_{i-1}: translation along x_{i-1}
        cols[:, 1] = _cross(self.x_prev, p[None] - self.o_prev)  # alpha_{i-1}
        cols[:, 2] = self.z_axis  # d_i
        cols[:, 3] = _cross(self.z_axis, p[None] - self.o_theta)  # theta_i
        cols[:, 4] = _cross(self.y_beta, p[None] - self.o_beta)  # beta_i
        geo = cols.reshape(5 * n, N, 3)
        base = self.x[5 * n: 5 * n + 6]
        rz_axis = self.R0[:, 2]
        ry_axis = (self.R0 @ _rz(base[5]))[:, 1]
        rx_axis = (self.R0 @ _rz(base[5]) @ _ry(base[4]))[:, 0]
        dp = p - self.base_origin
        bcols = np.stack([np.broadcast_to(e, (N, 3)) for e in np.eye(3)]
                         + [_cross(rx_axis, dp), _cross(ry_axis, dp), _cross(rz_axis, dp)])
        tcols = np.moveaxis(self.R[-1], 2, 0)  # (3, N, 3)
        J = np.concatenate([geo, bcols, tcols], axis=0)  # (P, N, 3)
        return np.moveaxis(J, 0, 2)


def forward(model: RobotModel, x: np.ndarray, q: np.ndarray, R0: np.ndarray | None = None) -> np.ndarray:
    """Measured point (N, 3) mm in the measurement frame for joints q (N, n) in rad / mm."""
    return Chain(model, x, q, R0).p


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R and translation t with dst ~ R src + t (Kabsch), points (N, 3)."""
    cs, cd = src.mean(0), dst.mean(0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs
