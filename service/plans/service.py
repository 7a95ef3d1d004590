"""Pose planning: which poses to measure, from a stored robot (and measurement set), with calib_core.plan.

The database is read in one short transaction (robot, measurement set, its latest calibration), then the plan is
computed outside it, in a plan process of its own (pool.py, a lane: bounded in number and time, 503 when busy): a diagnosis
plan refits the rival models and takes a few seconds.
"""
from __future__ import annotations

import csv
import io
from typing import NamedTuple

import anyio.to_thread
import numpy as np
from sqlalchemy import select

from calib_core.identify import CalibratedRobot, identify
from calib_core.io import Measurements
from calib_core.model import LENGTH_TO_MM, MAX_POINT_MM, RobotModel
from calib_core.plan import Plan, lookalike_pairs, plan, tracker_of

from ..calibrations.models import Calibration
from ..calibrations.service import restored
from ..db import Database
from ..measurements.models import MeasurementSet
from ..measurements.service import parse_or_reject
from ..problems import ProblemError
from ..robots.service import get_robot, model_of
from . import pool
from .schemas import PlanIn

AUTO_JOB = 'POST /jobs {"measurement_set_id": "%s", "model": "auto"}'


def _invalid(field: str, value, message: str) -> ProblemError:
    return ProblemError(422, message, kind="validation", errors=[{"field": field, "value": value, "message": message}])


def _latest_calibration(s, ms_id: str, with_diagnosis: bool) -> Calibration | None:
    """The set's newest calibration (with a diagnosis block: an `auto` one)."""
    for c in s.scalars(select(Calibration).where(Calibration.measurement_set_id == ms_id)
                       .order_by(Calibration.created_at.desc(), Calibration.id.desc())):
        if not with_diagnosis or isinstance(c.result.get("diagnosis"), dict):
            return c
    return None


class _Cal(NamedTuple):
    """What a plan uses of a stored calibration, as plain data (it crosses to a plan process)."""
    id: str
    result: dict
    robot_state: dict


def _load(db: Database, robot_id: str, body: PlanIn) -> tuple[RobotModel, tuple | None, _Cal | None]:
    """The robot's model, the measurement set's (raw, instrument, limits) and the calibration the plan starts
    from: for `diagnosis` the newest `auto` one, else the newest of any kind (for the tracker's position)."""
    with db.read_session() as s:
        model = model_of(get_robot(s, robot_id))
        ms_id = body.measurement_set_id
        if ms_id is None:
            if body.purpose == "diagnosis":
                raise _invalid("body.measurement_set_id", None, "a diagnosis plan needs the measurement set whose "
                               "calibration lists look-alike causes (indistinguishable_from)")
            return model, None, None
        ms = None if "\x00" in ms_id else s.get(MeasurementSet, ms_id)
        if ms is None:
            raise _invalid("body.measurement_set_id", ms_id, "no such measurement set")
        if ms.robot_id != robot_id:
            raise _invalid("body.measurement_set_id", ms_id, f"this measurement set belongs to robot {ms.robot_id!r}")
        raw, instrument, limits = ms.raw, ms.instrument, ms.limits or "reject"
        c = _latest_calibration(s, ms_id, body.purpose == "diagnosis")
        cal = None if c is None else _Cal(c.id, c.result, c.robot_state)
    if body.purpose == "diagnosis" and cal is None:
        raise _invalid("body.measurement_set_id", ms_id, "this measurement set has no `auto` calibration yet: run "
                       f"{AUTO_JOB % ms_id} and plan once it has succeeded")
    return model, (raw, instrument, limits), cal


def _tracker_mm(model: RobotModel, body: PlanIn, meas: Measurements | None, robot: CalibratedRobot | None):
    """The tracker in the base frame (mm): as given, else where the set was measured from (its calibration's base
    pose, or a registration of base and tool), else None (calib_core's default)."""
    if body.tracker is not None:
        mm = np.asarray(body.tracker, float) * LENGTH_TO_MM[model.length_unit]
        if np.abs(mm).max() > MAX_POINT_MM:
            raise _invalid("body.tracker", body.tracker, f"implausible: each coordinate must be within "
                           f"{MAX_POINT_MM / LENGTH_TO_MM[model.length_unit]:g} {model.length_unit} of the robot base")
        return mm
    if robot is not None:
        return tracker_of(robot)
    if meas is not None:
        return tracker_of(identify(model, meas, free=("base", "tool"), folds=0).robot)
    return None


def _rivals(model: RobotModel, meas: Measurements, cal: _Cal, robot: CalibratedRobot, ms_id: str) -> list:
    findings = cal.result["diagnosis"].get("findings") or []
    pairs = lookalike_pairs(model, meas, robot.effects, findings)
    if not pairs:
        said = "lists no look-alike causes (no finding has indistinguishable_from)" if not any(
            f.get("indistinguishable_from") for f in findings) else ("lists look-alikes no plan can split (nested "
                                                                     "or not rebuilt: each has `plannable` false)")
        raise _invalid("body.measurement_set_id", ms_id, f"its newest auto calibration ({cal.id}) {said}: there is "
                       "nothing to split; plan `geometric` poses instead")
    return pairs


def make_plan(db: Database, robot_id: str, body: PlanIn, processes: int = 0, timeout_s: float = 60.0,
              room: int | None = None) -> dict:
    """The plan answer (contract section 5): poses in model units, actuated joint order, and their observability.
    The database is read here; the plan is computed in a plan process (processes > 0, bounded in number, `room`
    waiting and timeout_s, see pool.py) or here (0)."""
    model, stored, cal = _load(db, robot_id, body)
    if processes > 0:
        return pool.configure(processes, timeout_s, room).run(compute, (model, stored, cal, body))
    return compute(model, stored, cal, body)


async def make_plan_async(db: Database, robot_id: str, body: PlanIn, processes: int = 0, timeout_s: float = 60.0,
                          room: int | None = None) -> dict:
    """make_plan for an async route: the database is read on a route thread, then the plan waits for its process on
    the event loop (a waiting plan holds no route thread: the lane's room can be larger than the route threads)."""
    model, stored, cal = await anyio.to_thread.run_sync(_load, db, robot_id, body)
    if processes > 0:
        return await pool.configure(processes, timeout_s, room).arun(compute, (model, stored, cal, body))
    return await anyio.to_thread.run_sync(compute, model, stored, cal, body)


def compute(model: RobotModel, stored: tuple | None, cal: _Cal | None, body: PlanIn) -> dict:
    """The plan from what _load read: the set parsed as its jobs parse it, the calibration restored, then plan()."""
    meas = None
    if stored is not None:
        raw, instrument, limits = stored
        meas = parse_or_reject(raw, model, instrument, limits)
    robot = None if cal is None else restored(model, cal)
    rivals = _rivals(model, meas, cal, robot, body.measurement_set_id) if body.purpose == "diagnosis" else ()
    tracker = _tracker_mm(model, body, meas, robot)
    try:
        p = plan(model, body.n_poses, body.purpose, seed=body.seed, tracker_mm=tracker,
                 max_incidence_deg=body.max_incidence_deg, meas=meas, effects=() if robot is None else robot.effects,
                 rivals=rivals)
    except np.linalg.LinAlgError:  # a numerical failure is ours, not the request's: a 500, never a 422 on n_poses
        raise
    except ValueError as exc:  # too few candidates face the tracker
        field, value = (("body.tracker", body.tracker) if body.tracker is not None else
                        ("body.max_incidence_deg", body.max_incidence_deg) if body.max_incidence_deg is not None
                        else ("body.n_poses", body.n_poses))
        raise _invalid(field, value, str(exc)) from None
    return answer(model, p)


def answer(model: RobotModel, p: Plan) -> dict:
    return {"joints": p.model_units(model).tolist(), "joint_names": list(model.actuated_names),
            "unit": {"length": model.length_unit, "angle": model.angle_unit},
            "targets": None if p.target is None else [model.target_names[t] for t in p.target],
            "payload_kg": None if p.payload is None else p.payload.tolist(), "observability": p.observability}


def plan_csv(model: RobotModel, p: Plan) -> str:
    """The plan as CSV a robot program can run: `point` and the actuated joints in model units (plus `target` and
    `payload` where the plan has them); `#` lines say what it is (the contract's CSV skips them). Add x, y, z
    (and `timestamp`) as measured and it uploads as a measurement set."""
    a = answer(model, p)
    obs = p.observability
    out = io.StringIO()
    out.write(f"# calib plan: {obs['n_poses']} poses, purpose {obs['purpose']} ({obs['criterion'].split(':')[0]}), "
              f"seed {obs['seed']}\n# joints in {model.length_unit} / {model.angle_unit}; tracker at "
              f"{', '.join(f'{v / LENGTH_TO_MM[model.length_unit]:.6g}' for v in obs['tracker_mm'])} "
              f"{model.length_unit} in the robot base frame, incidence <= {obs['max_incidence_deg']:g} deg\n")
    w = csv.writer(out, lineterminator="\n")
    extra = (["target"] if a["targets"] else []) + (["payload"] if a["payload_kg"] else [])
    w.writerow(["point", *a["joint_names"], *extra])
    for i, row in enumerate(a["joints"]):
        more = ([a["targets"][i]] if a["targets"] else []) + ([f"{a['payload_kg'][i]:g}"] if a["payload_kg"] else [])
        w.writerow([f"Q{i + 1:03d}", *(f"{v:.6f}" for v in row), *more])
    return out.getvalue()
