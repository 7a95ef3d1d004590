"""Geometric identification: from a model and tracker measurements to parameters with honest uncertainty.

Pipeline: rigid pre-alignment of the nominal model to the tracker points (the unknown base pose),
identifiability on the real pose set, weighted / regularised / robust Levenberg-Marquardt on the
independent parameters, covariance, and k-fold cross-validated held-out error.

A pose set that cannot calibrate anything (fewer than three distinct joint configurations, fewer equations
than parameters) is refused with a ValueError; one that identifies only part of what the model's structure
allows (a joint that never moved, too little excitation) is calibrated where it can be and the answer says
what it cannot tell (`warnings`, `identifiability.unidentifiable`).
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from . import kinematics as K
from .effects import Context, Effect
from .identifiability import Identifiability, analyse, assess  # noqa: F401 (re-exported: select.py, benchmarks)
from .fold_steps import fold_steps
from .reuse import prepared, start_at
from .shared_motion import PoseNoise
from .io import DISTINCT_DECIMALS, Measurements
from .model import ANGLE_TO_RAD, LENGTH_TO_MM, RobotModel
from .solve import Solution, least_squares, lm_steps, solve_together

FTOL = 1e-10
"""LM's convergence test of a fit: stop when a step would lower the weighted cost by less than this share of it."""
WARM_DAMPING = 1e-9
"""Initial LM damping of a fit that begins at a nearby solution (a cross-validation fold at the full-data one):
Gauss-Newton steps at once, so weakly determined directions converge too and not just pass the test damped."""
WARM_FTOL = 1e-12
"""Convergence tolerance of such a fit: a step or two from the start, it is held to a tighter test than a fit from
nominal (whose last steps overshoot the 1e-10 test by far), so that it lands as close to the optimum."""
WARM_MAX_ITER = 10
"""At most this many LM iterations for a cross-validation fold refitted in full from the full-data solution (a fold
whose plays are found again on its own poses): in a play's curved valley LM crawls at 1e-7 of the cost per
iteration for 30-56 iterations (the iiwa's folds: 1631 of its diagnosis's 3593 chain evaluations; 497 with this cap,
the same findings and held-out figures)."""
FOLD_STEPS = True
"""Cross-validation folds of a fit with effects refitted by one Gauss-Newton step from the full-data solution
(fold_steps) instead of an LM run each."""
PRIOR_STD_MM = 100.0
PRIOR_STD_RAD = 0.1
"""Default Tikhonov prior toward nominal: weak, it only steadies a poorly excited pose set."""
UNCERTAINTY_NOTE = ("std are 1-sigma of the estimates conditional on the identified model being the right one "
                    "(geometry plus the listed effects, noise weighted by the instrument's model and the fitted model "
                    "error); they do not cover errors of a structure the model lacks. null = not determined by "
                    "the data and the prior.")


from .calibrated import CalibratedRobot


@dataclass
class Calibration:
    """An identified model: the full parameter vector, which part was solved, and its covariance."""

    model: RobotModel
    x: np.ndarray  # full parameter vector, mm / rad
    R0: np.ndarray  # base reference rotation
    free: np.ndarray  # indices of the solved geometric parameters
    solution: Solution  # over [x[free], effect parameters]
    identifiability: Identifiability
    point_ids: list[str] = field(default_factory=list)
    holdout_residual_mm: np.ndarray | None = None  # (N,) cross-validated distance per pose
    effects: tuple[Effect, ...] = ()
    sigma_mm: np.ndarray | None = None  # (N,) the per-axis weights used: noise and model error
    model_error_mm: float = 0.0  # per-axis std of what the model leaves beyond the measurement noise
    sigma0_measurement: float | None = None  # sigma0 of the fit weighted by the measurement noise alone
    prior_scale: float = 1.0  # multiplier of the default prior precision of the joint parameters
    x_basis: np.ndarray | None = None  # the geometry the effect bases were evaluated on
    noise_model: str = ""  # which noise model weighted the fit: the CSV's sigma or an instrument preset
    unmodelled_mm: float = 0.0  # per-axis std of held-out structure no cause in the model explains (diagnose sets it)
    setup_names: tuple[str, ...] = ("",)  # one base pose per setup, in this order
    pose_index: np.ndarray | None = None  # (N,) the independent unit of each row (Measurements.pose_index)
    mass_doubt: tuple = ()  # (MassStep, covariance over [x[free], effect parameters, its step], move): uncertainty.py

    @property
    def warnings(self) -> list[str]:
        """Plain sentences on what this calibration cannot vouch for (from the identifiability analysis)."""
        return self.identifiability.warnings()

    @property
    def effect_values(self) -> tuple[np.ndarray, ...]:
        return tuple(_split(self.solution.x[len(self.free):], self.effects, self.model))

    @property
    def basis_x(self) -> np.ndarray:
        """The geometry the effect bases were evaluated on: x_basis where there is one, else x (mm, rad)."""
        return self.x if self.x_basis is None else self.x_basis

    @property
    def robot(self) -> CalibratedRobot:
        return CalibratedRobot(self.model, self.x, self.R0, self.effects, self.effect_values,
                               self.x_basis if self.effects else None, self.setup_names)

    def predict(self, joints: np.ndarray, columns: Measurements | None = None) -> np.ndarray:
        """Measured point (N, 3) mm for joints (N, n) in internal units."""
        return self.robot.predict(joints, columns)

    def to_dict(self) -> dict:
        """The calibration answer of the contract (without the service's id)."""
        m, lay = self.model, K.layout(self.model, self.x)
        poses = [self.base_pose(s) for s in range(lay.n_setups)]
        Rb, pb = poses[0]
        return {
            "model": ["geometric"] + sorted({e.kind for e in self.effects}),
            "parameters": self.parameters(),
            "metrics": self.metrics(),
            "identifiability": self.identifiability.to_dict(),
            "uncertainty": {"conditional_on_model": True, "note": UNCERTAINTY_NOTE,
                            "unmodelled_mm_per_axis": self.unmodelled_mm},
            "warnings": self.warnings,
            "noise_model": self.noise_model,
            "base_pose": {"position_mm": pb.tolist(), "rotation_matrix": Rb.tolist()},
            **({"setups": [{"setup": name, "base_pose": {"position_mm": p.tolist(), "rotation_matrix": R.tolist()}}
                           for name, (R, p) in zip(self.setup_names, poses)]} if lay.n_setups > 1 else {}),
            "calibrated_model": m.to_dict(self.x[lay.geometry].reshape(m.n_joints, -1),
                                          self.x[lay.tools].reshape(-1, 3)),
        }

    @property
    def names(self) -> list[str]:
        return K.parameter_names(self.model, self.setup_names)

    def base_pose(self, setup: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Rotation (3, 3) and position (3,) mm of the robot base in the measurement frame (of a setup)."""
        b = self.x[K.layout(self.model, self.x).base(setup)]
        return K.base_rotation(b, self.R0 if self.R0.ndim == 2 else self.R0[setup]), b[:3].copy()

    def inliers(self) -> np.ndarray:
        """(N,) bool: the poses the fit did not name as outliers (held-out figures leave the outliers out)."""
        keep = np.ones(len(self.solution.residual), bool)
        keep[self.solution.outliers] = False
        return keep

    def metrics(self) -> dict:
        """Fit and held-out figures (mm) over the poses that are not outliers, the robot's error, not the bad
        readings'; with outliers named, the RMS and max over every pose beside them (`*_with_outliers_mm`)."""
        every = np.linalg.norm(self.solution.residual, axis=1)
        keep = self.inliers()
        keep = keep if keep.any() else ~keep  # every pose an outlier: the figures over all of them
        d = every[keep]
        out = {"n_poses": int(len(every)), "n_parameters": int(len(self.solution.x)),
               "n_geometric_parameters": int(len(self.free)), "rms_mm": _rms(d),
               "mean_mm": float(d.mean()), "max_mm": float(d.max()), "sigma0": float(np.sqrt(self.solution.s2)),
               "model_error_mm": self.model_error_mm,
               "sigma0_measurement": self.sigma0_measurement if self.sigma0_measurement is not None
               else float(np.sqrt(self.solution.s2)),
               "iterations": self.solution.iterations, "converged": self.solution.converged}
        if len(self.solution.outliers):
            out["rms_with_outliers_mm"], out["max_with_outliers_mm"] = _rms(every), float(every.max())
        if self.holdout_residual_mm is not None:
            kept = self.holdout_residual_mm[keep]
            out["holdout_rms_mm"] = _rms(kept)
            out["holdout_max_mm"] = float(kept.max())
            if len(self.solution.outliers):
                out["holdout_rms_with_outliers_mm"] = _rms(self.holdout_residual_mm)
        out["outliers"] = [self.point_ids[i] if self.point_ids else int(i) for i in self.solution.outliers]
        return out

    def parameters(self) -> list[dict]:
        """Identified parameters in the model's units; base angles as absolute Z-Y-X Euler angles."""
        m = self.model
        ls, an = LENGTH_TO_MM[m.length_unit], ANGLE_TO_RAD[m.angle_unit]
        lay = K.layout(m, self.x)
        ang = K.angular_mask(m, lay.n_setups)
        std = dict(zip(self.free, self.solution.std))
        values = self.x.copy()
        pos = {int(i): k for k, i in enumerate(self.free)}
        for s in range(lay.n_setups):
            ib = lay.base(s).start + 3
            euler, E = _euler_and_jacobian(self.x[ib: ib + 3], self.R0 if self.R0.ndim == 2 else self.R0[s])
            values[ib: ib + 3] = euler
            sel = [pos.get(ib + k) for k in range(3)]
            if all(k is not None for k in sel):
                rot_cov = E @ self.solution.cov[np.ix_(sel, sel)] @ E.T
                bad = not np.all(np.isfinite(self.solution.std[sel]))
                for k in range(3):
                    std[ib + k] = np.inf if bad else float(np.sqrt(max(rot_cov[k, k], 0.0)))
        nominal = K.nominal_vector(m, n_setups=lay.n_setups)
        base = np.zeros(len(self.x), bool)
        base[lay.bases] = True
        out = []
        for i in self.free:
            scale = an if ang[i] else ls
            out.append({"name": self.names[i], "value": float(values[i] / scale),
                        "nominal": None if base[i] else float(nominal[i] / scale),
                        "std": _finite(std[i] / scale), "unit": m.angle_unit if ang[i] else m.length_unit})
        k = len(self.free)
        for e in self.effects:
            for name, unit in zip(e.parameter_names(m), e.parameter_units(m)):
                out.append({"name": name, "value": float(self.solution.x[k]), "nominal": 0.0,
                            "std": _finite(self.solution.std[k]), "unit": unit, "effect": e.kind})
                k += 1
        return out


def _finite(v: float) -> float | None:
    """A std for JSON: None where the parameter is undetermined (inf)."""
    return float(v) if np.isfinite(v) else None


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


def _prior_std(model: RobotModel, prior_scale: float = 1.0, n_setups: int = 1) -> np.ndarray:
    """Prior std toward nominal; prior_scale multiplies the precision of the joint parameters (base and tool
    keep theirs: the registration is always identified)."""
    lay = K.layout(model, n_setups)
    std = np.where(K.angular_mask(model, n_setups), PRIOR_STD_RAD, PRIOR_STD_MM)
    std[lay.geometry] /= np.sqrt(prior_scale)
    std[lay.bases] = np.inf  # the base poses are unknown: no prior
    return std


def _select(names: list[str], ident: Identifiability, free: tuple[str, ...] | None) -> np.ndarray:
    keep = ident.identifiable
    if free is not None:
        keep = [i for i in keep if any(names[i] == f or names[i].startswith((f + ".", f + "[")) for f in free)]
    return np.array(sorted(keep), dtype=int)


def model_error_sigma(residual: np.ndarray, sigma: np.ndarray, n_params: int, weights: np.ndarray) -> float:
    """Per-axis std s (mm) of the error beyond the measurement noise (a variance component): the root of
    sum w r^2 / (sigma^2 + s^2) = m - p; 0 when the noise alone explains the residual. Weighting by
    sigma^2 + s^2 keeps a few very precise tracker readings from dominating a model-error-limited fit."""
    r2 = weights * (residual**2).sum(1)
    dof = 3 * len(r2) - n_params
    f = lambda s2: float((r2 / (sigma**2 + s2)).sum() / 3.0 - dof / 3.0)  # noqa: E731
    if dof <= 0 or f(0.0) <= 0.0:
        return 0.0
    from scipy.optimize import brentq  # here: scipy.optimize is 0.6 s of import that parsing a model never needs

    hi = float(r2.max())
    return float(np.sqrt(brentq(f, 0.0, hi, xtol=1e-12 * hi + 1e-15)))


def _split(theta: np.ndarray, effects, model) -> list[np.ndarray]:
    sizes = np.cumsum([len(e.parameter_names(model)) for e in effects])[:-1] if effects else []
    return np.split(theta, sizes) if effects else []


def effect_bases(model, meas, effects, x, R0) -> tuple[np.ndarray, np.ndarray]:
    """Stacked bases of the effects at the poses: Phi_q (N, n, K) and Phi_p (N, 3, K)."""
    n = meas.joints.shape[1]
    ctx = Context.at(model, x, meas, R0)
    bq, bp = [], []
    for e in effects:
        q, p = ctx.basis(e).dense(n, len(e.parameter_names(model)))
        bq.append(q)
        bp.append(p)
    return np.concatenate(bq, axis=2), np.concatenate(bp, axis=2)


class ChainEvaluations:
    """Memoised chain evaluations of one pose set: the measured point (N, 3) and the full Jacobian (N, 3, P) at
    every pose, keyed by the full parameter vector. Fits that share the pose set (the folds of a
    cross-validation, candidate models, prior strengths) share them: a warm start at an already evaluated
    point costs nothing, and a fold's held-out prediction comes with its training evaluation."""

    def __init__(self, model: RobotModel, joints: np.ndarray, R0: np.ndarray, size: int = 32,
                 labels: K.Labels | None = None):
        self.model, self.joints, self.R0, self.size, self.labels = model, joints, R0, size, labels
        self._memo: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.many([x])[0]

    def many(self, xs: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """The evaluations at several parameter vectors; those not memoised are made in one pass of a batched
        Chain (35 vectors of 150 poses cost about what a dozen single passes cost: numpy's per-call overhead is
        paid once)."""
        keys = [np.asarray(x, float).tobytes() for x in xs]
        todo = {k: x for k, x in zip(keys, xs) if k not in self._memo}
        fresh = {}
        if todo:
            X = np.array(list(todo.values()), float)
            chain = K.Chain(self.model, X[0] if len(X) == 1 else X, self.joints, self.R0, self.labels)
            J = chain.jacobian()
            fresh = dict(zip(todo, [(chain.p, J)] if len(X) == 1 else zip(chain.p, J)))
        out = []
        for key in keys:
            hit = self._memo.pop(key, None) or fresh[key]
            self._memo[key] = hit  # the most recently used last
            out.append(hit)
        while len(self._memo) > self.size:
            self._memo.pop(next(iter(self._memo)))  # the least recently used
        return out


CONSTANT_COLUMNS = 64
"""A fit whose last effects have fixed columns (Effect.fixed_columns: a smooth field's weights, 372 of the Motoman's
469 parameters), this many or more, makes their block of the normal matrix once per LM run (lm_steps'
constant_from): the Motoman's field fit 0.52 -> 0.33 s. Only those: Hilti's search fits end in ~100 columns of
link deflection that move no joint either, and the blocks' rounding moved a knife edge of its split 0 (2.03 -> 2.07
mm held out)."""


class ThroughJoints:
    """The effects' bases (Phi_q (N, n, K), Phi_p (N, 3, K)) applied by their structure: most columns move no joint
    (a Cartesian effect) or one (a joint's own compliance), so the joint offsets Phi_q theta and the Jacobian
    columns Jq Phi_q + Phi_p are gathered from those alone (Agile Justin: 96 % of Phi_q is zeros; the dense products
    were a third of each LM evaluation). The same sums as the dense products, without their zero terms."""

    def __init__(self, Phi_q: np.ndarray, Phi_p: np.ndarray):
        n = Phi_q.shape[1]
        nz = np.abs(Phi_q).max(axis=0) > 0  # (n, K): the joints each column moves
        per = nz.sum(0)
        self.single = np.flatnonzero(per == 1)
        self.row = nz[:, self.single].argmax(0)
        self.w = np.ascontiguousarray(Phi_q[:, self.row, self.single].T)  # (Ks, N): each column's one joint
        self.onehot = np.zeros((len(self.single), n))
        self.onehot[np.arange(len(self.single)), self.row] = 1.0
        self.multi = np.flatnonzero(per > 1)
        self.rows = np.flatnonzero(nz[:, self.multi].any(1))
        self.P = np.ascontiguousarray(Phi_q[:, self.rows][:, :, self.multi])  # (N, r, Km)
        self.PpT = np.ascontiguousarray(Phi_p.transpose(2, 0, 1))  # (K, N, 3)

    def shift(self, theta: np.ndarray) -> np.ndarray:
        """Phi_q theta (N, n): the joint offsets the effects give."""
        out = (self.w.T * theta[self.single]) @ self.onehot
        if len(self.multi):
            out[:, self.rows] += self.P @ theta[self.multi]
        return out

    def columns(self, Jq: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Jq Phi_q + Phi_p into out (K, N, 3), parameters first; Jq (N, 3, n) the chain's joint Jacobian."""
        out[...] = self.PpT
        JqT = Jq.transpose(2, 0, 1)  # (n, N, 3)
        out[self.single] += JqT[self.row] * self.w[:, :, None]
        if len(self.multi):
            out[self.multi] += (Jq[:, :, self.rows] @ self.P).transpose(2, 0, 1)
        return out


def _fit(model, meas, sigma, x0, R0, idx, loss, regularize, bases=None, effect_prior=None, start=None,
         prior_scale: float = 1.0, *, evals: ChainEvaluations | None = None, covariance: bool = True,
         damping: float = 1e-4, ftol: float = FTOL, pose_noise: PoseNoise | None = None,
         max_iter: int = 100, fixed: int = 0) -> Solution:
    """LM over x[idx] and, with bases (Phi_q, Phi_p), the effect parameters: the coupled Jacobian. The last `fixed`
    effect parameters have fixed columns (Effect.fixed_columns; used from CONSTANT_COLUMNS on).

    `pose_noise` (shared_motion.PoseNoise): motions the targets of one pose share (the joints upstream of them
    landing a little differently at each visit) as noise of that pose: generalised least squares with per-pose
    covariance s^2 I + sum_k tau_k^2 z_k z_k' (a random effect), each pose's rows whitened by it. The solution's
    residual is measured minus the model's prediction; its covariance is GLS's (X' V^-1 X + L)^-1.

    `start` (default: nominal) is where LM begins; the optimum does not depend on it beyond the convergence
    tolerance. Geometric fits (no bases) may take memoised `evals` of meas's poses; `covariance=False` skips the
    covariance; `damping` is LM's initial damping (small for a start near the optimum); `max_iter=0` takes the
    covariance at `start` itself."""
    q, y, labels = meas.joints, meas.points, meas.labels
    p_geo = len(idx)
    K_eff = 0 if bases is None else bases[0].shape[2]
    through = None if not K_eff else ThroughJoints(*bases)

    def residual_jac(xs):
        x = x0.copy()
        x[idx] = xs[:p_geo]
        if not K_eff:
            if evals is not None:
                p, J = evals(x)
                return y - p, J[:, :, idx]
            chain = K.Chain(model, x, q, R0, labels)
            return y - chain.p, chain.jacobian_columns(idx)
        theta = xs[p_geo:p_geo + K_eff]
        chain = K.Chain(model, x, q + through.shift(theta), R0, labels)
        J = np.empty((p_geo + K_eff, len(q), 3))  # parameters first, as Chain.jacobian lays them out: no transposes
        chain.jacobian_columns(idx, out=J[:p_geo])
        through.columns(chain.joint_jacobian(), out=J[p_geo:])
        return y - chain.p - bases[1] @ theta, J.transpose(1, 2, 0)

    nominal, prior = _prior(model, meas, x0, idx, regularize, prior_scale, effect_prior, K_eff)
    begin = nominal if start is None else start
    if fixed >= CONSTANT_COLUMNS:
        prior["constant_from"] = p_geo + K_eff - fixed
    if pose_noise is None:
        return least_squares(residual_jac, begin, sigma, loss=loss, covariance=covariance, damping=damping,
                             ftol=ftol, max_iter=max_iter, **prior)
    white = pose_noise.whitening(sigma)

    def whitened(xs):
        r, J = residual_jac(xs)
        return white(r), white(J)

    sol = least_squares(whitened, begin, sigma, loss=loss, covariance=covariance, damping=damping, ftol=ftol,
                        max_iter=max_iter, **prior)
    return dataclasses.replace(sol, residual=residual_jac(sol.x)[0])


def _prior(model, meas, x0, idx, regularize, prior_scale, effect_prior=None, K_eff: int = 0) -> tuple[np.ndarray, dict]:
    """The nominal [x0[idx], 0 per effect parameter] (LM's default start) and lm_steps' prior options: the Tikhonov
    pull toward it (none when every prior std is infinite)."""
    p_geo = len(idx)
    geo_std = _prior_std(model, prior_scale, meas.n_setups)[idx] if regularize else np.full(p_geo, np.inf)
    prior_std = np.r_[geo_std, effect_prior] if effect_prior is not None else np.r_[geo_std, np.full(K_eff, np.inf)]
    nominal = np.r_[x0[idx], np.zeros(K_eff)]
    if not np.isfinite(prior_std).any():
        return nominal, {}
    return nominal, {"prior": nominal, "prior_std": prior_std}


def _effect_prior(model, effects) -> np.ndarray | None:
    """Ridge prior std per effect parameter (inf = none): Effect.prior_stds."""
    if not effects:
        return None
    return np.concatenate([np.broadcast_to(np.asarray(e.prior_stds(model), float), (len(e.parameter_names(model)),))
                           for e in effects])


def prealign(model: RobotModel, meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """Nominal parameter vector with each setup's base placed by a rigid fit, and the reference rotation R0
    ((3, 3), or (S, 3, 3) with several setups)."""
    S = meas.n_setups
    lay = K.layout(model, S)
    x = K.nominal_vector(model, n_setups=S)
    labels = meas.labels
    p = K.forward(model, x, meas.joints, np.broadcast_to(np.eye(3), (S, 3, 3)) if S > 1 else None, labels)
    R0 = np.empty((S, 3, 3))
    for s in range(S):
        rows = slice(None) if S == 1 else meas.setup == s
        if len(np.unique(np.round(p[rows], 6), axis=0)) < 3:
            raise ValueError(f"setup {meas.setup_names[s]!r} has fewer than three distinct measured positions: "
                             "its base pose cannot be placed")
        R0[s], t = K.rigid_fit(p[rows], meas.points[rows])
        x[lay.base(s).start: lay.base(s).start + 3] = t
    return x, (R0[0] if S == 1 else R0)


ON_AXIS_MM = 1.0
"""A target whose nominal point lies this close to the joint axis it turns about (a URDF tool link's origin) is
placed from the data before identifiability is judged: on the axis the last joint's a and alpha look confounded,
although the real SMR is off the axis and identifies them."""


def measured_targets(model: RobotModel, meas: Measurements, sigma: np.ndarray, x0: np.ndarray, R0
                     ) -> tuple[np.ndarray, RobotModel]:
    """Where to judge identifiability: x0 with the target points fitted to the data (base poses and points free,
    geometry nominal; the fit itself still starts at x0) when a nominal
    target lies within ON_AXIS_MM of the nearest moving row's joint axis, and the model with its targets there
    (for the structural analysis); else x0 and the model unchanged. Identifiability is judged where the targets
    really are, never at a point on a joint axis."""
    lay = K.layout(model, x0)
    ch = K.Chain(model, K.nominal_vector(model), np.zeros((1, model.n_joints)))
    moving, par = model.moving, model.parents
    on_axis = False
    for r, t in zip(model.target_rows, model.target_points):
        a = int(r)
        while a >= 0 and not moving[a]:
            a = int(par[a])
        if a < 0:
            continue
        p = ch.o_beta[r, 0] + ch.R[r, 0] @ t
        v = p - ch.o_theta[a, 0]
        z = ch.z_axis[a, 0]
        on_axis |= bool(np.linalg.norm(v - (v @ z) * z) < ON_AXIS_MM) and not model.prismatic[a]
    if not on_axis:
        return x0, model
    idx = np.r_[np.arange(lay.bases.start, lay.bases.stop), np.arange(lay.tools.start, lay.tools.stop)]
    sol = _fit(model, meas, sigma, x0, R0, idx, None, False, covariance=False)
    x = x0.copy()
    x[idx] = sol.x[: len(idx)]
    pts = x[lay.tools].reshape(-1, 3)
    targets = tuple((nm, r, pts[k]) for k, (nm, r, _) in enumerate(model.targets))
    return x, dataclasses.replace(model, tool=pts[0].copy(), targets=targets)


def identify(
    model: RobotModel,
    meas: Measurements,
    *,
    effects: tuple[Effect, ...] = (),
    free: tuple[str, ...] | None = None,
    loss: str | None = None,
    regularize: bool = True,
    folds: int = 5,
    x_ref: np.ndarray | None = None,
    prior_scale: float = 1.0,
    refold: Callable[[Calibration], Callable[[np.ndarray], tuple[Effect, ...]]] | None = None,
    pose_noise: PoseNoise | None = None,
    start: Calibration | None = None,
    model_error_mm: float | None = None,
    ftol: float = FTOL,
    first_ftol: float | None = None,
) -> Calibration:
    """Identify the independent geometric parameters (restricted to names/prefixes in `free` if given)
    jointly with the parameters of `effects`.

    sigma per pose comes from the CSV's `sigma` column or the laser-tracker model; `loss` is None,
    'huber' or 'cauchy'; `folds` > 1 adds k-fold cross-validated held-out distances. Effect bases are
    evaluated on the geometry `x_ref` (default: a geometric-only fit of the same data). `prior_scale`
    multiplies the precision of the default prior toward nominal of the joint parameters (> 1: a stronger
    pull to nominal; with regularize=True only). `refold(cal)(train)` gives each fold the effects to refit on
    its training poses (train: (N,) bool), for effects whose form was itself read off this data (a play's switch
    found on the residual): the held-out poses then have no say in it. `pose_noise` (shared_motion.PoseNoise)
    weights motions the targets of one pose share as noise of that pose (generalised least squares; see _fit).
    `start`, a calibration of the same model on the same poses whose effects are all among `effects`, is where LM
    begins (its geometry and effect values; new effects at 0): the optimum does not depend on it beyond the
    convergence tolerance, but a search that adds one cause to a fitted model then takes a step or two instead of
    the whole way from nominal.
    `model_error_mm` given: the fit weighted by the noise plus that model error (mm per axis), one solve instead
    of two (the first, weighted by the noise alone, estimates the model error; on a large model error it converges
    slowly: Agile Justin's mass steps, 100 iterations each); for fits that keep one weighting (the mass steps).
    `ftol`: LM's convergence test (relative drop of the weighted cost a step must promise), looser for a fit that is
    one step on a path whose end is fitted in full. `first_ftol` (used where looser than `ftol`): the test of the fit weighted by
    the noise alone, whose one use is the model error it leaves; where the model error is many times the noise, that
    fit is a large-residual problem on which Gauss-Newton converges linearly, so a search that makes hundreds of fits
    can stop it early (diagnosis.fitter) and the answer is then solved to `ftol` from there.

    Raises ValueError when the pose set cannot calibrate: fewer than three distinct joint configurations
    or fewer equations than parameters. A pose set that identifies less than the model's structure allows
    is calibrated where it can be; `warnings` and `identifiability` say what it cannot tell.
    """
    n_min = 3
    if meas.n_poses < n_min:
        raise ValueError(f"need at least {n_min} poses, got {meas.n_poses}")
    if not prior_scale > 0:
        raise ValueError(f"prior_scale must be positive, got {prior_scale}")
    n_distinct = len(np.unique(np.round(meas.joints, DISTINCT_DECIMALS), axis=0))
    if n_distinct < n_min:
        what = (f"all {meas.n_poses} poses are the same joint configuration" if n_distinct == 1 else
                f"the {meas.n_poses} poses are only {n_distinct} distinct joint configurations")
        raise ValueError(f"{what}: a calibration needs at least {n_min} different poses (better: dozens spread "
                         "over every joint's range); measure more poses")
    sigma = meas.noise_sigma_mm()
    x0, R0, names, ident = prepared(model, meas, sigma, prealign, measured_targets)
    idx = _select(names, ident, free)
    n_eff = sum(len(e.parameter_names(model)) for e in effects)
    if 3 * meas.n_poses <= len(idx) + n_eff:
        raise ValueError(f"{meas.n_poses} poses give {3 * meas.n_poses} equations for {len(idx) + n_eff} "
                         "parameters; measure more poses")
    return _calibrate(model, meas, sigma, x0, R0, ident, idx, effects=effects, loss=loss, regularize=regularize,
                      folds=folds, x_ref=x_ref, prior_scale=prior_scale, refold=refold, pose_noise=pose_noise,
                      model_error_mm=model_error_mm, start=start_at(start, model, x0, idx, effects), ftol=ftol,
                      first_ftol=first_ftol)[0]


def _calibrate(model, meas, sigma, x0, R0, ident, idx, *, effects=(), loss=None, regularize=True, folds=5,
               x_ref=None, prior_scale=1.0, start=None, evals: ChainEvaluations | None = None, refold=None,
               pose_noise=None, model_error_mm: float | None = None, ftol: float = FTOL,
               first_ftol: float | None = None) -> tuple[Calibration, Solution]:
    """identify() once the pose set is checked, pre-aligned and analysed: the fit weighted by the noise, again
    with the model error added to the weights, and the cross-validation. Also returns the first fit (noise
    weights alone). `start` (first fit) and memoised `evals` (geometric fits) let callers that fit one pose
    set many times share work (select.py)."""
    bases = None
    if effects:
        if x_ref is None:
            geo = _fit(model, meas, sigma, x0, R0, idx, loss, regularize, prior_scale=prior_scale)
            x_ref = x0.copy()
            x_ref[idx] = geo.x
        bases = effect_bases(model, meas, effects, x_ref, R0)
    eprior = _effect_prior(model, effects)
    fixed = 0  # the last effects' parameters whose columns are fixed
    for e in reversed(effects):
        if not e.fixed_columns:
            break
        fixed += len(e.parameter_names(model))
    fit = dict(prior_scale=prior_scale, evals=evals, pose_noise=pose_noise, fixed=fixed)
    if model_error_mm is not None:  # the weighting given: one solve
        s_model, sigma0_measurement = float(model_error_mm), None
        sigma = np.sqrt(sigma**2 + s_model**2)
        first = sol = _fit(model, meas, sigma, x0, R0, idx, loss, regularize, bases, eprior, start=start, ftol=ftol,
                           **fit)
    else:
        early = first_ftol is not None and first_ftol > ftol  # the first fit stopped before the answer's test
        first = sol = _fit(model, meas, sigma, x0, R0, idx, loss, regularize, bases, eprior, start=start,
                           ftol=first_ftol if early else ftol, **fit)
        sigma0_measurement = float(np.sqrt(sol.s2))
        s_model = model_error_sigma(sol.residual, sigma, len(sol.x), sol.weights)
        if s_model > 0.0 or early:  # weighted by the noise plus what the model leaves (or the noise alone, from
            sigma = np.sqrt(sigma**2 + s_model**2)  # where the first fit stopped), solved again to the full test
            sol = _fit(model, meas, sigma, x0, R0, idx, loss, regularize, bases, eprior, start=sol.x, ftol=ftol,
                       **fit)
    x = x0.copy()
    x[idx] = sol.x[: len(idx)]
    cal = Calibration(model=model, x=x, R0=R0, free=idx, solution=sol, identifiability=ident,
                      point_ids=list(meas.point_ids), effects=tuple(effects), sigma_mm=sigma,
                      model_error_mm=s_model, sigma0_measurement=sigma0_measurement, prior_scale=prior_scale,
                      x_basis=x_ref if effects else None, noise_model=meas.noise_source(),
                      setup_names=meas.setup_names, pose_index=meas.pose_index())
    if folds > 1 and meas.n_poses >= 2 * folds:
        fold_bases = None
        if refold is not None:
            fold_effects = refold(cal)
            fold_bases = lambda train: effect_bases(model, meas, fold_effects(train), x_ref, R0)  # noqa: E731
        cal.holdout_residual_mm = cross_validate(model, meas, sigma, x0, R0, idx, loss, regularize, folds, bases,
                                                 eprior, prior_scale=prior_scale, start=sol.x, evals=evals,
                                                 fold_bases=fold_bases, pose_noise=pose_noise)
    return cal, first


@functools.lru_cache(maxsize=64)
def fold_ids(n_poses: int, folds: int) -> np.ndarray:
    """A fixed, shuffled assignment of poses to folds (the same for every run on the same data size); read-only,
    made once per size (a model selection asks for it a dozen times)."""
    out = np.random.default_rng(12345).permutation(n_poses) % folds
    out.flags.writeable = False
    return out


def pose_folds(meas: Measurements, folds: int) -> np.ndarray:
    """Fold of every row: fold_ids over the independent units (Measurements.pose_index), so the targets measured
    at one pose are held out together; the rows' own fold_ids when every row is its own unit (one target)."""
    unit = meas.pose_index()
    return fold_ids(int(unit.max()) + 1 if len(unit) else 0, folds)[unit]


def cross_validate(model, meas, sigma, x0, R0, idx, loss, regularize, folds, bases=None,
                   effect_prior=None, prior_scale: float = 1.0, start: np.ndarray | None = None,
                   evals: ChainEvaluations | None = None, fold_bases=None, pose_noise=None) -> np.ndarray:
    """Distance (mm) of every pose to the model fitted on the other folds.

    Every fold's fit begins at `start` (the full-data solution over [x[idx], effect parameters]; default
    nominal): a few poses less move the optimum little, so LM needs a step or two (to the same convergence
    test) instead of the whole way from nominal. Geometric folds are solved together (held_out), with memoised
    `evals` (may be shared with the full-data fit). `fold_bases(train)`, if given, gives each fold its own effect
    bases (effects refitted in form on the training poses). With `pose_noise` each fold weights the training poses'
    shared motion (a held-out pose's own is unknown: predicted as zero)."""
    if bases is None:
        evals = evals or ChainEvaluations(model, meas.joints, R0, labels=meas.labels)
        return held_out(model, meas, x0, evals, [Folds(sigma, idx, loss, regularize, prior_scale, start)], folds)[0]
    assign = pose_folds(meas, folds)
    out = np.empty(meas.n_poses)
    if FOLD_STEPS and start is not None and fold_bases is None and pose_noise is None:
        return _one_step_folds(model, meas, sigma, x0, R0, idx, loss, regularize, folds, bases, effect_prior,
                               prior_scale, start, assign)
    warm = {} if start is None else {"damping": WARM_DAMPING, "ftol": WARM_FTOL, "max_iter": WARM_MAX_ITER}
    for k in range(folds):
        train, test = assign != k, assign == k
        fold = bases if fold_bases is None else fold_bases(train)
        sub = (fold[0][train], fold[1][train])
        noise = None if pose_noise is None else pose_noise.subset(train)
        sol = _fit(model, meas.subset(train), sigma[train], x0, R0, idx, loss, regularize, sub, effect_prior,
                   start=start, prior_scale=prior_scale, covariance=False, pose_noise=noise, **warm)
        x = x0.copy()
        x[idx] = sol.x[: len(idx)]
        theta = sol.x[len(idx):]
        labels = None if meas.labels is None else meas.labels[test]
        pred = K.forward(model, x, meas.joints[test] + fold[0][test] @ theta, R0, labels) + fold[1][test] @ theta
        out[test] = np.linalg.norm(meas.points[test] - pred, axis=1)
    return out


def _one_step_folds(model, meas, sigma, x0, R0, idx, loss, regularize, folds, bases, effect_prior, prior_scale,
                    start, assign) -> np.ndarray:
    """cross_validate's held-out distances (mm) with each fold refitted by one Gauss-Newton step from the full-data
    solution `start` (fold_steps), its held-out poses predicted at the stepped parameters."""
    q, labels, p_geo = meas.joints, meas.labels, len(idx)
    Phi_q, Phi_p = bases
    x = x0.copy()
    x[idx] = start[:p_geo]
    theta = start[p_geo:]
    chain = K.Chain(model, x, q + Phi_q @ theta, R0, labels)
    J = np.concatenate([chain.jacobian_columns(idx), (chain.joint_jacobian() @ Phi_q)
                        + Phi_p], axis=2)
    _, prior = _prior(model, meas, x0, idx, regularize, prior_scale, effect_prior, Phi_q.shape[2])
    out = np.empty(meas.n_poses)
    for k, xs in enumerate(fold_steps(meas.points - chain.p - Phi_p @ theta, J, sigma, assign, folds, start,
                                      loss=loss, **prior)):
        test = assign == k
        x[idx] = xs[:p_geo]
        theta = xs[p_geo:]
        pred = K.forward(model, x, q[test] + Phi_q[test] @ theta, R0, None if labels is None else labels[test])
        out[test] = np.linalg.norm(meas.points[test] - pred - Phi_p[test] @ theta, axis=1)
    return out


def _rows_columns(J: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """J[rows][:, :, cols] of a Jacobian (N, 3, P), C-contiguous: gathered with the poses innermost, as Chain
    computes them (several times faster than one np.ix_ gather)."""
    return np.ascontiguousarray(J.transpose(1, 2, 0)[:, cols][:, :, rows].transpose(2, 0, 1))


@dataclass(frozen=True)
class Folds:
    """One geometric model's k-fold cross-validation: the per-pose weights sigma (N,) mm of its fits, its free
    parameters, loss and prior, and the full-data solution x[idx] its folds start at (None: nominal)."""

    sigma: np.ndarray
    idx: np.ndarray
    loss: str | None = None
    regularize: bool = True
    prior_scale: float = 1.0
    start: np.ndarray | None = None


def held_out(model, meas, x0, evals: ChainEvaluations, models: list[Folds], folds: int) -> list[np.ndarray]:
    """Distance (mm) of every pose to each geometric model fitted on the other folds (the same fold assignment for
    all).

    All the folds of all the models are solved together (solve_together): each round, the chain is evaluated once
    for every parameter vector the fits ask for, in one batched pass (ChainEvaluations.many), so seven models' 35
    folds cost three or four batched passes instead of about seventy single ones; each fit takes exactly the steps
    it would take alone. A fold's held-out prediction comes with its training evaluation."""
    assign = pose_folds(meas, folds)
    tests = [assign == k for k in range(folds)]
    runs, fits = [], []  # fits: per run, its model's free parameters and training rows
    for m in models:
        nominal, prior = _prior(model, meas, x0, m.idx, m.regularize, m.prior_scale)
        warm = {} if m.start is None else {"damping": WARM_DAMPING, "ftol": WARM_FTOL}
        for test in tests:
            train = ~test
            runs.append(lm_steps(nominal if m.start is None else m.start, m.sigma[train], loss=m.loss,
                                 covariance=False, **prior, **warm))
            fits.append((m.idx, train))
    y, points = meas.points, {}
    y_train = [y[~test] for test in tests]

    def full(k: int, xs: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[fits[k][0]] = xs
        return x

    def evaluate(asks):
        xs = [full(k, xs) for k, xs in asks]
        out = []
        for (k, _), x, (p, J) in zip(asks, xs, evals.many(xs)):
            points[x.tobytes()] = p
            idx, train = fits[k]
            out.append((y_train[k % folds] - p[train], _rows_columns(J, train, idx)))
        return out

    sols = solve_together(runs, evaluate)
    out = []
    for i in range(len(models)):
        d = np.empty(meas.n_poses)
        for k, test in enumerate(tests):
            p = points[full(i * folds + k, sols[i * folds + k].x).tobytes()]
            d[test] = np.linalg.norm(y[test] - p[test], axis=1)
        out.append(d)
    return out


def widened(cal: Calibration, meas: Measurements, extra: list[Effect], loss: str | None
            ) -> tuple[np.ndarray, np.ndarray]:
    """`cal`'s fit on `meas` with the `extra` effects freed beside it (the same weights, prior and variance factor):
    its covariance over [x[free], effect parameters, the parameters of `extra`], and the move of those parameters
    from `cal`'s estimate (the extra ones at zero) to the widened optimum. The calibration's doubt when something
    fixed in its model (mass data, the model's or identified from these same poses) may be off. The covariance is
    linearised at `cal`'s estimate, so its block of `cal`'s parameters is never narrower than `cal`'s own (a Schur
    complement); refitted to the widened optimum instead, a prediction std narrowed by up to 8 % on one test world
    in ten."""
    effects = list(cal.effects) + list(extra)
    bases = effect_bases(cal.model, meas, effects, cal.basis_x, cal.R0)
    x0, _ = prealign(cal.model, meas)
    start = np.r_[cal.solution.x, np.zeros(bases[0].shape[2] + len(cal.free) - len(cal.solution.x))]
    fit = functools.partial(_fit, cal.model, meas, cal.sigma_mm, x0, cal.R0, cal.free, loss, True, bases,
                            _effect_prior(cal.model, effects), start=start, prior_scale=cal.prior_scale)
    # the move from cal's optimum, a start near the widened one: Gauss-Newton steps at once and at most
    # WARM_MAX_ITER of them, as a fold refitted in full (the iiwa's crawled 97 LM iterations, 1.6 s of its 8.8 s)
    here = fit(max_iter=0)
    there = fit(covariance=False, damping=WARM_DAMPING, ftol=WARM_FTOL, max_iter=WARM_MAX_ITER)
    return here.cov * (cal.solution.s2 / here.s2), there.x - start


def evaluate(cal: Calibration | CalibratedRobot, meas: Measurements) -> dict:
    """Error of a calibration on other (held-out) measurements: rms, mean, max distance in mm."""
    d = np.linalg.norm(meas.points - cal.predict(meas.joints, meas), axis=1)
    return {"n_poses": int(len(d)), "rms_mm": _rms(d), "mean_mm": float(d.mean()), "max_mm": float(d.max())}
