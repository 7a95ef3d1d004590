"""6-D measurements (contract section 5: `qw, qx, qy, qz`) as three virtual points per row.

A measured orientation R (target frame in the measurement frame) says where three points rigidly fixed to the
target frame are: p + L R e_x, p + L R e_y, p + L R e_z with a lever L (mm). Each becomes a point row of its own
virtual target on the same joint, so the orientation enters the identification, its held-out test and the
diagnosis through the one point machinery, weighted by its own noise: per axis
sqrt(sigma_point^2 + (L sigma_rad)^2), sigma_rad from the instrument preset. The virtual targets' points are
identified like any target's (9 numbers where the marker's rotation offset has 3: a small loss of rigidity for
no new code path); they start where the measured orientations put them (a chordal mean of the offset between
the nominal target frame and the measured one), so the pre-alignment and the prior start near the truth.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import kinematics as K
from .instruments import instrument
from .io import Measurements
from .model import RobotModel

LEVER_MM = 100.0
"""Distance of the virtual points from the target: an orientation error of 1 mrad moves them by 0.1 mm."""
AXES = ("x", "y", "z")
MARK = "~"
"""Virtual targets are named '<target>~x' etc."""


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of unit quaternions (N, 4) w, x, y, z."""
    w, x, y, z = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def n_virtual(model: RobotModel) -> int:
    """How many of the model's targets are virtual (appended last)."""
    return sum(MARK in t for t in model.target_names)


def with_orientation(model: RobotModel, meas: Measurements, lever_mm: float = LEVER_MM
                     ) -> tuple[RobotModel, Measurements]:
    """The model with three virtual targets per oriented target, and the measurements with three virtual point
    rows appended per 6-D row (both unchanged when no row carries an orientation)."""
    if meas.orientation is None or np.isnan(meas.orientation[:, 0]).all():
        return model, meas
    rows = np.flatnonzero(~np.isnan(meas.orientation[:, 0]))
    target = np.zeros(meas.n_poses, int) if meas.target is None else meas.target
    Rm = quaternion_matrix(meas.orientation[rows])
    # the base rotation from a rigid fit of the nominal points, then the target frame's rotation offset
    ch = K.Chain(model, K.nominal_vector(model, n_setups=meas.n_setups), meas.joints,
                 np.broadcast_to(np.eye(3), (meas.n_setups, 3, 3)) if meas.n_setups > 1 else None, meas.labels)
    setup = np.zeros(meas.n_poses, int) if meas.setup is None else meas.setup
    Rbase = np.empty((meas.n_setups, 3, 3))
    for s in range(meas.n_setups):
        Rbase[s] = K.rigid_fit(ch.p[setup == s], meas.points[setup == s])[0]
    sig_pt = meas.noise_sigma_mm()
    sig_virtual = np.sqrt(sig_pt[rows] ** 2 + (lever_mm * instrument(meas.instrument).sigma_rad) ** 2)
    targets = list(zip(model.target_names, model.target_rows, model.target_points))
    add_joints, add_points, add_target, add_sigma, add_rows = [], [], [], [], []
    for t in np.unique(target[rows]):
        mine = target[rows] == t
        i = rows[mine]
        R_off, _ = _offset(ch.R_end[i], Rbase[setup[i]], Rm[mine])
        name, row, xyz = targets[t]
        for k, axis in enumerate(AXES):
            add_target.append(np.full(len(i), len(targets)))
            targets.append((f"{name}{MARK}{axis}", row, xyz + lever_mm * R_off[:, k]))
            add_joints.append(meas.joints[i])
            add_points.append(meas.points[i] + lever_mm * Rm[mine][:, :, k])
            add_sigma.append(sig_virtual[mine])
            add_rows.append(i)
    virtual = dataclasses.replace(model, targets=tuple(targets))
    src = np.concatenate(add_rows)
    pick = lambda a: None if a is None else np.r_[a, a[src]]  # noqa: E731
    ids = list(meas.point_ids) + [f"{meas.point_ids[i] if meas.point_ids else i + 1}{MARK}{a}"
                                  for a, rr in zip(AXES * (len(add_rows) // 3), add_rows) for i in rr]
    out = Measurements(joints=np.r_[meas.joints, np.concatenate(add_joints)],
                       points=np.r_[meas.points, np.concatenate(add_points)], point_ids=ids,
                       timestamp=pick(meas.timestamp), sequence=pick(meas.sequence),
                       temperature=pick(meas.temperature), payload=pick(meas.payload),
                       sigma=np.r_[sig_pt, np.concatenate(add_sigma)], instrument=meas.instrument,
                       target=np.r_[target, np.concatenate(add_target)], setup=pick(meas.setup),
                       setup_names=meas.setup_names, orientation=None, tau=pick(meas.tau),
                       sigma_source=_sigma_source(meas))
    return virtual, out


def _sigma_source(meas: Measurements) -> str:
    """What the expanded rows' sigma comes from: the CSV's own column, or the instrument preset (the virtual points'
    sigma is computed from it here, which must not read as a CSV column: the iiwa's answer said "from the CSV's
    sigma column" of a CSV that has none)."""
    said = meas.noise_source()
    return f"{said}; orientation noise from the {instrument(meas.instrument).name} preset" if meas.sigma is not None \
        else f"{said}, orientation noise included"


def _offset(R_end: np.ndarray, Rbase: np.ndarray, Rm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The marker frame in the target's row frame, the chordal mean of R_end^T Rbase^T R_meas over the rows
    (3, 3), and each row's angle (deg) from it."""
    each = np.einsum("nba,nbc->nac", R_end, np.einsum("nba,nbc->nac", Rbase, Rm))
    U, _, Vt = np.linalg.svd(each.sum(0))
    R_off = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    cos = (np.einsum("ab,nab->n", R_off, each) - 1.0) / 2.0
    return R_off, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def offset_spread_deg(model: RobotModel, meas: Measurements) -> dict[str, np.ndarray]:
    """Per target with 6-D rows: each row's angle (deg) between its measured marker rotation and the one
    constant marker-in-flange rotation the virtual points assume (nominal geometry, rigidly fitted base).
    Beyond the orientation noise and the model's own angular errors (tenths of a degree) it says the marker
    was not rigidly the target's: e.g. mounted anew between sessions, which needs a target per mounting."""
    if meas.orientation is None or np.isnan(meas.orientation[:, 0]).all():
        return {}
    rows = np.flatnonzero(~np.isnan(meas.orientation[:, 0]))
    target = np.zeros(meas.n_poses, int) if meas.target is None else meas.target
    setup = np.zeros(meas.n_poses, int) if meas.setup is None else meas.setup
    ch = K.Chain(model, K.nominal_vector(model, n_setups=meas.n_setups), meas.joints,
                 np.broadcast_to(np.eye(3), (meas.n_setups, 3, 3)) if meas.n_setups > 1 else None, meas.labels)
    Rbase = np.stack([K.rigid_fit(ch.p[setup == s], meas.points[setup == s])[0] for s in range(meas.n_setups)])
    Rm = quaternion_matrix(meas.orientation[rows])
    out = {}
    for t in np.unique(target[rows]):
        mine = target[rows] == t
        out[model.target_names[t]] = _offset(ch.R_end[rows[mine]], Rbase[setup[rows[mine]]], Rm[mine])[1]
    return out


def without_virtual(model: RobotModel, x: np.ndarray) -> np.ndarray:
    """A parameter vector of the model with virtual targets, cut to the model without them (they come last)."""
    k = n_virtual(model)
    return x[: len(x) - 3 * k] if k else x
