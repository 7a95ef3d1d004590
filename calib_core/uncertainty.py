"""How well a calibration predicts the tool point at new poses: delta-method propagation of its covariance.

The predicted point p(q) = FK(x, q + Phi_q theta) + Phi_p theta depends on the solved geometric parameters
x[free] and the effect parameters theta. Its Jacobian at new poses is the coupled Jacobian of the fit
(identify._fit): the geometric columns dp/dx[free] at q + dq, and the effect columns J_q Phi_q + Phi_p, with
the effect bases evaluated on the calibrated geometry (as CalibratedRobot.predict does). Then
cov(p_i) = G_i cov(x[free], theta) G_i^T per pose, (3, 3) mm^2.

Like the parameter std, this is conditional on the identified model being the right one: it says how much the
parameters' estimation error moves the prediction (see identify.UNCERTAINTY_NOTE). When the diagnosis leaves
held-out structure significantly above the noise floor that no cause in the model explains, that de-noised model
error (`Calibration.unmodelled_mm`, per axis) is added in quadrature: a prediction cannot be surer than the part
of the robot the model does not describe. Mass data the diagnosis identified are fixed in the model, but they were
estimated from the same poses, and the model's own may be 15 % off: their doubt is propagated through one more
Gauss-Newton step of them (`Calibration.mass_doubt`: the step's columns beside the model's and the joint covariance
of that fit). The step's optimum moves the prediction by d; the prediction keeps the model's mass data (a richer
mass model must earn its place on held-out poses), so it carries d d^T too, the posterior mean square of that bias
(on the world's elastic bearings, where the mass data matter most, prediction z 1.52 -> 1.14 on one draw). A step in
time found by the diagnosis lies somewhere between two measured poses, and a gear play's switch somewhere near where
its load changes sign: a pose there carries what the other side would cost with its chance of being there.
Directions the data and the prior leave undetermined carry no variance in `solution.cov` (see solve.py): a
prediction along them is not covered.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import kinematics as K
from .effects import Backlash, Context, SessionStep
from .calibrated import CalibratedRobot, _columns
from .identify import Calibration, effect_bases
from .io import Measurements


def prediction_jacobian(cal: Calibration, joints, columns: Measurements | None = None, extra=()) -> np.ndarray:
    """d predicted point / d [x[free], effect parameters] at the poses, (N, 3, p) with p = len(cal.solution.x), then
    the columns of the `extra` effects (not in the prediction, such as a mass-data step)."""
    q = np.atleast_2d(np.asarray(joints, float))
    model = cal.model
    labels = None if columns is None else columns.labels
    if not cal.effects and not extra:
        return K.Chain(model, cal.x, q, cal.R0, labels).jacobian_columns(cal.free)
    meas = _columns(q, columns)
    Phi_q, Phi_p = effect_bases(model, meas, list(cal.effects) + list(extra), cal.basis_x, cal.R0)
    theta = cal.solution.x[len(cal.free):]
    k = len(theta)
    chain = K.Chain(model, cal.x, q + Phi_q[:, :, :k] @ theta, cal.R0, labels)
    J_eff = np.einsum("nij,njk->nik", chain.joint_jacobian(), Phi_q) + Phi_p
    return np.concatenate([chain.jacobian_columns(cal.free), J_eff], axis=2)


def prediction_cov(cal: Calibration, joints, columns: Measurements | None = None) -> np.ndarray:
    """Covariance (N, 3, 3) mm^2 of the predicted point at each pose: the parameters' covariance propagated (with
    the identified mass data's doubt where the diagnosis identified them), plus the unmodelled part the diagnosis
    measured, plus the poses that may be on the other side of a switch."""
    extra = cal.mass_doubt[:1]
    G = prediction_jacobian(cal, joints, columns, extra)
    if extra and cal.mass_doubt[1].shape[0] == G.shape[2]:
        C, move = cal.mass_doubt[1:]
    else:
        G, C, move = G[:, :, :len(cal.solution.x)], cal.solution.cov, None
    out = np.einsum("nip,pq,njq->nij", G, C, G)
    if move is not None:  # the mass data's posterior mean is off the model's: the kept prediction's bias
        d = G @ move
        out += d[:, :, None] * d[:, None, :]
    return 0.5 * (out + np.swapaxes(out, 1, 2)) + cal.unmodelled_mm**2 * np.eye(3) + _misplaced(cal, joints, columns)


def _misplaced(cal: Calibration, joints, columns: Measurements | None) -> np.ndarray:
    """(N, 3, 3) mm^2: what a switch the model places costs a pose that may be on its other side, the mean square
    error (not the variance about the prediction, which is what a z-score divides by): sum of P d d^T over
    switch_doubts."""
    q = np.atleast_2d(np.asarray(joints, float))
    out = np.zeros((len(q), 3, 3))
    for _, P, d in switch_doubts(cal.robot, _columns(q, columns)):
        out += P[:, None, None] * d[:, :, None] * d[:, None, :]
    return out


def switch_doubts(robot: CalibratedRobot, meas: Measurements) -> list[tuple]:
    """Per switch the model places, (the effect, P (N,), d (N, 3) mm): a pose on the switch's other side is off by d,
    with mean square weight P. A step in time lies somewhere between the two measured poses it fell between: P the
    chance of the wrong side (SessionStep.misplaced), d the step's whole displacement. A gear play's flank is in doubt
    where the load is near zero: P the flank factor's mean square error (Backlash.flank_doubt), d the half play's
    displacement."""
    switches = [(e, v) for e, v in zip(robot.effects, robot.effect_values)
                if (isinstance(e, SessionStep) and e.gap) or
                (isinstance(e, Backlash) and (e.switch_width > 0 or e.switch_draws))]
    if not switches or not meas.n_poses:
        return []
    Jq = robot.chain(meas.joints, meas)[0].joint_jacobian()
    ctx = Context.at(robot.model, robot.basis_x, meas, robot.R0)
    out = []
    for e, v in switches:
        if isinstance(e, SessionStep):
            every = np.full(meas.n_poses, np.inf)
            other = dataclasses.replace(meas, timestamp=every, sequence=every)  # every pose after the step
            Phi_q, Phi_p = effect_bases(robot.model, other, [e], robot.basis_x, robot.R0)
            d = np.einsum("nij,njk,k->ni", Jq, Phi_q, v) + np.einsum("nik,k->ni", Phi_p, v)
            out.append((e, e.misplaced(ctx), d))
        else:
            out.append((e, e.flank_doubt(ctx), 0.5 * v[0] * Jq[:, :, e.joints[0]]))
    return out


def prediction_std_mm(cal: Calibration, joints, columns: Measurements | None = None) -> np.ndarray:
    """1-sigma (N, 3) mm of the predicted point per coordinate (measurement frame) at each pose."""
    cov = prediction_cov(cal, joints, columns)
    return np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))


def z_scores(cal: Calibration, joints, truth: np.ndarray, columns: Measurements | None = None) -> np.ndarray:
    """(predicted - truth) / prediction std per coordinate, (N, 3): RMS ~ 1 when the std is honest."""
    pred = cal.predict(np.atleast_2d(np.asarray(joints, float)), columns)
    std = prediction_std_mm(cal, joints, columns)
    return (pred - np.asarray(truth, float)) / np.maximum(std, 1e-300)
