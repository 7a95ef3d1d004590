"""Forward kinematics and the analytic identification Jacobian, vectorised over N poses.

The parameter vector x (mm, rad) is laid out as
    [a, alpha, d, theta, beta, gamma, b] per row (7n, model.GEOMETRIC), base [x, y, z, rx, ry, rz] per setup (6S),
    [x, y, z] per target (3T);
a serial chain measured in one setup at one tool point has 7n + 9. A row is
``Rx(alpha) Tx(a) Ry(gamma) Ty(b) Rz(theta [+q]) Tz(d [+q]) Ry(beta)`` after its constant `pre` transform.
The base pose of the robot in the measurement frame is Trans(x, y, z) R0 Rz(rz) Ry(ry) Rx(rx):
R0 is a fixed reference rotation (from a rigid pre-alignment) so that the identified angles stay small.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from .model import ANGULAR, GEOMETRIC, RobotModel

G = len(GEOMETRIC)
"""Geometric parameters per row."""
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
    """Where each block sits in the parameter vector: G = len(GEOMETRIC) per row, 6 per setup's base, 3 per
    target."""

    n: int
    n_setups: int
    n_targets: int

    @property
    def geometry(self) -> slice:
        return slice(0, G * self.n)

    def base(self, s: int = 0) -> slice:
        return slice(G * self.n + 6 * s, G * self.n + 6 * s + 6)

    def tool(self, t: int = 0) -> slice:
        i = G * self.n + 6 * self.n_setups + 3 * t
        return slice(i, i + 3)

    @property
    def bases(self) -> slice:
        return slice(G * self.n, G * self.n + 6 * self.n_setups)

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
    S = (len(x_or_setups) - G * model.n_joints - 3 * T) // 6
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
    per_joint = [p in ANGULAR for p in GEOMETRIC]
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
    return _base_frame(base, R0)[0]


def _base_frame(base: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The base rotation R0 Rz(rz) Ry(ry) Rx(rx) and the world axes (3 which, 3) its rx, ry and rz turn about (rx
    about the twice-turned x), from the same products."""
    Rz = R0 @ _rz(base[5])
    Rzy = Rz @ _ry(base[4])
    return Rzy @ _rx(base[3]), np.array([Rzy[:, 0], Rz[:, 1], R0[:, 2]])


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
    """a x b over the first axis (vectors stored components first, broadcasting over the rest) written into out."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


def _row_parameters(g: np.ndarray) -> list[tuple]:
    """Per row (a, alpha, d, theta, beta, gamma, b) from the geometry block (n, G) of one parameter vector, as
    floats; of B vectors (B, n, G), a parameter equal in all of them is a float too, else its values as (B, 1)
    (they then broadcast against a batch of poses (3, B, N))."""
    if g.ndim == 2:
        return g.tolist()
    same = (g == g[0]).all(0).tolist()
    return [tuple(v if u else g[:, j, k, None] for k, (v, u) in enumerate(zip(row, same[j])))
            for j, row in enumerate(g[0].tolist())]


def _moves(v) -> bool:
    """Whether a motion by v (a float, or values per parameter vector that differ) can change a frame: a float 0
    adds exact zeros and is skipped."""
    return not isinstance(v, float) or v != 0.0


def _cos_sin(v):
    """cos and sin of a float (math) or of values per parameter vector (numpy)."""
    if isinstance(v, float):
        return math.cos(v), math.sin(v)
    return np.cos(v), np.sin(v)


def _step(out: np.ndarray, o: np.ndarray, length, axis: np.ndarray) -> np.ndarray:
    """o + length * axis written into out (a float length 0 copies o: it would add exact zeros)."""
    if not _moves(length):
        out[...] = o
        return out
    np.multiply(length, axis, out=out)
    out += o
    return out


def _first(a: np.ndarray, k: int = 1) -> np.ndarray:
    """Components-first view of an array in the poses' layout: (..., N, 3) -> (3, ..., N); for rotations (k = 2),
    (..., N, 3, 3) [component, axis] -> (3, 3, ..., N) [axis, component]."""
    return a.transpose(*range(a.ndim - 1, a.ndim - k - 1, -1), *range(a.ndim - k))


def _last(a: np.ndarray, rows: int = 0, k: int = 1) -> np.ndarray:
    """The poses' layout of a components-first array after its `rows` leading axes, contiguous: (rows, 3, ..., N)
    -> (rows, ..., N, 3); for rotations (k = 2), (rows, 3, 3, ..., N) [axis, component] -> (rows, ..., N, 3, 3)."""
    return np.ascontiguousarray(a.transpose(*range(rows), *range(rows + k, a.ndim), *range(rows + k - 1, rows - 1, -1)))


class _PosesLayout:
    """A Chain attribute in the poses' layout, made on first use from its components-first twin `_<name>` (`_last`
    with these `rows` and `k`) and kept: the effects read these, the chain itself never needs them."""

    def __init__(self, rows: int = 0, k: int = 1):
        self.rows, self.k = rows, k

    def __set_name__(self, owner, name: str):
        self.name = name

    def __get__(self, chain, owner=None):
        if chain is None:
            return self
        value = chain.__dict__[self.name] = _last(getattr(chain, "_" + self.name), self.rows, self.k)
        return value


class Chain:
    """Frames of every row for N poses: the one pass that both FK and Jacobian need.

    Stores per row the world axes and origins at which each elementary MD-H motion acts, over a tree
    (each row follows its parent's frame), for each pose's target and setup (`labels`, default all 0).

    Speed (an identification evaluates the chain a hundred times): vectors are stored components first, a row's
    vector as one contiguous (3, N) block, so every numpy call is a long loop over the poses (with (N, 3) it is N
    loops of 3, and broadcasting a per-pose cosine over the components costs several times more) and results are
    written in place; a frame is carried as its three axes and the elementary rotations are written out per axis,
    not as (N, 3, 3) matrix products of a built matrix; a rotation by a zero angle or a translation by zero length
    is skipped (it would add exact zeros); what depends on the model alone is computed once per model (_Static).
    Every element is the same arithmetic as in the poses' layout. The per-row frames in the (n, N, 3) layout the
    effects use (x_prev, ..., R) are made on first use.

    x may also be B parameter vectors (B, P) at the same poses (the folds of a cross-validation, solved together):
    every array then has a leading (B,) before the poses (p: (B, N, 3), jacobian(): (B, N, 3, P)), and one pass
    costs about a third of B single passes. A parameter equal in all B vectors is still a float, so each vector's
    frames are the arithmetic of its own chain, to the bit.
    """

    def __init__(self, model: RobotModel, x: np.ndarray, q: np.ndarray, R0: np.ndarray | None = None,
                 labels: Labels | None = None):
        n = model.n_joints
        st = _static(model)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        lead = x.shape[:-1]  # () or (B,): B parameter vectors at the same poses
        lay = layout(model, x[0] if lead else x)
        S, T = lay.n_setups, lay.n_targets
        bases = x[..., lay.bases].reshape(*lead, S, 6)
        tools = x[..., lay.tools].reshape(*lead, T, 3)
        R0s = _per_setup_R0(R0, S)
        frames = [_base_frame(b, R0s[i % S]) for i, b in enumerate(bases.reshape(-1, 6))]
        Rbs = np.array([R for R, _ in frames]).reshape(*lead, S, 3, 3)
        self._turns = np.array([a for _, a in frames]).reshape(*lead, S, 3, 3)  # per setup: the world axes rx, ry, rz
        if labels is None:
            setup = target = np.zeros(N, int)
        else:
            setup, target = labels.setup, labels.target
        self.model, self.x, self.N, self.layout, self.labels = model, x, N, lay, labels
        self.R0, self.Rbs, self.bases, self.setup, self.target = R0s[0] if S == 1 else R0s, Rbs, bases, setup, target
        self.Rb = Rbs[..., 0, :, :] if S == 1 else Rbs[..., setup, :, :]  # (3, 3) or per pose (N, 3, 3)
        self.base_origin = bases[..., 0, :3] if S == 1 else bases[..., setup, :3]
        # the base frame's axes and origin, components first: (3, 1) shared by every pose or (3, N) per pose
        Rbase, obase = _first(self.Rb, 2), _first(self.base_origin)
        if S == 1:
            Rbase, obase = Rbase[..., None], obase[..., None]
        # per row, components first (n, 3, N): x axis / origin of frame i-1, z axis / origin on the joint axis (after
        # Tx(a) Ry(gamma) Ty(b)), origin after Tz(d), the y axis gamma and b act about / along; the rotation of each joint frame as its axes (n, 3, 3, N) [axis, component]; y_beta is its y
        self._x_prev, self._o_prev, self._z_axis, self._o_theta, self._o_beta, self._y_prev = \
            np.empty((6, n, 3, *lead, N))
        self._R = np.empty((n, 3, 3, *lead, N))
        self._y_beta = self._R[:, 1]
        qT = np.ascontiguousarray(q.T)  # (n, N): each row's values contiguous
        for j, (a, alpha, d, theta, beta, gamma, b) in enumerate(
                _row_parameters(x[..., lay.geometry].reshape(*lead, n, G))):
            pj = st.parents[j]
            if pj < 0:
                (X, Y, Z), o = Rbase, obase
            else:
                X, Y, Z = self._R[pj]
                o = self._o_beta[pj]
            pre = st.pre[j]
            if pre is not None:  # o + R t, R P
                t, P = pre
                o = o + (X * t[0] + Y * t[1] + Z * t[2])
                X, Y, Z = (X * P[0, 0] + Y * P[1, 0] + Z * P[2, 0], X * P[0, 1] + Y * P[1, 1] + Z * P[2, 1],
                           X * P[0, 2] + Y * P[1, 2] + Z * P[2, 2])
            self._x_prev[j] = X
            self._o_prev[j] = o
            (x_j, y_j, z_j), z = self._R[j], self._z_axis[j]
            if _moves(alpha):  # R Rx(alpha): y and z turn about x
                ca, sa = _cos_sin(alpha)
                Y, Z = Y * ca + Z * sa, np.subtract(Z * ca, Y * sa, out=z)
            else:
                z[...] = Z
            o1 = _step(self._o_theta[j], o, a, X)  # o + a x
            if _moves(gamma):  # Ry(gamma): x and z turn about y
                cg, sg = _cos_sin(gamma)
                X, Z = X * cg - z * sg, X * sg + z * cg
                z[...] = Z
            self._y_prev[j] = Y
            if _moves(b):  # + b y: the origin stays on the joint axis
                o1 += b * Y
            if st.revolute_q[j]:
                th = theta + qT[j]
                c, s = np.cos(th), np.sin(th)
            else:
                c, s = _cos_sin(theta)
            if _moves(beta):
                xa = c * X + s * Y
            else:
                xa = np.multiply(c, X, out=x_j)
                xa += s * Y  # c x + s y
            np.multiply(c, Y, out=y_j)
            y_j -= s * X  # c y - s x
            _step(self._o_beta[j], o1, d + qT[j] if st.prismatic_q[j] else d, z)  # o1 + d z
            if _moves(beta):  # R2 Ry(beta)
                cb, sb = _cos_sin(beta)
                np.subtract(xa * cb, z * sb, out=x_j)
                np.add(xa * sb, z * cb, out=z_j)
            else:
                z_j[...] = z
        rows = st.target_rows
        self.end_row = rows[target]  # (N,) the row each pose's target sits on
        if T == 1 and len(rows) == 1:  # every pose on one row
            r = int(rows[0])
            self._o_end, self._R_end = self._o_beta[r], self._R[r]
        else:
            idx = np.arange(N)
            self._o_end = np.moveaxis(self._o_beta[self.end_row, ..., idx], 0, -1)
            self._R_end = np.moveaxis(self._R[self.end_row, ..., idx], 0, -1)
        # (N, 3) in the measurement frame; the lever summed by einsum in the poses' layout, as it always was
        self.p = self.o_end + np.einsum("...ab,...b->...a", self.R_end, tools[..., target, :])
        self._p = np.ascontiguousarray(_first(self.p))
        self.on_path = st.ancestors[self.end_row].T  # (n, N): row j carries pose i's target

    x_prev = _PosesLayout(1)  # (n, N, 3) x axis of frame i-1 (after the row's constant transform)
    o_prev = _PosesLayout(1)  # (n, N, 3) origin of frame i-1, mm
    z_axis = _PosesLayout(1)  # (n, N, 3) joint axis z_i
    y_prev = _PosesLayout(1)  # (n, N, 3) y axis about / along which gamma and b act
    o_theta = _PosesLayout(1)  # (n, N, 3) origin after Tx(a) Ry(gamma) Ty(b), on the joint axis, mm
    y_beta = _PosesLayout(1)  # (n, N, 3) y axis about which beta turns
    o_beta = _PosesLayout(1)  # (n, N, 3) origin of frame i, mm
    R = _PosesLayout(1, 2)  # (n, N, 3, 3) rotation of each joint frame in the measurement frame
    o_end = _PosesLayout()  # (N, 3) origin of the frame each pose's target sits on, mm
    R_end = _PosesLayout(0, 2)  # (N, 3, 3) rotation of the frame each pose's target sits on

    def joint_jacobian(self) -> np.ndarray:
        """dp/dq for every row, shape (N, 3, n): z x (p - o) for revolute, z for prismatic, 0 for fixed rows
        and rows not on the way to the pose's target (one parameter vector)."""
        st = _static(self.model)
        rev = _cross(self.z_axis, self.p[None] - self.o_theta)
        pri = self.z_axis
        J = np.where(st.prismatic[:, None, None], pri, rev)
        J = J * (self.on_path & st.moving[:, None])[..., None]
        return np.moveaxis(J, 0, 2)

    def jacobian(self) -> np.ndarray:
        """dp/dx for the full parameter vector, shape (N, 3, P), x in mm and rad (layout()); (B, N, 3, P) for B
        parameter vectors.

        Filled block by block into one array through its components-first view (3, P, [B,] N) and returned as its
        (N, 3, P) view: for one vector the array is (P, N, 3), the layout it always had (what is computed from it
        sums in the same order); for B vectors it is components first, which the folds' gathers read fastest."""
        n, N, lay = self.model.n_joints, self.N, self.layout
        lead = self._p.shape[1:-1]
        if lead:
            J = np.empty((3, lay.size, *lead, N))
            out = J.transpose(1, *range(2, J.ndim), 0)  # (P, B, N, 3)
        else:
            out = np.empty((lay.size, N, 3))
            J = _first(out)
        cols = J[:, : G * n].reshape(3, n, G, *lead, N)
        for g in range(G):
            self._row_columns(g, slice(None), cols[:, :, g])
        if not _static(self.model).serial:
            cols *= self.on_path.reshape(n, 1, *(1,) * len(lead), N)
        for s in range(lay.n_setups):
            self._base_columns(s, J[:, lay.base(s)])
        for t in range(lay.n_targets):
            self._tool_columns(t, J[:, lay.tool(t)])
        return out.transpose(*range(1, out.ndim), 0)

    def jacobian_columns(self, idx: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """jacobian()[:, :, idx] for one parameter vector, computing those columns alone (a fit's free parameters:
        Agile Justin's 76 of 173, Hilti's 65 of 157), each by the same arithmetic as jacobian(): the same bits.
        Returned (N, 3, len(idx)) C-contiguous, as jacobian()[:, :, idx] is; or written into `out`, a
        (len(idx), N, 3) array (parameters first, as jacobian() lays them out), and returned as its (N, 3, len(idx))
        view."""
        if self._p.ndim != 2:
            raise ValueError("jacobian_columns takes one parameter vector; jacobian() takes several")
        n, N, lay = self.model.n_joints, self.N, self.layout
        idx = np.asarray(idx, int)
        if out is None:
            res = np.empty((N, 3, len(idx)))
            J = res.transpose(1, 2, 0)  # (3, len(idx), N)
        else:
            res, J = out.transpose(1, 2, 0), _first(out)
        serial = _static(self.model).serial
        rows = idx < G * n
        for g in range(G):
            mine = rows & (idx % G == g)
            if mine.any():
                j = idx[mine] // G
                col = self._row_columns(g, j, np.empty((3, len(j), N)))
                J[:, mine] = col if serial else col * self.on_path[j]
        for s in range(lay.n_setups):
            mine = (idx >= lay.base(s).start) & (idx < lay.base(s).stop)
            if mine.any():
                J[:, mine] = self._base_columns(s, np.empty((3, 6, N)))[:, idx[mine] - lay.base(s).start]
        for t in range(lay.n_targets):
            mine = (idx >= lay.tool(t).start) & (idx < lay.tool(t).stop)
            if mine.any():
                J[:, mine] = self._tool_columns(t, np.empty((3, 3, N)))[:, idx[mine] - lay.tool(t).start]
        return res

    _ROW_KINDS = (("_x_prev", None), ("_x_prev", "_o_prev"), ("_z_axis", None), ("_z_axis", "_o_theta"),
                  ("_y_beta", "_o_beta"), ("_y_prev", "_o_theta"), ("_y_prev", None))
    """Per row parameter (a_{i-1}, alpha_{i-1}, d_i, theta_i, beta_i, gamma_i, b_i): the axis it translates along, or
    turns about through the origin given (gamma_i about y through the joint axis)."""

    def _row_columns(self, g: int, rows, out: np.ndarray) -> np.ndarray:
        """The columns of row parameter kind g for `rows` (a slice or indices), components first (3, rows, [B,] N),
        written into out."""
        axis, origin = (getattr(self, a) if a else None for a in self._ROW_KINDS[g])
        if origin is None:
            out[...] = axis[rows].swapaxes(0, 1)
        else:
            _cross_into(out, axis[rows].swapaxes(0, 1), self._p[:, None] - origin[rows].swapaxes(0, 1))
        return out

    def _base_columns(self, s: int, b: np.ndarray) -> np.ndarray:
        """Setup s's base columns (3, 6, [B,] N) written into b: translations, then the turns about the world axes rx,
        ry, rz (zero on the other setups' poses)."""
        axes = self._turns[..., s, :, :]
        dp = self._p - _first(self.bases[..., s, :3])[..., None]
        b[:, :3] = 0.0
        b[0, 0] = b[1, 1] = b[2, 2] = 1.0
        for k in range(3):
            _cross_into(b[:, 3 + k], _first(axes[..., k, :])[..., None], dp)
        if self.layout.n_setups > 1:
            b *= self.setup == s
        return b

    def _tool_columns(self, t: int, tc: np.ndarray) -> np.ndarray:
        """Target t's tool columns (3, 3, [B,] N) written into tc: d p_c / d tool_k is axis k's component c (zero on
        the other targets' poses)."""
        tc[:] = self._R_end.swapaxes(0, 1)
        if self.layout.n_targets > 1:
            tc *= self.target == t
        return tc

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
