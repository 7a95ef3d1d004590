"""Calibrations: read the stored answer, predict with calib_core's CalibratedRobot."""
from __future__ import annotations

import numpy as np
from sqlalchemy.orm import Session

from calib_core.identify import CalibratedRobot
from calib_core.io import Measurements
from calib_core.model import LENGTH_TO_MM

from ..problems import ProblemError, not_found
from ..robots.models import Robot
from ..robots.schemas import iso
from ..robots.service import model_of
from .models import Calibration


def get_calibration(s: Session, cal_id: str) -> Calibration:
    c = s.get(Calibration, cal_id)
    if c is None:
        raise not_found("calibration", cal_id)
    return c


def answer(c: Calibration) -> dict:
    out = {"id": c.id, "job_id": c.job_id, "robot_id": c.robot_id, "measurement_set_id": c.measurement_set_id}
    out.update(c.result)
    out.setdefault("model", ["geometric"])
    out.setdefault("parameters", [])
    out.setdefault("metrics", {})
    out["created_at"] = iso(c.created_at)
    return out


def predict(s: Session, c: Calibration, joints: list[list[float]], payload) -> tuple[list[list[float]], str]:
    model = model_of(s.get(Robot, c.robot_id))
    n = model.n_joints
    errors = [{"field": f"body.joints[{i}]", "value": len(row), "message": f"expected {n} joint values "
               f"({', '.join(model.joint_names)})"} for i, row in enumerate(joints) if len(row) != n]
    if isinstance(payload, list) and len(payload) != len(joints):
        errors.append({"field": "body.payload", "value": len(payload), "message": "one payload per pose, or one number"})
    if errors:
        raise ProblemError(422, "the joints do not fit the robot model", kind="validation", errors=errors[:1000])
    q = np.asarray(joints, float) * model.joint_scale()
    robot = CalibratedRobot.from_state(model, c.robot_state)
    load = None if payload is None else np.broadcast_to(np.asarray(payload, float), (len(q),)).copy()
    p_mm = robot.predict(q, Measurements(joints=q, points=np.zeros((len(q), 3)), payload=load))
    return (p_mm / LENGTH_TO_MM[model.length_unit]).tolist(), model.length_unit
