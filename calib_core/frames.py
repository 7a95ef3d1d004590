"""Exact folding of a serial chain given as arbitrary rigid transforms into contract MD-H rows.

Robot descriptions (URDF, rokin, vendor CAD) place every joint with an arbitrary fixed
transform; the contract (section 1) wants MD-H rows
``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i [+q]) Tz(d_i [+q]) Ry(beta_i)``.
This module does the rewrite exactly (to rounding), so nobody folds fixed frames by hand.

Two ways in, one way out:

* :func:`fold_links`: a list of :class:`Link` (a fixed 4x4 transform followed by a joint
  that rotates about / slides along its local z, the rokin / URDF way; ``"fixed"`` links
  only add their transform), the measured point in the frame after the last link.
* :func:`fold_axes`: every joint axis at the zero configuration as a :class:`Axis`
  (point + direction in the original base frame, or :meth:`Axis.from_frame`), plus
  the measured point in base coordinates at the zero configuration.

Both return a :class:`Folded`: MD-H rows ``(a, alpha, d, theta, beta)`` per joint (lengths
in the unit of the input, angles in rad), the tool point in the last MD-H frame, and
``base``: the 4x4 pose of the MD-H base frame in the original base frame, so that for
every joint vector q

    original_point(q) = base @ mdh_point(q)        and     gravity_mdh = base[:3, :3].T @ gravity.

:meth:`Folded.model_dict` writes contract model JSON.

Construction (standard, see Craig ch. 3 and Hayati 1983/1985): between consecutive axes
i and i+1

* not parallel: the common normal gives ``a_i`` (>= 0) and ``alpha_i``; the foot of the
  normal on axis i fixes ``d_i`` and the normal's direction ``theta_i``; ``beta_i = 0``.
  Intersecting axes (``a_i = 0``): the normal is ``z_i x z_{i+1}``, signed to stay
  closest to the incoming x axis (so ``theta_i`` stays small).
* parallel or nearly so (``|sin| < parallel_tol``, Hayati): the common normal is not
  unique (or lies far away, which makes ``d`` huge and ill-conditioned). Keep ``d_i = 0``
  (the origin stays where the previous row landed), go along x perpendicular to axis i+1
  to meet it (``a_i``), and take up the residual tilt with ``beta_i``, the rotation
  about the new y that closes row i (``Ry(beta_i)`` in calib_core.model). Coincident
  axes keep the incoming x axis (``theta_i = 0``, ``a_i = 0``).

The original base frame's z axis is treated as a virtual axis 0, so ``base`` is
``Rz(theta_0) Tz(d_0) Ry(beta_0)`` of the original base: a base whose z is the first
joint axis (the usual case) is kept unchanged (``base`` = identity) and a z-up base keeps
its gravity ``[0, 0, -g]`` exactly (beta_0 is non-zero only when the first axis is
*nearly*, not exactly, parallel to the base z). The last joint gets ``theta_n = d_n =
beta_n = 0``: its frame is where the previous row lands; the tool point absorbs the rest.

Exactness: at q = 0 each MD-H joint frame's z line coincides (point and direction) with
the original joint axis and the tool points agree, so by the product of exponentials both
chains give the same point for every q. Rigid transforms are required (see
:func:`nearest_rotation` for published matrices rounded to three digits).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

PARALLEL_SIN = 1e-6
"""Consecutive axes with |sin(angle)| below this are treated as parallel (Hayati's beta)."""
ZERO_REL = 1e-12
"""Lengths below this fraction of the chain's size (and angles below this many rad) are written as 0."""
RIGID_TOL = 1e-9
"""Largest |R^T R - I| entry accepted for a rotation."""

JOINT_TYPES = ("revolute", "prismatic")


# --- elementary transforms -------------------------------------------------------------

def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1.0, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])


def trans(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def mdh_transform(a: float, alpha: float, d: float, theta: float, beta: float = 0.0, gamma: float = 0.0,
                  b: float = 0.0) -> np.ndarray:
    """One contract MD-H row as a 4x4: Rx(alpha) Tx(a) Ry(gamma) Ty(b) Rz(theta) Tz(d) Ry(beta) (joint value already
    added; gamma and b, model.GEOMETRIC's completing pair, are 0 in a plain MD-H row)."""
    return rot_x(alpha) @ trans(a) @ rot_y(gamma) @ trans(y=b) @ rot_z(theta) @ trans(z=d) @ rot_y(beta)


def nearest_rotation(T: Sequence) -> np.ndarray:
    """The rigid transform nearest to T (4x4 or 3x3, polar decomposition of the rotation part).

    For published frames whose rotation entries were rounded (0.866 for cos 30 deg):
    the fold requires rigid transforms and refuses others."""
    T = np.array(T, dtype=float)
    R = T[:3, :3]
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    out = np.eye(4) if T.shape == (4, 4) else np.eye(3)
    out[:3, :3] = Rn
    if T.shape == (4, 4):
        out[:3, 3] = T[:3, 3]
    return out


def _check_rigid(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: a 4x4 homogeneous transform is needed, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: non-finite entries")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > RIGID_TOL or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise ValueError(f"{what}: not a rigid transform (|R^T R - I| = {err:.2g}, det {np.linalg.det(R):.6g}); "
                         "use frames.nearest_rotation for rounded published matrices")
    return T


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


# --- inputs ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Axis:
    """A joint axis at the zero configuration, in the original base frame.

    ``point``: any point on the axis; ``direction``: the positive joint direction (need not be unit).
    ``limits``: (lo, hi) in rad (revolute) or the input length unit (prismatic), or None.
    """

    point: Sequence[float]
    direction: Sequence[float]
    type: str = "revolute"
    name: str | None = None
    limits: tuple[float, float] | None = None

    @classmethod
    def from_frame(cls, T: Sequence, type: str = "revolute", name: str | None = None,
                   limits: tuple[float, float] | None = None) -> "Axis":
        """The z axis of a 4x4 frame given in the base frame."""
        T = _check_rigid(np.asarray(T, float), f"axis {name or ''} frame")
        return cls(T[:3, 3].copy(), T[:3, 2].copy(), type, name, limits)


@dataclass(frozen=True)
class Link:
    """A fixed 4x4 transform from the previous link's frame (after its joint motion) followed by a joint
    about / along the local z of the resulting frame; ``type="fixed"`` adds the transform only."""

    transform: Sequence
    type: str = "revolute"
    name: str | None = None
    limits: tuple[float, float] | None = None


def links_to_axes(links: Iterable[Link], tool: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[list[Axis], np.ndarray]:
    """The joint axes at q = 0 in the base frame and the tool point in base coordinates."""
    T = np.eye(4)
    axes: list[Axis] = []
    for k, link in enumerate(links):
        if link.type not in (*JOINT_TYPES, "fixed"):
            raise ValueError(f"link {k} ({link.name}): type must be revolute, prismatic or fixed, not {link.type!r}")
        T = T @ _check_rigid(link.transform, f"link {k} ({link.name or ''})")
        if link.type != "fixed":
            axes.append(Axis(T[:3, 3].copy(), T[:3, 2].copy(), link.type, link.name, link.limits))
    return axes, T[:3, :3] @ np.asarray(tool, float) + T[:3, 3]


def chain_point(links: Sequence[Link], q: np.ndarray, tool: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The tool point (N, 3) in the original base frame by plain 4x4 products, q (N, n_joints)."""
    q = np.atleast_2d(np.asarray(q, float))
    out = np.empty((len(q), 3))
    t = np.r_[np.asarray(tool, float), 1.0]
    for i, qi in enumerate(q):
        T, j = np.eye(4), 0
        for link in links:
            T = T @ np.asarray(link.transform, float)
            if link.type == "revolute":
                T = T @ rot_z(qi[j])
                j += 1
            elif link.type == "prismatic":
                T = T @ trans(z=qi[j])
                j += 1
        out[i] = (T @ t)[:3]
    return out


# --- output ----------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Folded:
    """A chain in contract MD-H form.

    ``rows`` (n, 5): a_{i-1}, alpha_{i-1}, d_i, theta_i, beta_i (input length unit, rad).
    ``tool``: the measured point in the last MD-H frame. ``base``: 4x4 pose of the MD-H base
    frame in the original base frame. ``gravity``: the given gravity rotated into the MD-H base.
    """

    names: tuple[str, ...]
    prismatic: np.ndarray
    rows: np.ndarray
    tool: np.ndarray
    base: np.ndarray
    gravity: np.ndarray
    limits: tuple[tuple[float, float] | None, ...]

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def frames(self, q: Sequence[float]) -> list[np.ndarray]:
        """The MD-H joint frames (after Ry(beta_i)) for one joint vector, in the MD-H base frame."""
        T, out = np.eye(4), []
        for (a, alpha, d, theta, beta), pri, qi in zip(self.rows, self.prismatic, q):
            row = (a, alpha, d + qi, theta, beta) if pri else (a, alpha, d, theta + qi, beta)
            T = T @ mdh_transform(*row)
            out.append(T)
        return out

    def forward(self, q: np.ndarray, original_base: bool = True) -> np.ndarray:
        """The tool point (N, 3) for joints q (N, n) (rad / input length), by plain 4x4 products;
        in the original base frame unless ``original_base`` is False (then in the MD-H base)."""
        q = np.atleast_2d(np.asarray(q, float))
        B = self.base if original_base else np.eye(4)
        t = np.r_[self.tool, 1.0]
        return np.array([(B @ self.frames(qi)[-1] @ t)[:3] for qi in q])

    def model_dict(self, name: str, *, length_unit: str = "mm", angle_unit: str = "deg",
                   limits: Sequence[tuple[float, float] | None] | None = None) -> dict:
        """Contract model JSON (``"convention": "mdh"``).

        Lengths are written as they are (``length_unit`` only declares the unit the input used);
        angles and revolute limits are converted from rad when ``angle_unit="deg"``. ``limits``
        overrides the joints' limits (same units as the input: rad / length); a revolute joint
        without limits gets none (unbounded), a prismatic joint must have them.
        """
        if length_unit not in ("mm", "m") or angle_unit not in ("deg", "rad"):
            raise ValueError("length_unit must be 'mm' or 'm' and angle_unit 'deg' or 'rad'")
        ang = math.degrees if angle_unit == "deg" else float
        lims = self.limits if limits is None else tuple(limits)
        if len(lims) != self.n_joints:
            raise ValueError(f"{len(lims)} limits for {self.n_joints} joints")
        joints = []
        for j, jname in enumerate(self.names):
            a, alpha, d, theta, beta = (float(v) for v in self.rows[j])
            row = {"name": jname, "type": "prismatic" if self.prismatic[j] else "revolute",
                   "a": a, "alpha": ang(alpha), "d": d, "theta": ang(theta), "beta": ang(beta)}
            lim = lims[j]
            if lim is not None:
                conv = float if self.prismatic[j] else ang
                row["limits"] = [conv(float(lim[0])), conv(float(lim[1]))]
            elif self.prismatic[j]:
                raise ValueError(f"joint {jname}: a prismatic joint needs limits")
            joints.append(row)
        return {"name": name, "convention": "mdh", "units": {"length": length_unit, "angle": angle_unit},
                "joints": joints, "tool": [float(v) for v in self.tool],
                "gravity": [float(v) for v in self.gravity]}


# --- the fold --------------------------------------------------------------------------

def _step(L: np.ndarray, p: np.ndarray, u: np.ndarray, tol: float, eps: float):
    """From the landing frame L (z = current axis, origin on it) to the next axis (p, u).

    Returns theta, d, beta (closing the current row), alpha, a (opening the next row)."""
    o, x0, y0, z = L[:3, 3], L[:3, 0], L[:3, 1], L[:3, 2]
    cr = np.cross(z, u)
    s = np.linalg.norm(cr)
    if s >= tol:  # skew or intersecting: the common normal
        n = cr / s
        a = float((p - o) @ n)
        if abs(a) <= eps:  # intersecting: keep the normal closest to the incoming x
            if n @ x0 < 0:
                n, a = -n, -a
        elif a < 0:
            n, a = -n, -a
        b, w = float(z @ u), o - p
        t = (b * float(u @ w) - float(z @ w)) / (1.0 - b * b)
        d = t
        x1 = _unit(n - (n @ z) * z)
        beta = 0.0
        xp = x1
    else:  # parallel (Hayati): stay at d = 0, reach the next axis perpendicular to it, tilt with beta
        d = 0.0
        X = p + ((o - p) @ u) * u
        nvec = X - o
        nvec = nvec - (nvec @ u) * u
        a = float(np.linalg.norm(nvec))
        if a <= eps:  # coincident: keep the incoming x
            xp = _unit(x0 - (x0 @ u) * u)
            a = float(nvec @ xp)
        else:
            xp = nvec / a
        x1 = _unit(xp - (xp @ z) * z)
        beta = math.atan2(-float(xp @ z), float(xp @ x1))
    theta = math.atan2(float(x1 @ y0), float(x1 @ x0))
    F = L @ rot_z(theta) @ trans(z=d) @ rot_y(beta)
    uf = F[:3, :3].T @ u
    alpha = math.atan2(-float(uf[1]), float(uf[2]))
    return theta, d, beta, alpha, a


def _clean(v: float, scale: float) -> float:
    return 0.0 if abs(v) <= ZERO_REL * scale else float(v)


def _angle(v: float) -> float:
    """An angle from atan2, written 0 when negligible and +pi (not -pi) for a half turn (same rotation)."""
    if v <= -math.pi + ZERO_REL:
        v += 2.0 * math.pi
    return _clean(v, 1.0)


def fold_axes(axes: Sequence[Axis], tool: Sequence[float] = (0.0, 0.0, 0.0), *,
              gravity: Sequence[float] = (0.0, 0.0, -9.81), parallel_tol: float = PARALLEL_SIN) -> Folded:
    """Fold joint axes at q = 0 (base frame) and the tool point (base coordinates at q = 0) into MD-H rows."""
    if not axes:
        raise ValueError("the chain needs at least one joint")
    pts = [np.asarray(ax.point, float) for ax in axes]
    dirs = []
    for k, ax in enumerate(axes):
        if ax.type not in JOINT_TYPES:
            raise ValueError(f"axis {k} ({ax.name}): type must be revolute or prismatic, not {ax.type!r}")
        v = np.asarray(ax.direction, float)
        if v.shape != (3,) or pts[k].shape != (3,) or not np.all(np.isfinite(np.r_[v, pts[k]])) \
                or np.linalg.norm(v) == 0:
            raise ValueError(f"axis {k} ({ax.name}): point and direction must be finite 3-vectors, direction non-zero")
        dirs.append(_unit(v))
    tool = np.asarray(tool, float)
    scale = max(1.0, max(float(np.linalg.norm(p)) for p in pts), float(np.linalg.norm(tool)))
    eps = ZERO_REL * scale
    n = len(axes)
    rows = np.zeros((n, 5))
    # virtual axis 0: the original base z; its theta, d, beta place the MD-H base frame
    L = np.eye(4)
    th0, d0, b0, alpha, a = _step(L, pts[0], dirs[0], parallel_tol, eps)
    th0, d0, b0 = _angle(th0), _clean(d0, scale), _angle(b0)
    base = rot_z(th0) @ trans(z=d0) @ rot_y(b0)
    F = base
    for i in range(n):
        alpha, a = _angle(alpha), _clean(a, scale)
        L = F @ rot_x(alpha) @ trans(a)
        if i + 1 < n:
            theta, d, beta, alpha_next, a_next = _step(L, pts[i + 1], dirs[i + 1], parallel_tol, eps)
        else:
            theta, d, beta, alpha_next, a_next = 0.0, 0.0, 0.0, 0.0, 0.0
        theta, d, beta = _angle(theta), _clean(d, scale), _angle(beta)
        rows[i] = (a, alpha, d, theta, beta)
        F = L @ rot_z(theta) @ trans(z=d) @ rot_y(beta)
        alpha, a = alpha_next, a_next
    tool_mdh = (np.linalg.inv(F) @ np.r_[tool, 1.0])[:3]
    names = tuple(ax.name or f"J{k + 1}" for k, ax in enumerate(axes))
    return Folded(names=names, prismatic=np.array([ax.type == "prismatic" for ax in axes]), rows=rows,
                  tool=tool_mdh, base=base, gravity=base[:3, :3].T @ np.asarray(gravity, float),
                  limits=tuple(None if ax.limits is None else (float(ax.limits[0]), float(ax.limits[1]))
                               for ax in axes))


def fold_links(links: Sequence[Link], tool: Sequence[float] = (0.0, 0.0, 0.0), *,
               gravity: Sequence[float] = (0.0, 0.0, -9.81), parallel_tol: float = PARALLEL_SIN) -> Folded:
    """Fold a chain of links (fixed transform, then joint about local z) into MD-H rows.

    ``tool``: the measured point in the frame after the last link (a trailing ``"fixed"`` link
    such as a flange / TCP frame is allowed). ``gravity``: in the original base frame."""
    axes, tool_base = links_to_axes(links, tool)
    return fold_axes(axes, tool_base, gravity=gravity, parallel_tol=parallel_tol)
