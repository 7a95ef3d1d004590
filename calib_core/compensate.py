"""Compensation: per-target joint commands that put the tool where the program wants, with the calibrated model.

The residual of every iteration is the full calibrated prediction (`CalibratedRobot.predict`: geometry
plus every identified effect), so a deflection that depends on the pose it produces is solved for, not
added afterwards: the fixed point satisfies  predict(q) = target  exactly, whatever the step Jacobian.
The step Jacobian is the chain's joint Jacobian at the effective joints q + dq (effects change slowly with
q: they only slow the convergence by their tiny derivative, never bias it).

Per target, the answer is the joint command nearest the seed (the program's own joints) in a joint-space
metric where 1 rad weighs like 1000 mm of a prismatic joint, within the joint limits:

* Gauss-Newton on  min |z - z_seed|^2  s.t.  f(z) = target  (z the scaled joints): every step is the
  damped minimum-norm correction plus the null-space pull toward the seed,
  dz = J^T (J J^T + lambda^2 I)^-1 e + (I - J^+ J) pull,  pull = z_seed - z
  (the projector undamped, so the pull never biases where the target is met; a target whose residual stops
  shrinking has its pull halved, which settles the chase between pull and correction near a fold).
  The seed is clipped into the limits first, so the pull also leads back inside them.
* `locked` joints (e.g. the telescopic J6, as in Wang et al. 2023, section 6) stay at their seed; the
  others solve the position (3 constraints).
* A step that would leave the limits is clamped and that joint stays at its limit from then on (active set).
* A target not within `tol_mm` after `max_iter` iterations is reported (`reachable` False, `reason`),
  never raised: one bad target does not fail the batch.

Everything is vectorised over targets: one batched 3x3 solve per iteration for all the targets still moving.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from . import kinematics as K
from .identify import CalibratedRobot
from .io import Measurements
from .model import RobotModel

RAD_PER_MM = 1e-3
"""Joint-space metric: 1 rad of a revolute joint weighs like 1000 mm of a prismatic joint."""
MAX_STEP = 0.25
"""Trust region per iteration in scaled joints (0.25 rad / 250 mm)."""
DAMPING = 1e-8
"""lambda^2 relative to the mean squared singular value of the (scaled) Jacobian: steadies singular poses,
leaves well-conditioned ones unbiased (relative bias ~ lambda^2 / sigma_min^2)."""
PULL_BACKOFF = 0.5
"""A target whose residual shrinks by less than this factor in one iteration has its null-space pull halved
(curvature: the pull back toward the seed and the correction can chase each other near a fold)."""


@dataclass
class Compensation:
    """Corrected joint commands, internal units (rad / mm), one row per target."""

    joints: np.ndarray  # (N, n_act) the command of the actuated joints nearest the seed, always within the limits
    residual_mm: np.ndarray  # (N,) the calibrated model's distance to the target at `joints`
    reachable: np.ndarray  # (N,) bool: residual within tolerance
    reason: list[str | None]  # None where reachable, else why not
    iterations: np.ndarray  # (N,) iterations used per target

    def to_dict(self, model: RobotModel) -> dict:
        """The contract answer (joints in the model's units, NaN-free) plus the per-target status."""
        return {"joints": (self.joints / model.joint_scale()[model.actuated]).tolist(),
                "residual_mm": [float(r) if np.isfinite(r) else None for r in self.residual_mm],
                "reachable": self.reachable.tolist(), "reason": list(self.reason)}


def compensate(
    robot: CalibratedRobot,
    targets_mm: np.ndarray,
    seed_joints: np.ndarray,
    *,
    locked: Sequence[int | str] = (),
    columns: Measurements | None = None,
    tol_mm: float = 1e-3,
    max_iter: int = 30,
) -> Compensation:
    """Commands of the actuated joints (N, n_act) for which the calibrated model puts each row's target there.

    targets_mm (N, 3): points in the measurement frame. seed_joints (N, n_act), internal units: the program's
    actuated joints (the nominal solution); the answer is the command nearest to them. Coupled joints follow
    their coupling at every iterate (a coupling is never broken) and fixed rows stay fixed. locked: actuated
    joint indices or names that stay at their seed value (redundancy resolution by locking); with none, the
    redundant joints follow the damped least-squares null-space pull toward the seed. columns: which model
    target each row is (`target`), its setup, and payload / temperature / timestamp for the effects that need
    them (its joints are ignored).
    Raises ValueError only for malformed input arrays; per-target failures are reported in the answer.
    """
    model = robot.model
    act = model.actuated
    n = len(act)
    A = model.coupling_matrix()  # (rows, n_act): the chain's joint Jacobian -> the actuated joints'
    T = np.asarray(targets_mm, float).reshape(-1, 3)
    seed = np.atleast_2d(np.asarray(seed_joints, float))
    if seed.shape != (len(T), n):
        raise ValueError(f"seed_joints must be ({len(T)}, {n}) for {len(T)} targets, got {seed.shape}")
    if columns is not None and columns.n_poses != len(T):
        raise ValueError(f"columns hold {columns.n_poses} rows for {len(T)} targets")
    N = len(T)
    lock = _joint_indices(model, locked)
    lo, hi = model.limits[act, 0], model.limits[act, 1]
    scale = np.where(model.prismatic[act], 1.0 / RAD_PER_MM, 1.0)
    names = model.actuated_names

    reason: list[str | None] = [None] * N
    ok = np.isfinite(T).all(1) & np.isfinite(seed).all(1)
    for i in np.flatnonzero(~ok):
        reason[i] = "target or seed joints are not finite"
    q = np.clip(np.where(np.isfinite(seed), seed, 0.0), lo, hi)
    if lock:
        out = (seed[:, lock] < lo[lock]) | (seed[:, lock] > hi[lock])
        for i in np.flatnonzero(ok & out.any(1)):
            held = ", ".join(names[lock[k]] for k in np.flatnonzero(out[i]))
            reason[i] = f"locked joint(s) {held}: seed outside the joint limits"
        ok &= ~out.any(1)
    ref = q.copy()  # the seed within the limits: what the null-space pull leads back to

    fixed = np.zeros((N, n), bool)
    fixed[:, lock] = True
    at_limit = np.zeros((N, n), bool)
    residual = np.full(N, np.nan)
    iterations = np.zeros(N, int)
    gain = np.ones(N)  # null-space pull gain, halved for a target whose residual stops shrinking
    prev = np.full(N, np.inf)
    best_r, best_q = np.full(N, np.inf), q.copy()  # an unreachable target gets its closest iterate
    active = ok.copy()
    for it in range(max_iter + 1):
        idx = np.flatnonzero(active)
        if not idx.size:
            break
        rows = model.expand_joints(q[idx])
        p, J = _point_and_jacobian(robot, rows, _rows(columns, idx, rows))
        J = J @ A
        e = T[idx] - p
        r = np.sqrt((e**2).sum(1))
        residual[idx] = r
        iterations[idx] = it
        better = r < best_r[idx]
        best_r[idx[better]], best_q[idx[better]] = r[better], q[idx[better]]
        moving = r > tol_mm
        active[idx[~moving]] = False
        if it == max_iter:
            break
        idx, e, J = idx[moving], e[moving], J[moving]
        free = ~fixed[idx]
        Jz = J * scale * free[:, None, :]  # (m, 3, n) in scaled joints, fixed joints removed
        slow = r[moving] > PULL_BACKOFF * prev[idx]
        gain[idx[slow]] *= 0.5
        prev[idx] = r[moving]
        pull = gain[idx, None] * (ref[idx] - q[idx]) / scale * free
        dz = pull + np.einsum("mji,mj->mi", Jz, _solve_3x3(Jz, e, np.einsum("mij,mj->mi", Jz, pull)))
        norm = np.sqrt((dz**2).sum(1))
        dz *= np.minimum(1.0, MAX_STEP / np.maximum(norm, 1e-300))[:, None]
        qn = q[idx] + dz * scale
        hit = (qn < lo) | (qn > hi)
        q[idx] = np.clip(qn, lo, hi)
        fixed[idx] |= hit
        at_limit[idx] |= hit

    reachable = ok & (residual <= tol_mm)
    miss = np.flatnonzero(ok & ~reachable)
    q[miss], residual[miss] = best_q[miss], best_r[miss]
    for i in miss:
        stuck = [names[j] for j in np.flatnonzero(at_limit[i] & ((q[i] <= lo) | (q[i] >= hi)))]
        if stuck:
            where = f"needs {', '.join(stuck)} beyond {'its limit' if len(stuck) == 1 else 'their limits'}"
        elif residual[i] < 0.9 * prev[i]:
            where = f"still converging: raise max_iter above {max_iter}"
        else:
            where = "out of reach or at a singular pose"
        if lock:
            where += f"; with {', '.join(names[j] for j in lock)} locked"
        reason[i] = f"not reachable: {residual[i]:.3f} mm left after {iterations[i]} iterations ({where})"
    return Compensation(joints=q, residual_mm=residual, reachable=reachable, reason=reason, iterations=iterations)


def nominal_to_calibrated(
    robot: CalibratedRobot,
    nominal_model: RobotModel | None,
    program_joints: np.ndarray,
    *,
    locked: Sequence[int | str] = (),
    columns: Measurements | None = None,
    tol_mm: float = 1e-3,
    max_iter: int = 30,
) -> Compensation:
    """A program given as joints only: the commands that make the real robot reach where the nominal model
    said it would.

    Frame convention: the nominal model (geometry and tool exactly as in the model file, default
    `robot.model`) is evaluated at `program_joints` in its own base frame; that point is then placed in the
    measurement frame by the CALIBRATED base pose (the identified base frame, `Calibration.base_pose()`),
    and `compensate` solves for it with the program joints as seeds. So the program's points are kept
    relative to the robot's calibrated base: what the offline program meant in robot coordinates is what
    the robot does. (Parameters that only the base can carry, e.g. J1.d against base.z on the spray7, sit
    in the calibrated base pose, so "the base frame" is the one the calibration defines.)
    """
    nominal_model = robot.model if nominal_model is None else nominal_model
    if nominal_model.joint_names != robot.model.joint_names:
        raise ValueError("the nominal model must have the calibrated robot's joints, in the same order")
    q = np.atleast_2d(np.asarray(program_joints, float))
    targets = nominal_targets(robot, nominal_model, q, columns)
    return compensate(robot, targets, q, locked=locked, columns=columns, tol_mm=tol_mm, max_iter=max_iter)


def nominal_targets(robot: CalibratedRobot, nominal_model: RobotModel, program_joints: np.ndarray,
                    columns: Measurements | None = None) -> np.ndarray:
    """Nominal target points (N, 3) of the program (actuated joints) in the measurement frame, via the calibrated
    base pose of each row's setup (`columns`: target and setup per row; default the first of each)."""
    lay = K.layout(robot.model, robot.x)
    labels = None if columns is None else columns.labels
    setup = np.zeros(len(program_joints), int) if labels is None else labels.setup
    at_base = None if labels is None else K.Labels(labels.target, np.zeros_like(labels.setup))
    p_base = K.forward(nominal_model, K.nominal_vector(nominal_model), nominal_model.expand_joints(program_joints),
                       None, at_base)
    out = np.empty_like(p_base)
    for s in np.unique(setup):
        base = robot.x[lay.base(s)]
        Rb = K.base_rotation(base, robot.R0 if robot.R0.ndim == 2 else robot.R0[s])
        out[setup == s] = p_base[setup == s] @ Rb.T + base[:3]
    return out


def _joint_indices(model: RobotModel, joints: Sequence[int | str]) -> list[int]:
    """Indices into the actuated joints of names or indices (coupled and fixed rows cannot be locked)."""
    names, out = model.actuated_names, []
    for j in joints:
        if isinstance(j, str):
            if j not in names:
                why = "it follows its coupling" if j in model.joint_names else "unknown joint"
                raise ValueError(f"cannot lock {j!r} ({why}); the actuated joints are {', '.join(names)}")
            out.append(names.index(j))
        else:
            if not -len(names) <= int(j) < len(names):
                raise ValueError(f"joint index {j} out of range for {len(names)} actuated joints")
            out.append(int(j) % len(names))
    return sorted(set(out))


def _rows(columns: Measurements | None, idx: np.ndarray, q: np.ndarray) -> Measurements:
    """The measurement columns of these targets, with the current joints (effects read meas.joints)."""
    pick = lambda a: None if a is None else a[idx]  # noqa: E731
    if columns is None:
        return Measurements(joints=q, points=np.zeros((len(q), 3)))
    return Measurements(joints=q, points=np.zeros((len(q), 3)), timestamp=pick(columns.timestamp),
                        temperature=pick(columns.temperature), payload=pick(columns.payload),
                        target=pick(columns.target), setup=pick(columns.setup), setup_names=columns.setup_names)


def _solve_3x3(Jz: np.ndarray, e: np.ndarray, Jpull: np.ndarray) -> np.ndarray:
    """(J J^T + lambda^2)^-1 e  -  (J J^T)^+ J pull, batched via the 3x3 eigen-decomposition of J J^T.

    The damping acts on the correction only; the null-space projection of the pull uses the undamped
    inverse, so the pull cannot leak into the task space and bias the fixed point (directions with a
    singular value below 1e-6 of the largest are left out of both)."""
    w, U = np.linalg.eigh(Jz @ np.swapaxes(Jz, 1, 2))
    lam2 = DAMPING * w.sum(1, keepdims=True) / 3 + 1e-12
    keep = w > 1e-12 * w[:, -1:]
    damped = np.where(keep, 1.0 / (w + lam2), 0.0)
    proj = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    ue, up = np.einsum("mji,mj->mi", U, e), np.einsum("mji,mj->mi", U, Jpull)
    return np.einsum("mij,mj->mi", U, damped * ue - proj * up)


def _point_and_jacobian(robot: CalibratedRobot, q: np.ndarray, cols: Measurements):
    """The calibrated prediction (exactly `robot.predict(q, cols)`) and dp/dq at the effective joints."""
    if not robot.effects:
        ch = K.Chain(robot.model, robot.x, q, robot.R0, cols.labels)
        return ch.p, ch.joint_jacobian()
    dq, dp = robot.effect_offsets(q, cols)
    ch = K.Chain(robot.model, robot.x, q + dq, robot.R0, cols.labels)
    return ch.p + dp, ch.joint_jacobian()
