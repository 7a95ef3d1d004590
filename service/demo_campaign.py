"""`calib demo`'s data: the campaign measured in the simulated world or read from the user's files, and what the
story reads off poses and answers."""
from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from calib_core.io import MeasurementError, Measurements, parse_measurements, write_measurements
from calib_core.model import ModelError, RobotModel, parse_model

from .demo_console import DemoError
from .report.figures import finding_title

N_CAL, N_VAL = 150, 100
"""Calibration and validation poses of the simulated campaign."""
HOLDOUT_FRACTION = 0.3
"""Share of a user's poses held out client-side for validation."""
SIZE_RANGE = (4.0, 10.0)
"""A drawn hidden cause's part no geometric parameter can absorb is this many times the noise RMS."""


def _commands(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """The actuated joints' values (N, n_act) in the model's units from row values (N, n) in internal units: what
    predict and compensate take (coupled rows follow, fixed rows do not move)."""
    return q[:, model.actuated] / model.joint_scale()[model.actuated]


def _groups(meas: Measurements, by_payload: bool = False) -> list[np.ndarray]:
    """The rows of each setup (and payload): a predict or compensate request takes one setup (and one payload)."""
    n = meas.n_poses
    keys = np.c_[np.zeros(n) if meas.setup is None else meas.setup, meas.payload_kg() if by_payload else np.zeros(n)]
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    return [np.flatnonzero(inv == g) for g in range(inv.max() + 1)]


def _pose_fields(model: RobotModel, meas: Measurements, rows: np.ndarray) -> dict:
    """A predict or compensate request's setup, and each row's target, measured torques, temperature, time and
    sequence number, as the CSV gives them: without the target, every pose of a set with a marker per payload run
    (the iiwa) was placed at the first marker, and the demo reported 2.2 mm where the service's folds said 0.4 mm;
    without the time and temperature, the twin's compensated poses were measured before a re-homing the compensation
    took as made (0.78-1.25 mm where validation said 0.1) and at other temperatures than the calibration's mean."""
    body: dict = {}
    if meas.temperature is not None:
        body["temperature"] = meas.temperature[rows].tolist()
    if meas.timestamp is not None:
        body["timestamp"] = [datetime.fromtimestamp(t, timezone.utc).isoformat() for t in meas.timestamp[rows]]
    if meas.sequence is not None:
        body["sequence"] = meas.sequence[rows].tolist()
    if meas.setup is not None:
        body["setup"] = meas.setup_names[meas.setup[rows[0]]]
    if meas.target is not None:
        body["target"] = [model.target_names[t] for t in meas.target[rows]]
    if meas.tau is not None:
        tau = meas.tau[rows]
        body["tau"] = {f"tau_{model.joint_names[j]}": [None if np.isnan(v) else float(v) for v in tau[:, j]]
                       for j in range(model.n_joints) if not np.isnan(tau[:, j]).all()}
    return body


UNEXPLAINED = {"smooth_field": "corrected by a smooth joint-space field",
               "joint_driven_offsets": "corrected by offsets of the other joints following one joint",
               None: "not corrected: no correction helped on held-out poses"}


def cause_name(f: dict) -> str:
    """A finding's name in the story: a named cause on its joints, a step in time order, or structure outside the
    vocabulary with the correction the diagnosis kept (never a correction it did not make)."""
    if f["kind"] != "unexplained":
        return finding_title(f)
    if "correction" not in f:  # a step in time order (diagnosis.findings._finding of a SessionStep)
        return finding_title(f)
    said = UNEXPLAINED[f["correction"]]
    if f.get("weighted_as_pose_noise"):
        said = ("not corrected by a model, but what the targets of a pose share is weighted as noise of each pose"
                if f["correction"] is None else said + ", and what the targets of a pose share weighted as noise")
    return f"structure no named cause explains, {said}"


def errors_mm(points_mm: np.ndarray, predicted_mm: np.ndarray) -> dict:
    d = np.linalg.norm(points_mm - predicted_mm, axis=1)
    return {"n": int(len(d)), "rms_mm": float(np.sqrt(np.mean(d**2))), "mean_mm": float(d.mean()),
            "max_mm": float(d.max())}


# ----------------------------------------------------------------------------------------------- data

@dataclass
class Campaign:
    model_doc: dict
    model: RobotModel
    csv_text: str  # what is uploaded
    cal: Measurements  # the uploaded poses, parsed
    val: Measurements  # validation poses, never uploaded
    source: str  # one line: where the data comes from
    validation: str  # one line: what the validation poses are
    twin: object | None = None  # the simulated world (calib_world.World)
    hidden: dict | None = None  # calib_world.hide's description of the hidden cause
    val_truth: np.ndarray | None = None  # noise-free validation points of the simulated world
    n_total: int = 0
    n_planned: int = 0  # the first n_planned calibration poses are the geometric plan's


def spray7_model() -> tuple[dict, RobotModel]:
    """The simulated campaign's robot: its contract JSON and the parsed model."""
    from calib_core.robots import spray7

    doc = spray7()
    return doc, parse_model(doc)


def simulated(effect: str | None, seed: int, planned: np.ndarray | None = None,
              robot: tuple[dict, RobotModel] | None = None) -> Campaign:
    """The twin's campaign: N_CAL calibration poses (the `planned` rows (k, n) first, internal units, then random
    ones), the hidden cause sized on them, and N_VAL random validation poses; all drawn from `seed`. The robot is the
    spray robot, or `robot` (a user's model JSON and its parsed model): a drawn cause its joints cannot show is
    passed over for another one."""
    from calib_world import KINDS, World, hide

    doc, model = robot or spray7_model()
    rng = np.random.default_rng((seed, 1))
    kind = effect or str(rng.choice(KINDS))
    if kind != "none" and kind not in KINDS:
        raise DemoError(f"unknown effect {kind!r}: use one of {', '.join(KINDS)} or none")
    world = World(model, seed)
    hidden = None
    planned = np.zeros((0, model.n_joints)) if planned is None else np.atleast_2d(np.asarray(planned, float))
    size = float(np.exp(rng.uniform(*np.log(SIZE_RANGE)))) if kind != "none" else None
    q = np.vstack([planned, world.sample_joints(N_CAL - len(planned), rng)])
    others = None  # drawn only when a kind is passed over, from a stream of its own: the draws above stay the same
    while kind != "none" and hidden is None:
        try:
            hidden = hide(world, kind, size, rng, q=q)
        except ValueError as exc:  # the robot has no joint that shows it (a rail's straightness on an arm)
            if others is None and effect is None:
                others = [str(k) for k in np.random.default_rng((seed, 2)).permutation(KINDS) if k != kind]
            if not others:
                raise DemoError(f"--effect {kind} cannot be hidden on {model.name}: {exc}") from None
            kind = others.pop(0)
    thermal = bool(hidden and hidden["temperature"])
    cal = world.measure(q, temperature=thermal)
    val = world.campaign(world.sample_joints(N_VAL, rng), temperature=thermal)
    rep = 1000 * world.repeatability_mm
    errors = "the paper's errors" if robot is None else "the errors of a robot as built"
    return Campaign(doc, model, write_measurements(cal, model), cal, val.meas,
                    source=f"simulated: a digital twin of the robot in an independent world (its true geometry "
                           f"off by {errors}, masses not the model's, tool point off by millimetres, laser "
                           f"tracker noise 15 um + 6 um/m, repeatability {rep:.0f} um), seed {seed}",
                    validation=f"{N_VAL} more poses measured on the same twin, never uploaded",
                    twin=world, hidden=hidden, val_truth=val.truth.points, n_total=N_CAL + N_VAL,
                    n_planned=len(planned))


def read_model(robot: Path) -> tuple[dict, RobotModel]:
    """A user's model JSON and the parsed model; DemoError saying what is wrong with the file."""
    try:
        doc = json.loads(robot.read_text())
    except (OSError, ValueError) as exc:
        raise DemoError(f"cannot read the model {robot}: {exc}") from None
    try:
        return doc, parse_model(doc)
    except ModelError as exc:
        raise DemoError(f"the model {robot} is not valid: {exc}") from None


def from_files(robot: Path, data: Path, seed: int, instrument: str | None = None, limits: str = "reject") -> Campaign:
    doc, model = read_model(robot)
    try:
        text = data.read_text(encoding="utf-8-sig")
        meas = parse_measurements(text, model, instrument=instrument, limits=limits)
    except OSError as exc:
        raise DemoError(f"cannot read the measurements {data}: {exc}") from None
    except MeasurementError as exc:
        listed = "".join(f"\n    {', '.join(f'{k} {e[k]}' for k in ('row', 'column') if e[k] is not None)}: "
                         f"{e['message']}" for e in exc.errors[:10])
        raise DemoError(f"{data} does not fit the contract CSV ({exc.total} error{'s' if exc.total != 1 else ''}):"
                        f"{listed}") from None
    lines = text.splitlines()
    body = [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    header, rows = body[0], body[1:]
    if len(rows) != meas.n_poses:
        raise DemoError(f"{data}: {len(rows)} data lines but {meas.n_poses} poses parsed")
    n_val = int(round(HOLDOUT_FRACTION * meas.n_poses))
    if meas.n_poses - n_val < 30 or n_val < 5:
        raise DemoError(f"{data} has {meas.n_poses} poses: too few to hold out {100 * HOLDOUT_FRACTION:.0f} %")
    # the targets measured at one pose go to the same side (they share the pose's errors); one target: row by row
    unit = meas.pose_index()
    n_units = int(unit.max()) + 1
    n_val_units = int(round(HOLDOUT_FRACTION * n_units))
    perm = np.random.default_rng(seed).permutation(n_units)
    held = np.isin(unit, perm[:n_val_units])
    val_idx, cal_idx = np.flatnonzero(held), np.flatnonzero(~held)
    upload = "\n".join([lines[header]] + [lines[rows[i]] for i in cal_idx]) + "\n"
    share = f"{100 * HOLDOUT_FRACTION:.0f} %"
    held_out = f"{len(val_idx)} poses ({share})" if n_units == meas.n_poses else \
        f"{len(val_idx)} rows (the targets of {n_val_units} poses together, {share})"
    return Campaign(doc, model, upload, meas.subset(cal_idx), meas.subset(val_idx),
                    source=f"{data} ({counted(meas)}) and the model {robot}",
                    validation=f"{held_out} held out at random (seed {seed}) before the upload, never seen by the "
                               "service",
                    n_total=meas.n_poses)


def _n_poses(meas: Measurements) -> int:
    """Poses of the robot: the rows measuring several targets at one placement count once (Measurements.pose_index)."""
    return int(meas.pose_index().max()) + 1 if meas.n_poses else 0


def _unit(meas: Measurements) -> str:
    """What a row of `meas` is: a pose (one target per placement), else a row (one target of a pose)."""
    return "poses" if _n_poses(meas) == meas.n_poses else "rows"


def counted(meas: Measurements, brief: bool = False) -> str:
    """What the rows of a measurement set are, in words: poses, or rows of several targets (markers) per pose; the
    6-D rows and the points the fit makes of them. Agile Justin's "1000 measured poses" were 500 poses x 2 markers,
    the iiwa's 554 rows 2216 points in the answer's metrics."""
    from calib_core.orientation import LEVER_MM

    rows, poses = meas.n_poses, _n_poses(meas)
    if poses == rows:
        out = f"{rows} measured poses"
    else:
        per = np.bincount(meas.pose_index())
        targets = len(np.unique(meas.target)) if meas.target is not None else 1
        out = (f"{rows} rows: {poses} poses x {per[0]} targets (markers)" if (per == per[0]).all() else
               f"{rows} rows: {poses} poses, {per.min()} to {per.max()} of the {targets} targets (markers) each")
    if meas.orientation is not None and (n6 := int((~np.isnan(meas.orientation[:, 0])).sum())):
        each = "each" if n6 == rows else f"{n6} of them"
        out += (f" ({'' if n6 == rows else f'{n6} '}6-D: {rows + 3 * n6} points in the fit)" if brief else
                f"; {each} 6-D (a point and an orientation): the fit takes each 6-D row as its point and 3 virtual "
                f"points {LEVER_MM:g} mm along the measured axes, {rows + 3 * n6} points in all")
    return out
