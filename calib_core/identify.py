"""Geometric identification: from a model and tracker measurements to parameters with honest uncertainty.

Pipeline: rigid pre-alignment of the nominal model to the tracker points (the unknown base pose),
identifiability on the real pose set, weighted / regularised / robust Levenberg-Marquardt on the
independent parameters, covariance, and k-fold cross-validated held-out error.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import kinematics as K
from .identifiability import Identifiability, analyse
from .io import Measurements
from .model import ANGLE_TO_RAD, LENGTH_TO_MM, RobotModel
from .solve import Solution, least_squares

TRACKER_SIGMA0_MM = 0.015
TRACKER_SIGMA_PER_M_MM = 0.006
"""Laser-tracker 1-sigma per coordinate: 15 um + 6 um/m of distance from the tracker (frame origin)."""
PRIOR_STD_MM = 100.0
PRIOR_STD_RAD = 0.1
"""Default Tikhonov prior toward nominal: weak, it only steadies a poorly excited pose set."""


def tracker_sigma_mm(points_mm: np.ndarray) -> np.ndarray:
    """Per-pose 1-sigma (mm) of a laser tracker at the origin of the measurement frame."""
    return TRACKER_SIGMA0_MM + TRACKER_SIGMA_PER_M_MM * np.linalg.norm(points_mm, axis=1) / 1000.0


@dataclass(frozen=True, eq=False)
class CalibratedRobot:
    """What a calibration leaves behind for prediction and compensation: the model and its parameters."""

    model: RobotModel
    x: np.ndarray  # full parameter vector, mm / rad
    R0: np.ndarray  # base reference rotation

    def predict(self, joints: np.ndarray) -> np.ndarray:
        """Measured point (N, 3) mm in the measurement frame for joints (N, n) in internal units."""
        return K.forward(self.model, self.x, joints, self.R0)

    def to_state(self) -> dict:
        """JSON-able state; `from_state(model, state)` restores it exactly."""
        return {"x": self.x.tolist(), "R0": self.R0.tolist()}

    @classmethod
    def from_state(cls, model: RobotModel, state: dict) -> "CalibratedRobot":
        return cls(model, np.array(state["x"], float), np.array(state["R0"], float))


@dataclass
class Calibration:
    """An identified model: the full parameter vector, which part was solved, and its covariance."""

    model: RobotModel
    x: np.ndarray  # full parameter vector, mm / rad
    R0: np.ndarray  # base reference rotation
    free: np.ndarray  # indices of the solved parameters
    solution: Solution
    identifiability: Identifiability
    point_ids: list[str] = field(default_factory=list)
    holdout_residual_mm: np.ndarray | None = None  # (N,) cross-validated distance per pose

    @property
    def robot(self) -> CalibratedRobot:
        return CalibratedRobot(self.model, self.x, self.R0)

    def predict(self, joints: np.ndarray) -> np.ndarray:
        """Measured point (N, 3) mm for joints (N, n) in internal units."""
        return self.robot.predict(joints)

    def to_dict(self) -> dict:
        """The calibration answer of the contract (without the service's id)."""
        n = self.model.n_joints
        Rb, pb = self.base_pose()
        ls = LENGTH_TO_MM[self.model.length_unit]
        return {
            "model": ["geometric"],
            "parameters": self.parameters(),
            "metrics": self.metrics(),
            "identifiability": self.identifiability.to_dict(),
            "base_pose": {"position_mm": pb.tolist(), "rotation_matrix": Rb.tolist()},
            "calibrated_model": self.model.to_dict(self.x[: 5 * n].reshape(n, 5), self.x[5 * n + 6:]),
            "units": {"length": self.model.length_unit, "angle": self.model.angle_unit, "length_per_mm": 1 / ls},
        }

    @property
    def names(self) -> list[str]:
        return K.parameter_names(self.model)

    def base_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (3, 3) and position (3,) mm of the robot base in the measurement frame."""
        n = self.model.n_joints
        b = self.x[5 * n: 5 * n + 6]
        return K.base_rotation(b, self.R0), b[:3].copy()

    def metrics(self) -> dict:
        d = np.linalg.norm(self.solution.residual, axis=1)
        out = {"n_poses": int(len(d)), "n_parameters": int(len(self.free)), "rms_mm": _rms(d),
               "mean_mm": float(d.mean()), "max_mm": float(d.max()), "sigma0": float(np.sqrt(self.solution.s2)),
               "iterations": self.solution.iterations, "converged": self.solution.converged}
        if self.holdout_residual_mm is not None:
            out["holdout_rms_mm"] = _rms(self.holdout_residual_mm)
            out["holdout_max_mm"] = float(self.holdout_residual_mm.max())
        out["outliers"] = [self.point_ids[i] if self.point_ids else int(i) for i in self.solution.outliers]
        return out

    def parameters(self) -> list[dict]:
        """Identified parameters in the model's units; base angles as absolute Z-Y-X Euler angles."""
        m = self.model
        ls, an = LENGTH_TO_MM[m.length_unit], ANGLE_TO_RAD[m.angle_unit]
        ang = K.angular_mask(m)
        std = dict(zip(self.free, self.solution.std))
        values = self.x.copy()
        n = m.n_joints
        ib = 5 * n + 3
        euler, E = _euler_and_jacobian(self.x[ib: ib + 3], self.R0)
        values[ib: ib + 3] = euler
        rot_cov = np.zeros((3, 3))
        pos = {int(i): k for k, i in enumerate(self.free)}
        sel = [pos.get(ib + k) for k in range(3)]
        if all(s is not None for s in sel):
            rot_cov = E @ self.solution.cov[np.ix_(sel, sel)] @ E.T
            for k in range(3):
                std[ib + k] = float(np.sqrt(rot_cov[k, k]))
        out = []
        for i in self.free:
            scale = an if ang[i] else ls
            out.append({"name": self.names[i], "value": float(values[i] / scale),
                        "nominal": float(_nominal(m)[i] / scale) if i < 5 * n or i >= ib + 3 else None,
                        "std": float(std[i] / scale), "unit": m.angle_unit if ang[i] else m.length_unit})
        return out


def _nominal(model: RobotModel) -> np.ndarray:
    return K.nominal_vector(model)


def _rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.mean(d**2)))


def _euler_zyx(R: np.ndarray) -> np.ndarray:
    """(rx, ry, rz) with R = Rz(rz) Ry(ry) Rx(rx)."""
    return np.array([np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(np.clip(R[2, 0], -1, 1)), np.arctan2(R[1, 0], R[0, 0])])


def _euler_and_jacobian(small: np.ndarray, R0: np.ndarray, h: float = 1e-7):
    """Absolute Euler angles of R0 Rz Ry Rx(small) and their derivative wrt the small angles (3x3)."""
    e0 = _euler_zyx(K.base_rotation(np.r_[0, 0, 0, small], R0))
    E = np.empty((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        E[:, k] = (_euler_zyx(K.base_rotation(np.r_[0, 0, 0, small + d], R0)) - e0) / h
    return e0, E


def _prior_std(model: RobotModel) -> np.ndarray:
    std = np.where(K.angular_mask(model), PRIOR_STD_RAD, PRIOR_STD_MM)
    std[5 * model.n_joints: 5 * model.n_joints + 6] = np.inf  # the base pose is unknown: no prior
    return std


def _select(names: list[str], ident: Identifiability, free: tuple[str, ...] | None) -> np.ndarray:
    keep = ident.identifiable
    if free is not None:
        keep = [i for i in keep if any(names[i] == f or names[i].startswith(f + ".") for f in free)]
    return np.array(sorted(keep))


def _fit(model, meas, sigma, x0, R0, idx, loss, regularize) -> Solution:
    q, y = meas.joints, meas.points
    prior_std = _prior_std(model)[idx]

    def residual_jac(xs):
        x = x0.copy()
        x[idx] = xs
        chain = K.Chain(model, x, q, R0)
        return y - chain.p, chain.jacobian()[:, :, idx]

    return least_squares(residual_jac, x0[idx], sigma, prior=x0[idx] if regularize else None,
                         prior_std=prior_std if regularize else None, loss=loss)


def prealign(model: RobotModel, meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """Nominal parameter vector with the base placed by a rigid fit, and the reference rotation R0."""
    x = K.nominal_vector(model)
    R0, t = K.rigid_fit(K.forward(model, x, meas.joints), meas.points)
    x[5 * model.n_joints: 5 * model.n_joints + 3] = t
    return x, R0


def identify(
    model: RobotModel,
    meas: Measurements,
    *,
    free: tuple[str, ...] | None = None,
    loss: str | None = None,
    regularize: bool = True,
    folds: int = 5,
) -> Calibration:
    """Identify the independent geometric parameters (restricted to names/prefixes in `free` if given).

    sigma per pose comes from the CSV's `sigma` column or the laser-tracker model; `loss` is None,
    'huber' or 'cauchy'; `folds` > 1 adds k-fold cross-validated held-out distances.
    """
    n_min = 3
    if meas.n_poses < n_min:
        raise ValueError(f"need at least {n_min} poses, got {meas.n_poses}")
    sigma = meas.sigma if meas.sigma is not None else tracker_sigma_mm(meas.points)
    x0, R0 = prealign(model, meas)
    names = K.parameter_names(model)
    J = K.Chain(model, x0, meas.joints, R0).jacobian().reshape(-1, len(x0))
    ident = analyse(J, names)
    idx = _select(names, ident, free)
    if 3 * meas.n_poses <= len(idx):
        raise ValueError(f"{meas.n_poses} poses give {3 * meas.n_poses} equations for {len(idx)} parameters; "
                         "measure more poses")
    sol = _fit(model, meas, sigma, x0, R0, idx, loss, regularize)
    x = x0.copy()
    x[idx] = sol.x
    cal = Calibration(model=model, x=x, R0=R0, free=idx, solution=sol, identifiability=ident,
                      point_ids=list(meas.point_ids))
    if folds > 1 and meas.n_poses >= 2 * folds:
        cal.holdout_residual_mm = cross_validate(model, meas, sigma, x0, R0, idx, loss, regularize, folds)
    return cal


def fold_ids(n_poses: int, folds: int) -> np.ndarray:
    """A fixed, shuffled assignment of poses to folds (the same for every run on the same data size)."""
    return np.random.default_rng(12345).permutation(n_poses) % folds


def cross_validate(model, meas, sigma, x0, R0, idx, loss, regularize, folds) -> np.ndarray:
    """Distance (mm) of every pose to the model fitted on the other folds."""
    assign = fold_ids(meas.n_poses, folds)
    out = np.empty(meas.n_poses)
    for k in range(folds):
        train, test = assign != k, assign == k
        sol = _fit(model, meas.subset(train), sigma[train], x0, R0, idx, loss, regularize)
        x = x0.copy()
        x[idx] = sol.x
        out[test] = np.linalg.norm(meas.points[test] - K.forward(model, x, meas.joints[test], R0), axis=1)
    return out


def evaluate(cal: Calibration, meas: Measurements) -> dict:
    """Error of a calibration on other (held-out) measurements: rms, mean, max distance in mm."""
    d = np.linalg.norm(meas.points - cal.predict(meas.joints), axis=1)
    return {"n_poses": int(len(d)), "rms_mm": _rms(d), "mean_mm": float(d.mean()), "max_mm": float(d.max())}
