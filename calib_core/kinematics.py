"""Forward kinematics and the analytic identification Jacobian, vectorised over N poses.

The parameter vector x (mm, rad) is laid out as
    [a, alpha, d, theta, beta] per row (5n), base [x, y, z, rx, ry, rz] per setup (6S), [x, y, z] per target (3T);
a serial chain measured in one setup at one tool point has 5n + 9.
The base pose of the robot in the measurement frame is Trans(x, y, z) R0 Rz(rz) Ry(ry) Rx(rx):
R0 is a fixed reference rotation (from a rigid pre-alignment) so that the identified angles stay small.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from .model import GEOMETRIC, RobotModel

BASE = ("x", "y", "z", "rx", "ry", "rz")
TOOL = ("x", "y", "z")


@dataclass(frozen=True)
class Labels:
    """Per pose: which target it measures and which setup (base-to-tracker transform) it was taken in."""

    target: np.ndarray  # (N,) int index into model.target_names
    setup: np.ndarray  # (N,) int index into the measurement set's setups

    def __getitem__(self, idx) -> "Labels":
        return Labels(self.target[idx], self.setup[idx])

    @property
    def n_setups(self) -> int:
        return int(self.setup.max()) + 1 if len(self.setup) else 1


@dataclass(frozen=True)
class Layout:
    """Where each block sits in the parameter vector: 5 per row, 6 per setup's base, 3 per target."""

    n: int
    n_setups: int
    n_targets: int

    @property
    def geometry(self) -> slice:
        return slice(0, 5 * self.n)

    def base(self, s: int = 0) -> slice:
        return slice(5 * self.n + 6 * s, 5 * self.n + 6 * s + 6)

    def tool(self, t: int = 0) -> slice:
        i = 5 * self.n + 6 * self.n_setups + 3 * t
        return slice(i, i + 3)

    @property
    def bases(self) -> slice:
        return slice(5 * self.n, 5 * self.n + 6 * self.n_setups)

    @property
    def tools(self) -> slice:
        return slice(self.bases.stop, self.bases.stop + 3 * self.n_targets)

    @property
    def size(self) -> int:
        return self.tools.stop


def layout(model: RobotModel, x_or_setups=1) -> Layout:
    """The layout for a model and a number of setups (or a parameter vector, from its length)."""
    T = model.n_targets
    if isinstance(x_or_setups, (int, np.integer)):
        return Layout(model.n_joints, int(x_or_setups), T)
    S = (len(x_or_setups) - 5 * model.n_joints - 3 * T) // 6
    return Layout(model.n_joints, S, T)


def parameter_names(model: RobotModel, setups: tuple[str, ...] = ("",)) -> list[str]:
    """Names of the full parameter vector, e.g. 'J4.theta', 'base.rx', 'tool.z' ('base[s2].rx' with several
    setups, 'tool[left].z' with several targets)."""
    bname = (lambda s: "base") if len(setups) == 1 else (lambda s: f"base[{s}]")
    tname = (lambda t: "tool") if model.n_targets == 1 else (lambda t: f"tool[{t}]")
    return ([f"{j}.{p}" for j in model.joint_names for p in GEOMETRIC]
            + [f"{bname(s)}.{p}" for s in setups for p in BASE]
            + [f"{tname(t)}.{p}" for t in model.target_names for p in TOOL])


def angular_mask(model: RobotModel, n_setups: int = 1) -> np.ndarray:
    """True where a parameter is an angle (rad internally), False for lengths (mm)."""
    per_joint = [p in ("alpha", "theta", "beta") for p in GEOMETRIC]
    return np.array(per_joint * model.n_joints + ([False] * 3 + [True] * 3) * n_setups
                    + [False] * 3 * model.n_targets)


def nominal_vector(model: RobotModel, base: np.ndarray | None = None, n_setups: int = 1) -> np.ndarray:
    """The model's own parameters as a vector; base poses zero unless given ((6,) or (S, 6))."""
    b = np.zeros((n_setups, 6)) if base is None else np.broadcast_to(base, (n_setups, 6))
    return np.concatenate([model.geometry.ravel(), np.ravel(b), model.target_points.ravel()])


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


def _per_setup_R0(R0, S: int) -> np.ndarray:
    R0 = np.eye(3) if R0 is None else np.asarray(R0, float)
    return np.broadcast_to(R0, (S, 3, 3)) if R0.ndim == 2 else R0


class _Static:
    """What Chain needs of a model that never changes with x or q, computed once per model (its properties build
    arrays on every call): per row the parent, whether it moves / is prismatic, its constant `pre` transform
    (None for the identity), and the target rows and ancestors."""

    def __init__(self, model: RobotModel):
        n = model.n_joints
        fixed, prismatic = model.is_fixed, model.prismatic
        self.parents = [int(p) for p in model.parents]
        self.revolute_q = [bool(not fixed[j] and not prismatic[j]) for j in range(n)]  # theta_i + q_i
        self.prismatic_q = [bool(not fixed[j] and prismatic[j]) for j in range(n)]  # d_i + q_i
        pre = model.pre
        self.pre = [None if pre is None or np.array_equal(pre[j], _EYE4) else
                    (pre[j, :3, 3].copy(), pre[j, :3, :3].copy()) for j in range(n)]
        self.target_rows = model.target_rows
        self.ancestors = model.ancestors()
        self.prismatic = np.asarray(prismatic, bool)
        self.moving = np.asarray(model.moving, bool)
        self.serial = model.is_serial


_STATIC: "weakref.WeakKeyDictionary[RobotModel, _Static]" = weakref.WeakKeyDictionary()


def _static(model: RobotModel) -> _Static:
    st = _STATIC.get(model)
    if st is None:
        st = _STATIC[model] = _Static(model)
    return st


def _cross_into(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcasting) written into out: the arithmetic of _cross, without its stack."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


class Chain:
    """Frames of every row for N poses: the one pass that both FK and Jacobian need.

    Stores per row the world axes and origins at which each elementary MD-H motion acts, over a tree
    (each row follows its parent's frame), for each pose's target and setup (`labels`, default all 0).

    Speed (an identification evaluates the chain a hundred times): a frame is carried as its three axes (columns)
    and the elementary rotations are written out per column, not as (N, 3, 3) matrix products of a built matrix;
    a rotation by a zero angle or a translation by zero length is skipped (it would add exact zeros); what
    depends on the model alone is computed once per model (_Static).
    """

    def __init__(self, model: RobotModel, x: np.ndarray, q: np.ndarray, R0: np.ndarray | None = None,
                 labels: Labels | None = None):
        n = model.n_joints
        st = _static(model)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        lay = layout(model, x)
        S, T = lay.n_setups, lay.n_targets
        g = x[lay.geometry].reshape(n, 5)
        bases = x[lay.bases].reshape(S, 6)
        tools = x[lay.tools].reshape(T, 3)
        R0s = _per_setup_R0(R0, S)
        Rbs = np.array([base_rotation(bases[s], R0s[s]) for s in range(S)])
        if labels is None:
            setup = target = np.zeros(N, int)
        else:
            setup, target = labels.setup, labels.target
        self.model, self.x, self.N, self.layout, self.labels = model, x, N, lay, labels
        self.R0, self.Rbs, self.bases, self.setup, self.target = R0s[0] if S == 1 else R0s, Rbs, bases, setup, target
        self.Rb = Rbs[0] if S == 1 else Rbs[setup]  # (3, 3) or per pose (N, 3, 3)
        self.base_origin = bases[0, :3] if S == 1 else bases[setup, :3]
        # the base frame's axes and origin: (3,) vectors shared by every pose, or per pose (N, 3)
        Rbase = self.Rb
        base_axes = (Rbase[..., 0], Rbase[..., 1], Rbase[..., 2])
        obase = self.base_origin
        # per row: x axis / origin of frame i-1, z axis / origin after Tx(a), y axis / origin after Tz(d)
        self.x_prev = np.empty((n, N, 3))
        self.o_prev = np.empty((n, N, 3))
        self.z_axis = np.empty((n, N, 3))
        self.o_theta = np.empty((n, N, 3))
        self.y_beta = np.empty((n, N, 3))
        self.o_beta = np.empty((n, N, 3))
        self.R = np.empty((n, N, 3, 3))  # rotation of each joint frame
        for j, (a, alpha, d, theta, beta) in enumerate(g.tolist()):
            pj = st.parents[j]
            if pj < 0:
                (X, Y, Z), o = base_axes, obase
            else:
                Rp = self.R[pj]
                X, Y, Z, o = Rp[:, :, 0], Rp[:, :, 1], Rp[:, :, 2], self.o_beta[pj]
            pre = st.pre[j]
            if pre is not None:  # o + R t, R P
                t, P = pre
                o = o + (X * t[0] + Y * t[1] + Z * t[2])
                X, Y, Z = (X * P[0, 0] + Y * P[1, 0] + Z * P[2, 0], X * P[0, 1] + Y * P[1, 1] + Z * P[2, 1],
                           X * P[0, 2] + Y * P[1, 2] + Z * P[2, 2])
            self.x_prev[j] = X
            self.o_prev[j] = o
            if alpha != 0.0:  # R Rx(alpha): y and z turn about x
                ca, sa = math.cos(alpha), math.sin(alpha)
                Y, Z = Y * ca + Z * sa, Z * ca - Y * sa
            o1 = o + a * X if a != 0.0 else o
            if st.revolute_q[j]:
                th = theta + q[:, j]
                c, s = np.cos(th)[:, None], np.sin(th)[:, None]
            else:
                c, s = math.cos(theta), math.sin(theta)
            xa = c * X + s * Y
            ya = c * Y - s * X
            if st.prismatic_q[j]:
                o2 = o1 + (d + q[:, j])[:, None] * Z
            else:
                o2 = o1 + d * Z if d != 0.0 else o1
            self.z_axis[j] = Z
            self.o_theta[j] = o1
            self.y_beta[j] = ya
            self.o_beta[j] = o2
            Rj = self.R[j]
            if beta != 0.0:  # R2 Ry(beta)
                cb, sb = math.cos(beta), math.sin(beta)
                Rj[:, :, 0] = xa * cb - Z * sb
                Rj[:, :, 1] = ya
                Rj[:, :, 2] = xa * sb + Z * cb
            else:
                Rj[:, :, 0] = xa
                Rj[:, :, 1] = ya
                Rj[:, :, 2] = Z
        rows = st.target_rows
        self.end_row = rows[target]  # (N,) the row each pose's target sits on
        if T == 1 and len(rows) == 1:  # every pose on one row: plain copies instead of fancy indexing
            r = int(rows[0])
            self.o_end = self.o_beta[r].copy()
            self.R_end = self.R[r].copy()
        else:
            idx = np.arange(N)
            self.o_end = self.o_beta[self.end_row, idx]
            self.R_end = self.R[self.end_row, idx]
        self.p = self.o_end + np.einsum("nab,nb->na", self.R_end, tools[target])  # (N, 3) in the measurement frame
        self.on_path = st.ancestors[self.end_row].T  # (n, N): row j carries pose i's target

    def joint_jacobian(self) -> np.ndarray:
        """dp/dq for every row, shape (N, 3, n): z x (p - o) for revolute, z for prismatic, 0 for fixed rows
        and rows not on the way to the pose's target."""
        st = _static(self.model)
        rev = _cross(self.z_axis, self.p[None] - self.o_theta)
        pri = self.z_axis
        J = np.where(st.prismatic[:, None, None], pri, rev)
        J = J * (self.on_path & st.moving[:, None])[..., None]
        return np.moveaxis(J, 0, 2)

    def jacobian(self) -> np.ndarray:
        """dp/dx for the full parameter vector, shape (N, 3, P), x in mm and rad (layout()).

        Filled block by block into one (P, N, 3) array (returned as its (N, 3, P) view)."""
        n, N, p, lay = self.model.n_joints, self.N, self.p, self.layout
        J = np.empty((lay.size, N, 3))
        cols = J[: 5 * n].reshape(n, 5, N, 3)
        cols[:, 0] = self.x_prev  # a_{i-1}: translation along x_{i-1}
        _cross_into(cols[:, 1], self.x_prev, p[None] - self.o_prev)  # alpha_{i-1}
        cols[:, 2] = self.z_axis  # d_i
        _cross_into(cols[:, 3], self.z_axis, p[None] - self.o_theta)  # theta_i
        _cross_into(cols[:, 4], self.y_beta, p[None] - self.o_beta)  # beta_i
        if not _static(self.model).serial:
            cols *= self.on_path[:, None, :, None]
        for s in range(lay.n_setups):
            base, R0 = self.bases[s], (self.R0 if lay.n_setups == 1 else self.R0[s])
            rz_axis = R0[:, 2]
            ry_axis = (R0 @ _rz(base[5]))[:, 1]
            rx_axis = (R0 @ _rz(base[5]) @ _ry(base[4]))[:, 0]
            dp = p - base[:3]
            b = J[lay.base(s)]
            b[:3] = 0.0
            b[0, :, 0] = b[1, :, 1] = b[2, :, 2] = 1.0
            _cross_into(b[3], rx_axis, dp)
            _cross_into(b[4], ry_axis, dp)
            _cross_into(b[5], rz_axis, dp)
            if lay.n_setups > 1:
                b *= (self.setup == s)[None, :, None]
        for t in range(lay.n_targets):
            tc = J[lay.tool(t)]
            tc[:] = np.moveaxis(self.R_end, 2, 0)  # (3, N, 3)
            if lay.n_targets > 1:
                tc *= (self.target == t)[None, :, None]
        return np.moveaxis(J, 0, 2)


_EYE4 = np.eye(4)


def forward(model: RobotModel, x: np.ndarray, q: np.ndarray, R0: np.ndarray | None = None,
            labels: Labels | None = None) -> np.ndarray:
    """Measured point (N, 3) mm in the measurement frame for row values q (N, n) in rad / mm."""
    return Chain(model, x, q, R0, labels).p


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation R and translation t with dst ~ R src + t (Kabsch), points (N, 3)."""
    cs, cd = src.mean(0), dst.mean(0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs
