"""Calibrations: read the stored answer, predict with calib_core's CalibratedRobot."""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
from sqlalchemy.orm import Session

from calib_core.compensate import compensate as solve_compensation
from calib_core.compensate import nominal_to_calibrated
from calib_core.identify import CalibratedRobot
from calib_core.io import Measurements
from calib_core.model import LENGTH_TO_MM

from ..problems import ProblemError, get_or_404
from ..report import decorate
from ..robots.models import Robot
from ..robots.schemas import iso
from ..robots.service import model_of
from .models import Calibration


def get_calibration(s: Session, cal_id: str) -> Calibration:
    return get_or_404(s, Calibration, cal_id, "calibration")


def answer(c: Calibration) -> dict:
    out = {"id": c.id, "job_id": c.job_id, "robot_id": c.robot_id, "measurement_set_id": c.measurement_set_id}
    out.update(c.result)
    out.setdefault("model", ["geometric"])
    out.setdefault("parameters", [])
    out.setdefault("metrics", {})
    out["created_at"] = iso(c.created_at)
    return decorate(out, f"/calibrations/{c.id}")


def report(c: Calibration, inline: bool = False) -> str:
    """The HTML report of the stored answer (the same dict `GET /calibrations/{id}` returns)."""
    from ..report import html as report_html

    a = answer(c)
    return report_html.render(a, (lambda name: plot_png(c, name, a)) if inline else None)


def plot_png(c: Calibration, name: str, a: dict | None = None) -> bytes:
    from ..report import plots as report_plots

    a = a if a is not None else answer(c)
    try:
        return report_plots.png(a, name, cache_key=c.id)
    except report_plots.UnknownPlot:
        have = ", ".join(p["name"] for p in a["plots"]) or "none (plots come with the auto model's diagnosis)"
        raise ProblemError(404, f"calibration {c.id!r} has no plot {name!r}; it has: {have}",
                           kind="not-found") from None


def _per_pose(name: str, v, n: int, errors: list) -> np.ndarray | None:
    if v is None:
        return None
    if isinstance(v, list) and len(v) != n:
        errors.append({"field": f"body.{name}", "value": len(v), "message": "one value per pose, or one value"})
        return None
    return np.broadcast_to(np.asarray(v, float), (n,)).copy()


def _epoch(stamps, errors: list):
    if stamps is None:
        return None
    out = []
    for i, t in enumerate(stamps if isinstance(stamps, list) else [stamps]):
        try:
            d = datetime.fromisoformat(t.replace("Z", "+00:00"))
        except ValueError:
            errors.append({"field": f"body.timestamp[{i}]", "value": t,
                           "message": "not an ISO 8601 timestamp (e.g. 2026-11-03T08:00:19+00:00)"})
            out.append(float("nan"))
            continue
        out.append((d if d.tzinfo else d.replace(tzinfo=timezone.utc)).timestamp())
    return out if isinstance(stamps, list) else (out[0] if out else None)


def predict(s: Session, c: Calibration, joints: list[list[float]], payload, temperature=None,
            timestamp=None) -> tuple[list[list[float]], str]:
    model = model_of(s.get(Robot, c.robot_id))
    n = model.n_joints
    errors = [{"field": f"body.joints[{i}]", "value": len(row), "message": f"expected {n} joint values "
               f"({', '.join(model.joint_names)})"} for i, row in enumerate(joints) if len(row) != n]
    if isinstance(payload, list) and len(payload) != len(joints):
        errors.append({"field": "body.payload", "value": len(payload), "message": "one payload per pose, or one number"})
    temp = _per_pose("temperature", temperature, len(joints), errors)
    stamps = _per_pose("timestamp", _epoch(timestamp, errors), len(joints), errors)
    if errors:
        raise ProblemError(422, "the joints do not fit the robot model", kind="validation", errors=errors[:1000])
    q = np.asarray(joints, float) * model.joint_scale()
    robot = CalibratedRobot.from_state(model, c.robot_state)
    load = None if payload is None else np.broadcast_to(np.asarray(payload, float), (len(q),)).copy()
    p_mm = robot.predict(q, Measurements(joints=q, points=np.zeros((len(q), 3)), payload=load, temperature=temp,
                                         timestamp=stamps))
    return (p_mm / LENGTH_TO_MM[model.length_unit]).tolist(), model.length_unit


def compensate(s: Session, c: Calibration, body) -> dict:
    """Joint commands for targets (or for a joints-only program) with the calibrated model and its effects."""
    model = model_of(s.get(Robot, c.robot_id))
    n = model.n_joints
    errors = []
    program = body.program_joints is not None
    if program == (body.targets is not None):
        errors.append({"field": "body", "value": None, "message": "give either targets with seed_joints, "
                                                                  "or program_joints"})
    rows = body.program_joints if program else body.seed_joints
    if not program and body.targets is not None and rows is None:
        errors.append({"field": "body.seed_joints", "value": None, "message": "seed_joints are required with targets"})
    errors += [{"field": f"body.{'program_joints' if program else 'seed_joints'}[{i}]", "value": len(r),
                "message": f"expected {n} joint values ({', '.join(model.joint_names)})"}
               for i, r in enumerate(rows or []) if len(r) != n]
    if not program and body.targets is not None:
        errors += [{"field": f"body.targets[{i}]", "value": len(t), "message": "expected x, y, z"}
                   for i, t in enumerate(body.targets) if len(t) != 3]
        if rows is not None and len(rows) != len(body.targets):
            errors.append({"field": "body.seed_joints", "value": len(rows),
                           "message": f"one seed per target ({len(body.targets)})"})
    errors += [{"field": "body.locked_joints", "value": j, "message": f"unknown joint; the model has "
                f"{', '.join(model.joint_names)}"} for j in body.locked_joints if j not in model.joint_names]
    if errors:
        raise ProblemError(422, "the request does not fit the robot model", kind="validation", errors=errors[:1000])
    q = np.asarray(rows, float).reshape(-1, n) * model.joint_scale()
    robot = CalibratedRobot.from_state(model, c.robot_state)
    columns = Measurements(joints=q, points=np.zeros((len(q), 3)),
                           payload=None if body.payload is None else np.full(len(q), body.payload))
    locked = tuple(body.locked_joints)
    if program:
        result = nominal_to_calibrated(robot, None, q, locked=locked, columns=columns)
    else:
        targets = np.asarray(body.targets, float).reshape(-1, 3) * LENGTH_TO_MM[model.length_unit]
        result = solve_compensation(robot, targets, q, locked=locked, columns=columns)
    out = result.to_dict(model)
    out["unit"] = {"length": model.length_unit, "angle": model.angle_unit}
    return out
