"""Motion the targets measured at one pose share: whether the residual left moves them together.

Several targets (two hands, several SMRs) measured at the same joint values in the same setup see the robot standing
in one place. What is their own (noise, the joints beyond where their chains part) is independent between them; a
motion upstream of the split moves them together: a joint every target hangs on landing a little differently at each
visit, the base rocking or shifting, the instrument's frame moving between poses. Each such motion u (a rotation of a
shared joint, of the base about one of its axes, a shift along one) moves target a by u_a delta at a pose, so the
projections u_a . r_a and u_b . r_b of two targets' residuals are positively correlated over the poses, and
uncorrelated when the targets' errors are independent, whatever each target's own error looks like (up to the fit's
coupling of the rows, -u_a' Q_a Q_b' u_b from the hat matrix, which is added back). A one-sided rank correlation over
the poses (one pair of targets each) per motion, Bonferroni over the motions; var(delta) from the mean product
(u_a . r_a)(u_b . r_b) / (|u_a|^2 |u_b|^2).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .io import Measurements
from .kinematics import Chain, _cross
from .model import RobotModel
from .orientation import MARK

MIN_POSES = 10
"""Poses with two or more targets needed before the test is made."""
AXES = "xyz"


@dataclass(frozen=True)
class SharedMotion:
    motion: str  # the motion, in words: "T2 turning", "the base tilting about its x axis", ...
    size: float  # its RMS per pose: rad (a rotation) or mm (a shift)
    unit: str  # "rad" or "mm"
    share: float  # fraction of a target's residual mean square it explains (0..1)
    rms_mm: float  # RMS (3-D) of what it moves at one target, mm
    p_value: float  # Bonferroni over the motions tried: the targets' residuals are not related within a pose
    n_poses: int  # poses with two or more targets
    shared_joints: tuple[int, ...]  # moving model rows on the way to every target


def pose_groups(meas: Measurements, model: RobotModel) -> list[np.ndarray]:
    """Rows of every pose measured with several physical targets (Measurements.pose_index: the same setup and joint
    values, each target once; a pose visited again is another placement of the robot, not the same one). The
    virtual points of a 6-D reading (orientation.MARK) are one reading of one target, not targets of their own."""
    if meas.target is None:
        return []
    unit = meas.pose_index()
    real = np.array([MARK not in name for name in model.target_names], bool)[meas.target]
    order = np.argsort(unit, kind="stable")
    order = order[real[order]]
    groups = np.split(order, np.flatnonzero(np.diff(unit[order])) + 1)
    return [g for g in groups if len(g) > 1]


def shared_joints(model: RobotModel) -> tuple[int, ...]:
    """Moving rows every target's chain passes through (the torso of a two-armed robot)."""
    on_way = model.ancestors()[model.target_rows].all(axis=0)
    return tuple(int(j) for j in np.flatnonzero(on_way & np.asarray(model.moving, bool)))


def motions(chain: Chain) -> list[tuple[str, str, np.ndarray]]:
    """(what, unit, displacement per unit (N, 3) mm) of every motion upstream of all targets: each shared joint
    turning (or sliding), the base turning about each of its axes through its origin, and shifting along each."""
    model, n = chain.model, chain.N
    Jq = chain.joint_jacobian()
    Rb = np.broadcast_to(chain.Rb, (n, 3, 3))
    ob = np.broadcast_to(chain.base_origin, (n, 3))
    out = [(f"{model.joint_names[j]} {'sliding' if model.prismatic[j] else 'turning'}",
            "mm" if model.prismatic[j] else "rad", Jq[:, :, j]) for j in shared_joints(model)]
    out += [(f"the base tilting about its {a} axis", "rad", _cross(Rb[:, :, k], chain.p - ob))
            for k, a in enumerate(AXES)]
    out += [(f"the base shifting along its {a} axis", "mm", Rb[:, :, k].copy()) for k, a in enumerate(AXES)]
    return out


def shared_motion(chain: Chain, meas: Measurements, residual_mm: np.ndarray, sigma: np.ndarray,
                  Q: np.ndarray) -> list[SharedMotion] | None:
    """The test over the poses with several targets. chain: the calibrated model at meas' poses; residual_mm (N, 3)
    measured minus predicted; sigma (N,) the fit's 1-sigma per coordinate; Q (3N, r) an orthonormal basis of the
    fit's weighted Jacobian (rows pose-major). Every motion tried, largest share first; None when fewer than
    MIN_POSES poses have two targets."""
    from scipy import stats  # here, not at the top: 0.5 s of import a process that never diagnoses (the API's) skips

    groups = pose_groups(meas, chain.model)
    if len(groups) < MIN_POSES:
        return None
    a, b = np.array([g[:2] for g in groups]).T  # one pair per pose: the poses are the independent units
    w = residual_mm / sigma[:, None]
    Qp = Q.reshape(len(w), 3, -1)
    rows = np.concatenate(groups)
    dof = w.size / max(w.size - Q.shape[1], 1)  # a fitted residual is smaller than the error by the fit's dof
    ms = dof * float(np.mean(np.sum(residual_mm[rows] ** 2, axis=1)))
    found, upstream = [], shared_joints(chain.model)
    cand = motions(chain)
    for what, unit, u in cand:
        uw = u / sigma[:, None]
        na, nb = np.linalg.norm(uw[a], axis=1), np.linalg.norm(uw[b], axis=1)
        if not (np.all(na > 0) and np.all(nb > 0)):
            continue  # a motion that leaves a target still at some pose
        ea, eb = (uw[a] * w[a]).sum(1) / na, (uw[b] * w[b]).sum(1) / nb  # N(0, 1) each when nothing is shared
        # a rank correlation (products of two projections have tails too heavy for a t-test), with the fit's own
        # coupling of the two rows added back: corr(ea, eb) = -ua' Q_a Q_b' ub / (|ua| |ub|) from the hat matrix
        coupling = np.einsum("pc,pck,pdk,pd->p", uw[a], Qp[a], Qp[b], uw[b]) / (na * nb)
        rho = stats.spearmanr(ea, eb).statistic + float(np.mean(coupling))
        p = min(1.0, len(cand) * float(stats.norm.sf(rho * np.sqrt(len(a) - 1)))) if np.isfinite(rho) else 1.0
        ua2, ub2 = (u[a] ** 2).sum(1), (u[b] ** 2).sum(1)
        var = max(float(((u[a] * residual_mm[a]).sum(1) * (u[b] * residual_mm[b]).sum(1)).sum() / (ua2 * ub2).sum()),
                  0.0)  # var(delta), in the motion's unit squared
        moved = var * float(np.mean((u[rows] ** 2).sum(1)))
        found.append(SharedMotion(motion=what, size=float(np.sqrt(var)), unit=unit,
                                  share=min(moved / ms, 1.0) if ms > 0 else 0.0,
                                  rms_mm=float(np.sqrt(moved)), p_value=p, n_poses=len(groups),
                                  shared_joints=upstream))
    return sorted(found, key=lambda s: -s.share)


@dataclass(frozen=True)
class PoseNoise:
    """Motions the targets of one pose share, as noise of that pose (identify's `pose_noise`): unit (N,) each row's
    pose (Measurements.pose_index), Z (N, 3, k) its displacement per unit of each motion (mm), tau (k,) their RMS
    per pose. A pose's rows have covariance diag(sigma^2) + sum_k tau_k^2 z_k z_k' (generalised least squares)."""

    unit: np.ndarray
    Z: np.ndarray
    tau: np.ndarray

    def subset(self, rows) -> "PoseNoise":
        return PoseNoise(self.unit[rows], self.Z[rows], self.tau)

    def whitening(self, sigma: np.ndarray):
        """f(a) for a (N, 3, ...) in mm: sigma V_p^-1/2 (a / sigma) over each pose's rows, V_p = I + sum_k tau_k^2
        z_k z_k' in the rows' weighted units: what a least-squares fit weighted by sigma then treats as independent
        rows is the GLS fit (the same estimate as a nuisance value per pose and motion with prior std tau_k, without
        its columns). Poses are grouped by their number of rows; each group is one batched eigendecomposition."""
        order = np.argsort(self.unit, kind="stable")
        groups = np.split(order, np.flatnonzero(np.diff(self.unit[order])) + 1)
        blocks = []
        for m in sorted({len(g) for g in groups}):
            idx = np.array([g for g in groups if len(g) == m])  # (P, m)
            s = sigma[idx]
            z = (self.Z[idx] / s[:, :, None, None]).reshape(len(idx), 3 * m, -1) * self.tau  # (P, 3m, k)
            lam, E = np.linalg.eigh(np.eye(3 * m) + z @ z.transpose(0, 2, 1))
            blocks.append((idx, s, (E / np.sqrt(lam)[:, None, :]) @ E.transpose(0, 2, 1)))

        def white(a: np.ndarray) -> np.ndarray:
            out = np.empty_like(a)
            for idx, s, W in blocks:
                P, m = idx.shape
                scale = s.reshape(P, m, *([1] * (a.ndim - 1)))
                x = (a[idx] / scale).reshape(P, 3 * m, -1)
                out[idx] = (W @ x).reshape(P, m, *a.shape[1:]) * scale
            return out

        return white


def pose_noise(chain: Chain, meas: Measurements, found: list[SharedMotion]) -> PoseNoise | None:
    """The motions found together as noise of each pose, each with its own size. A motion that only resembles the
    true one (the base shifting where a torso joint turns with its passive partner) weighs the wrong direction
    alone; together they cover it. None when none has a size."""
    moves = {what: v for what, _, v in motions(chain)}
    sized = [s for s in found if s.size > 0]
    if not sized:
        return None
    return PoseNoise(meas.pose_index(), np.stack([moves[s.motion] for s in sized], axis=2),
                     np.array([s.size for s in sized]))


def describe(s: SharedMotion, model: RobotModel) -> str:
    """What the residual follows, in words a process engineer can act on."""
    size = f"{1e3 * s.size:.2f} mrad" if s.unit == "rad" else f"{s.size:.3f} mm"
    return (f"the pose as a whole: the targets measured at one pose move together, most like {s.motion} by "
            f"{size} RMS from pose to pose ({s.rms_mm:.2f} mm RMS at a target, over {s.n_poses} poses): a motion "
            "upstream of where their chains part (a joint they all hang on, the base or mounting) or of the "
            "instrument's frame between poses")
