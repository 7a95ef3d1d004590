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
  A coupled joint's own limits bound a linear combination of the actuated joints (its row of the coupling
  matrix): a step that would take it past them is shortened to the limit, and from then on every step keeps
  it there (the step is projected onto that constraint's null space, like a clamped joint's column removed).
  A seed that puts a coupled joint outside its limits is first moved inside them (alternating projections).
* A target not within `tol_mm` after `max_iter` iterations is reported (`reachable` False, `reason`),
  never raised: one bad target does not fail the batch.

Everything is vectorised over targets: one batched 3x3 solve per iteration for all the targets still moving.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import kinematics as K
from .effects.base import rows_said
from .effects.joint_effects import Backlash
from .identify import CalibratedRobot
from .io import Measurements
from .model import RobotModel
from .uncertainty import switch_doubts

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
PROGRESS_WINDOW = 5
"""Last iterations over which an unreached target's progress is judged: the rate its best residual shrank at there
says how many more iterations would reach the tolerance..."""
MAX_ADVISED_ITER = 200
"""...and a target that would need more than this many in all is called out of reach, not "still converging": the
iiwa's stretched arm (A3-A7 at 0) put measured points 0.03-1.3 mm beyond its reach, their residual the same from
iteration 10 to 120, and the reason asked for more iterations (the service's largest max_iter)."""
FLANK_DOUBT_MM = 0.05
"""A row is named in the flank note (flank_doubts) when not knowing which flank of a gear play it sits on costs more
than this at the tool (RMS)."""


@dataclass
class Compensation:
    """Corrected joint commands, internal units (rad / mm), one row per target."""

    joints: np.ndarray  # (N, n_act) the command of the actuated joints nearest the seed, always within the limits
    residual_mm: np.ndarray  # (N,) the calibrated model's distance to the target at `joints`
    reachable: np.ndarray  # (N,) bool: residual within tolerance
    reason: list[str | None]  # None where reachable, else why not
    iterations: np.ndarray  # (N,) iterations used per target
    notes: list[str] = field(default_factory=list)  # what the answer could not take into account (missing loads)

    def to_dict(self, model: RobotModel) -> dict:
        """The contract answer (joints in the model's units, NaN-free), the per-target status and the notes."""
        return {"joints": (self.joints / model.joint_scale()[model.actuated]).tolist(),
                "residual_mm": [float(r) if np.isfinite(r) else None for r in self.residual_mm],
                "reachable": self.reachable.tolist(), "reason": list(self.reason), "notes": list(self.notes)}


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
    target each row is (`target`), its setup, and payload / temperature / timestamp / tau (measured joint
    torques N*m or N: the load of load-driven causes, NaN: the model's statics) for the effects that need them
    (its joints are ignored).
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
    cc = _CoupledLimits(model, scale)

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
    if cc.k:
        q, bad = cc.make_feasible(q, lo, hi, lock)
        for i in np.flatnonzero(ok & bad):
            reason[i] = f"not reachable: {cc.describe_violation(q[i])}" + (
                f" (with {', '.join(names[j] for j in lock)} locked at the seed)" if lock else "")
        ok &= ~bad
    ref = q.copy()  # the seed within the limits: what the null-space pull leads back to

    fixed = np.zeros((N, n), bool)
    fixed[:, lock] = True
    at_limit = np.zeros((N, n), bool)
    c_active = np.zeros((N, cc.k), bool)  # coupled joints held at a limit (active constraints)
    residual = np.full(N, np.nan)
    iterations = np.zeros(N, int)
    gain = np.ones(N)  # null-space pull gain, halved for a target whose residual stops shrinking
    prev = np.full(N, np.inf)
    best_r, best_q = np.full(N, np.inf), q.copy()  # an unreachable target gets its closest iterate
    mark = max(max_iter - PROGRESS_WINDOW, 0)
    best_at_mark = np.full(N, np.inf)  # best_r as of iteration `mark`: the progress since then (_unreached)
    active = ok.copy()
    for it in range(max_iter + 1):
        idx = np.flatnonzero(active)
        if not idx.size:
            break
        rows = model.expand_joints(q[idx])
        p, Jq, dq, dp = _prediction(robot, rows, _rows(columns, idx, rows))
        J = Jq @ A
        e = T[idx] - p
        r = np.sqrt((e**2).sum(1))
        residual[idx] = r
        iterations[idx] = it
        better = r < best_r[idx]
        best_r[idx[better]], best_q[idx[better]] = r[better], q[idx[better]]
        if it == mark:
            best_at_mark[idx] = best_r[idx]
        moving = r > tol_mm
        active[idx[~moving]] = False
        if it == max_iter:
            break
        idx, e, J = idx[moving], e[moving], J[moving]
        if robot.effects and it >= EXACT_AFTER:  # slow to converge: the effects' own slope too (a smooth field)
            J = J + _effects_jacobian(robot, rows[moving], _rows(columns, idx, rows[moving]), A, Jq[moving],
                                      dq[moving], dp[moving])
        free = ~fixed[idx]
        slow = r[moving] > PULL_BACKOFF * prev[idx]
        gain[idx[slow]] *= 0.5
        prev[idx] = r[moving]
        pull = gain[idx, None] * (ref[idx] - q[idx]) / scale * free
        if cc.k and c_active[idx].any():  # fixed joints and coupled joints at a limit removed from the step
            P = cc.projector(free, c_active[idx])
            Jz = np.einsum("mjk,mki->mji", J * scale, P)
            pull = np.einsum("mik,mk->mi", P, pull)
        else:
            Jz = J * scale * free[:, None, :]  # (m, 3, n) in scaled joints, fixed joints removed
        dz = pull + np.einsum("mji,mj->mi", Jz, _solve_3x3(Jz, e, np.einsum("mij,mj->mi", Jz, pull)))
        norm = np.sqrt((dz**2).sum(1))
        dz *= np.minimum(1.0, MAX_STEP / np.maximum(norm, 1e-300))[:, None]
        qn = q[idx] + dz * scale
        hit = (qn < lo) | (qn > hi)
        if cc.k:  # line search: the step ends at the first limit it meets (a joint's or a coupled joint's)
            q0 = q[idx]
            with np.errstate(divide="ignore", invalid="ignore"):
                t_box = np.where(qn > hi, (hi - q0) / (qn - q0), np.where(qn < lo, (lo - q0) / (qn - q0), np.inf))
            t_box = np.clip(t_box, 0.0, None)
            t_c = cc.crossing(q0, qn)
            t = np.minimum(1.0, np.minimum(t_box.min(1), t_c.min(1, initial=np.inf)))
            hit &= t_box <= t[:, None] + 1e-12  # these joints reach their limit and stay there
            c_active[idx] |= t_c <= t[:, None] + 1e-12  # these coupled joints reach theirs
            qn = q0 + t[:, None] * (qn - q0)
        q[idx] = np.clip(qn, lo, hi)
        fixed[idx] |= hit
        at_limit[idx] |= hit

    reachable = ok & (residual <= tol_mm)
    miss = np.flatnonzero(ok & ~reachable)
    q[miss], residual[miss] = best_q[miss], best_r[miss]
    for i in miss:
        stuck = [names[j] for j in np.flatnonzero(at_limit[i] & ((q[i] <= lo) | (q[i] >= hi)))]
        if cc.k:
            stuck += cc.at_limit_names(q[i], c_active[i])
        if stuck:
            where = f"needs {', '.join(stuck)} beyond {'its limit' if len(stuck) == 1 else 'their limits'}"
        else:
            where = _unreached(residual[i], best_at_mark[i], max_iter - mark, max_iter, tol_mm, bool(robot.effects))
        if lock:
            where += f"; with {', '.join(names[j] for j in lock)} locked"
        reason[i] = f"not reachable: {residual[i]:.3f} mm left after {iterations[i]} iterations ({where})"
    rows = _rows(columns, np.arange(N), model.expand_joints(q))
    notes = robot.notes(rows) + flank_doubts(robot, rows)
    return Compensation(joints=q, residual_mm=residual, reachable=reachable, reason=reason, iterations=iterations,
                        notes=notes)


def flank_doubts(robot: CalibratedRobot, rows: Measurements) -> list[str]:
    """Sentences naming the rows where an identified gear play's flank is in doubt: the load there lies near where
    it changes sign, within what the calibration could tell of that place (Backlash.flank_doubt), so the robot may
    sit elsewhere in the play than the commands assume, by up to the play's swing at the tool. A hard play's cube
    point at 2 % of its joint's load range was commanded on the model's soft flank and landed 0.38 mm off where the
    other four landed within 0.07 mm (RESULTS 4.2): the answer said nothing."""
    out = []
    for e, P, d in switch_doubts(robot, rows):
        if not isinstance(e, Backlash):
            continue
        rms = np.sqrt(P) * np.linalg.norm(d, axis=1)
        doubt = np.flatnonzero(rms > FLANK_DOUBT_MM)
        if doubt.size:
            name = robot.model.joint_names[e.joints[0]]
            out.append(f"{name}'s gear play: at {rows_said(doubt)} the load on {name} is near where it "
                       f"changes sign, so the robot may sit elsewhere in the play than these commands assume: up to "
                       f"{rms.max():.3f} mm RMS at the tool (elsewhere under {FLANK_DOUBT_MM:g} mm); a pose with a "
                       f"clear load on {name}, or a measured tau_{name}, settles it")
    return out


def _unreached(best: float, before: float, span: int, max_iter: int, tol_mm: float, effects: bool) -> str:
    """Why a target the iterations did not reach is unreached, from its best residual (mm) now and `span`
    iterations before: still converging when, shrinking at the rate it did over them, it reaches tol_mm within
    MAX_ADVISED_ITER iterations in all (said with the count). Else, on the geometry alone (a smooth map: a residual
    that stops shrinking sits at its minimum) out of reach; with effects, a cause's switch or slope can hold the
    iterate off for a while (on the iiwa's calibrated model, 76 of 94 such targets were reached in 200 iterations),
    so both are said."""
    if span == 0:
        return f"still converging: raise max_iter above {max_iter}"
    rate = (best / before) ** (1.0 / span) if before > best > 0 else 1.0
    need = max_iter + np.log(tol_mm / best) / np.log(rate) if rate < 1.0 else np.inf  # iterations in all
    if need <= MAX_ADVISED_ITER:
        return f"still converging: raise max_iter above {max_iter} (about {int(np.ceil(need))} at this rate)"
    edge = "the edge of the workspace, such as an arm stretched out, or a singular pose"
    if not effects:
        return f"out of reach near the seed: at the rate it closed in, not within {MAX_ADVISED_ITER} iterations; {edge}"
    return (f"not closing in over the last {span} iterations: out of reach near the seed ({edge}), or held off by a "
            f"cause of the calibrated model (a play's switch, a steep correction): a larger max_iter may reach it")


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


class _CoupledLimits:
    """The limits of the coupled joints as linear inequalities on the actuated joints: lo <= G q + off <= hi,
    G the coupled rows of the coupling matrix (internal units, rad / mm); only coupled joints with a finite limit."""

    TOL = 1e-9
    """rad / mm: how far past its limit a coupled joint may be from rounding alone."""

    def __init__(self, model: RobotModel, scale: np.ndarray):
        A = model.coupling_matrix()
        off = model.expand_joints(np.zeros((1, len(model.actuated))))[0]
        self.rows = [row for row, _, _ in model.coupling if np.isfinite(model.limits[row]).any()]
        self.k = len(self.rows)
        self.G = A[self.rows]  # (k, n_act)
        self.scale = scale
        self.Gz = self.G * scale  # d(coupled value) / d(scaled joints)
        self.off = off[self.rows]
        self.lo, self.hi = model.limits[self.rows, 0], model.limits[self.rows, 1]
        self.model = model

    def value(self, q: np.ndarray) -> np.ndarray:
        """Coupled joint values (N, k), rad / mm, at actuated joints q (N, n_act)."""
        return q @ self.G.T + self.off

    def make_feasible(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, lock: list[int], sweeps: int = 200
                      ) -> tuple[np.ndarray, np.ndarray]:
        """q moved into the coupled limits (and kept in the box, locked joints unchanged) by alternating
        projections in the scaled metric; also a bool (N,) of rows for which no such command was found."""
        q = q.copy()
        movable = np.ones(q.shape[1], bool)
        movable[lock] = False
        Gz = self.Gz * movable
        dq_per = Gz * self.scale  # the scaled step along Gz, back in rad / mm
        for _ in range(sweeps):
            v = self.value(q)
            if not ((v < self.lo - self.TOL) | (v > self.hi + self.TOL)).any():
                break
            for c in range(self.k):
                g2 = float(Gz[c] @ Gz[c])
                if g2 > 0.0:
                    vc = self.value(q)[:, c]
                    q = np.clip(q + np.outer((np.clip(vc, self.lo[c], self.hi[c]) - vc) / g2, dq_per[c]), lo, hi)
        v = self.value(q)
        return q, ((v < self.lo - self.TOL) | (v > self.hi + self.TOL)).any(1)

    def projector(self, free: np.ndarray, active: np.ndarray) -> np.ndarray:
        """(m, n, n): the orthogonal projector (scaled joints) onto the steps that move no fixed joint and no
        coupled joint held at a limit: P = D - Ga^T (Ga Ga^T)^+ Ga, D = diag(free), Ga the active rows of G D."""
        D = free.astype(float)
        Ga = self.Gz[None] * D[:, None, :] * active[:, :, None]  # (m, k, n), inactive rows zero
        M = np.linalg.pinv(Ga @ np.swapaxes(Ga, 1, 2), rcond=1e-10, hermitian=True)
        return D[:, :, None] * np.eye(len(free[0]))[None] - np.swapaxes(Ga, 1, 2) @ M @ Ga

    def crossing(self, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
        """(m, k): the share of the step q0 -> q1 at which each coupled joint reaches the limit it would cross
        (q0 within them), inf where it stays within them."""
        v0, v1 = self.value(q0), self.value(q1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(v1 > self.hi + self.TOL, (self.hi - v0) / (v1 - v0),
                         np.where(v1 < self.lo - self.TOL, (self.lo - v0) / (v1 - v0), np.inf))
        return np.clip(t, 0.0, None)

    def _formula(self, c: int) -> str:
        """'T4 = -T2 - T3' (its coupling in model units) from the coupling matrix."""
        m, row = self.model, self.rows[c]
        js = m.joint_scale()
        text = ""
        for g, a in zip(self.G[c], m.actuated):
            if g != 0:
                k = abs(g) * js[a] / js[row]
                term = f"{'' if np.isclose(k, 1.0) else f'{k:g}*'}{m.joint_names[a]}"
                text += (f"{'-' if g < 0 else ''}{term}" if not text else f" {'-' if g < 0 else '+'} {term}")
        off = self.off[c] / js[row]
        if off:
            text += f" {'-' if off < 0 else '+'} {abs(off):g}" if text else f"{off:g}"
        return f"{m.joint_names[row]} = {text or '0'}"

    def _limits_text(self, c: int) -> str:
        m, row = self.model, self.rows[c]
        js = m.joint_scale()[row]
        return f"[{self.lo[c] / js:g}, {self.hi[c] / js:g}] {m.joint_unit(row)}"

    def at_limit_names(self, q: np.ndarray, active: np.ndarray) -> list[str]:
        """Coupled joints held at a limit at q (n_act,), named with their coupling."""
        v = self.value(q[None])[0]
        at = active & ((v <= self.lo + 1e-6) | (v >= self.hi - 1e-6))
        return [f"the coupled {self._formula(c)}" for c in np.flatnonzero(at)]

    def describe_violation(self, q: np.ndarray) -> str:
        """Why no command keeps the coupled joints within their limits, for one row's q (n_act,)."""
        m = self.model
        v = self.value(q[None])[0]
        bad = np.flatnonzero((v < self.lo - self.TOL) | (v > self.hi + self.TOL))
        return "; ".join(f"the coupled {self._formula(c)} stays outside its limits {self._limits_text(c)} "
                         f"(at best {v[c] / m.joint_scale()[self.rows[c]]:g}) for every command within the "
                         "actuated joints' limits" for c in bad)


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
    """The measurement columns of these targets, with the current joints (effects read meas.joints) and the
    measured torques tau (N*m or N, the load of load-driven causes where given)."""
    pick = lambda a: None if a is None else a[idx]  # noqa: E731
    if columns is None:
        return Measurements(joints=q, points=np.zeros((len(q), 3)))
    return Measurements(joints=q, points=np.zeros((len(q), 3)), timestamp=pick(columns.timestamp),
                        sequence=pick(columns.sequence), temperature=pick(columns.temperature), payload=pick(columns.payload),
                        target=pick(columns.target), setup=pick(columns.setup), setup_names=columns.setup_names,
                        tau=pick(columns.tau))


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


EFFECT_STEP = 1e-5
"""rad / mm: the forward-difference step of the effects' own dependence on the joints in the Jacobian."""
EXACT_AFTER = 2
"""Iterations with the chain's Jacobian alone before the effects' own dependence on the joints is added: most
targets converge before (2 iterations for a joint spring), where it would cost 2-5x per iteration."""


def _prediction(robot: CalibratedRobot, q: np.ndarray, cols: Measurements):
    """The calibrated prediction (exactly `robot.predict(q, cols)`) at rows q (N, n), the chain's joint Jacobian
    (N, 3, n) at the effective joints, and the effects' joint offsets (N, n) and displacements (N, 3) mm."""
    dq, dp = robot.effect_offsets(q, cols) if robot.effects else (np.zeros_like(q), np.zeros((len(q), 3)))
    ch = K.Chain(robot.model, robot.x, q + dq, robot.R0, cols.labels)
    return ch.p + dp, ch.joint_jacobian(), dq, dp


def _effects_jacobian(robot: CalibratedRobot, q: np.ndarray, cols: Measurements, A: np.ndarray, Jq: np.ndarray,
                      dq: np.ndarray, dp: np.ndarray) -> np.ndarray:
    """What the effects' own dependence on the joints adds to the prediction's derivative in the actuated joints
    (N, 3, n_act), by forward differences of their offsets, batched over the joints (A: the coupling matrix). The
    chain's Jacobian alone left a smooth-field correction on the Hilti set 163 of 927 targets short after 30
    steps, up to 7 mm."""
    k, N = A.shape[1], len(q)
    if N == 0:
        return np.zeros((0, 3, k))
    moved = (q[None] + EFFECT_STEP * A.T[:, None, :]).reshape(k * N, -1)  # each actuated joint stepped in turn
    dq1, dp1 = robot.effect_offsets(moved, _rows(cols, np.tile(np.arange(N), k), moved))
    d_dq = (dq1.reshape(k, N, -1) - dq) / EFFECT_STEP  # (k, N, n)
    d_dp = (dp1.reshape(k, N, 3) - dp) / EFFECT_STEP  # (k, N, 3)
    return np.einsum("nir,knr->nik", Jq, d_dq) + d_dp.transpose(1, 2, 0)


def _point_and_jacobian(robot: CalibratedRobot, q: np.ndarray, cols: Measurements, A: np.ndarray):
    """The prediction at rows q and its whole derivative (N, 3, n_act) in the actuated joints, effects included."""
    p, Jq, dq, dp = _prediction(robot, q, cols)
    J = Jq @ A
    if robot.effects:
        J = J + _effects_jacobian(robot, q, cols, A, Jq, dq, dp)
    return p, J

