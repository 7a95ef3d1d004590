"""Calibrations: read the stored answer, predict with calib_core's CalibratedRobot."""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, object_session

from calib_core.compensate import compensate as solve_compensation
from calib_core.compensate import nominal_to_calibrated
from calib_core.calibrated import CalibratedRobot, StaleState
from calib_core.io import MAX_SEQUENCE, MAX_TAU, Measurements
from calib_core.model import (ANGLE_TO_RAD, JOINT_MARGIN_FRACTION, LENGTH_TO_MM, MAX_PAYLOAD_KG, MAX_POINT_MM,
                               MAX_REVOLUTE_DEG, TEMPERATURE_RANGE_C, TIMESTAMP_RANGE_S, TIMESTAMP_RANGE_UTC,
                               RobotModel)

from ..problems import MAX_ERRORS, ProblemError, get_or_404
from ..report import decorate
from ..report.models import CalibrationPlot
from ..robots.models import Robot
from ..robots.schemas import iso
from ..robots.service import model_of
from .models import Calibration


def get_calibration(s: Session, cal_id: str) -> Calibration:
    return get_or_404(s, Calibration, cal_id, "calibration")


def restored(model: RobotModel, c) -> CalibratedRobot:
    """The stored calibration for prediction; a 409 when it was saved before its causes' meaning changed (a cause
    on a coupled mechanism now acts on its drive), rather than a number it was not fitted to give."""
    try:
        return CalibratedRobot.from_state(model, c.robot_state)
    except StaleState as exc:
        raise ProblemError(409, str(exc), kind="stale-calibration") from None


def answer(c: Calibration) -> dict:
    out = {"id": c.id, "job_id": c.job_id, "robot_id": c.robot_id, "measurement_set_id": c.measurement_set_id}
    out.update(c.result)
    out.setdefault("model", ["geometric"])
    out.setdefault("parameters", [])
    out.setdefault("metrics", {})
    out["created_at"] = iso(c.created_at)
    return decorate(out, f"/calibrations/{c.id}")


def report(c: Calibration, inline: bool = False) -> str:
    """The HTML report of the stored answer (the same dict `GET /calibrations/{id}` returns); with `inline`, the
    plots its job drew and stored, embedded (one query for all of them)."""
    from ..report import html as report_html

    a = answer(c)
    if not inline:
        return report_html.render(a, None)
    stored = _stored_plots(c)
    return report_html.render(a, lambda name: stored[name] if name in stored else plot_png(c, name, a))


def _stored_plots(c: Calibration, name: str | None = None) -> dict[str, bytes]:
    s = object_session(c)
    if s is None:
        return {}
    q = select(CalibrationPlot.name, CalibrationPlot.png).where(CalibrationPlot.calibration_id == c.id)
    if name is not None:
        q = q.where(CalibrationPlot.name == name)
    return {n: bytes(png) for n, png in s.execute(q)}


def plot_png(c: Calibration, name: str, a: dict | None = None) -> bytes:
    """A plot of the calibration: the PNG its job drew when it finished and stored (`calibration_plots`).
    Only a calibration stored before plots were (migration 0002) has its plots drawn here, once per process."""
    from ..report.figures import plot_list

    a = a if a is not None else answer(c)
    if name not in {p["name"] for p in plot_list(a)}:
        have = ", ".join(p["name"] for p in a["plots"]) or "none (plots come with the auto model's diagnosis)"
        raise ProblemError(404, f"calibration {c.id!r} has no plot {name!r}; it has: {have}", kind="not-found")
    stored = _stored_plots(c, name)
    if name in stored:
        return stored[name]
    from ..report import plots as report_plots  # an old calibration: matplotlib here, once (cached)

    return report_plots.png(a, name, cache_key=c.id)


def calibrated_model(s: Session, c: Calibration) -> dict:
    """The calibrated model as contract JSON (identified geometry and tool point, model units), with the stored
    model's URDF extension and a `calibration` object (effects the rows cannot hold, base pose)."""
    from calib_core.urdf_write import calibrated_model_dict

    r = s.get(Robot, c.robot_id)
    doc = calibrated_model_dict(model_of(r), c.robot_state, r.model_json)
    doc["calibration"]["id"] = c.id
    return doc


def calibrated_urdf(s: Session, c: Calibration, base_joint: str | bool | None = None, form: str | None = None) -> str:
    """The calibrated model as URDF. A robot imported from a URDF (its stored model keeps the text as
    ``urdf.source``): that file patched, only the origins of the joints the calibration moved changed
    (calib_core.urdf_patch), with a root link carrying the identified base pose when `base_joint` names one.
    Any other model, or `form` ``"rows"``: a URDF written from the model rows (the identified geometry in the
    joint origins, each target a link at its identified point, effects and base pose in comments)."""
    if form not in (None, "original", "rows"):
        raise ProblemError(422, "form is 'original' (the imported URDF patched) or 'rows' (written from the model "
                           "rows)", kind="validation", errors=[{"field": "form", "value": form,
                                                                "message": "must be 'original' or 'rows'"}])
    patched = urdf_patch(s, c, base_joint) if form != "rows" else None
    if patched is not None:
        return patched.urdf
    if form == "original":
        raise ProblemError(404, f"calibration {c.id!r} is of a robot not imported from a URDF: there is no original "
                           "to patch (form=rows writes one from the model rows)", kind="not-found")
    if base_joint:
        raise ProblemError(422, "base_joint needs the original URDF (a robot imported from a URDF, form=original); "
                           "the URDF written from the model rows lists the base pose in a comment", kind="validation",
                           errors=[{"field": "base_joint", "value": base_joint, "message": "no URDF source"}])
    from calib_core.urdf_write import to_urdf

    return to_urdf(calibrated_model(s, c))


def urdf_side_file(s: Session, c: Calibration) -> dict:
    """The side document of the patched URDF: targets in their links, base poses, effects, mimic (m, rad)."""
    patched = urdf_patch(s, c, None)
    if patched is None:
        raise ProblemError(404, f"calibration {c.id!r} is of a robot not imported from a URDF: its URDF is written "
                           "from the model rows; GET /calibrations/{id}/model has the base pose and effects",
                           kind="not-found")
    return patched.side


def urdf_patch(s: Session, c: Calibration, base_joint: str | bool | None):
    """calib_core.urdf_patch.PatchedUrdf of the calibration, or None when the robot's model has no URDF source."""
    from calib_core.model import ModelError
    from calib_core.urdf_patch import SIDE_FILE, export_calibration, source_of

    r = s.get(Robot, c.robot_id)
    if source_of(r.model_json) is None:
        return None
    try:
        return export_calibration(r.model_json, c.robot_state, base_joint=base_joint, calibration_id=c.id,
                                  side_ref=f"/calibrations/{c.id}/urdf/{SIDE_FILE}")
    except ModelError as exc:
        n = len(exc.errors)
        raise ProblemError(422, f"the calibrated URDF cannot be written: {n} problem{'s' * (n != 1)}",
                           kind="validation", errors=exc.errors) from None


def _joint_range_problems(model, rows, field: str, errors: list) -> int:
    """Joint values far outside the limits (JOINT_MARGIN_FRACTION of the range beyond them; revolute joints
    without limits: MAX_REVOLUTE_DEG) as errors naming field[i][j] and the accepted range (at most MAX_ERRORS
    listed); returns how many more there are than listed."""
    act = model.actuated
    n = len(act)
    if not rows or any(len(r) != n for r in rows):
        return 0
    q = np.asarray(rows, float)
    js = model.joint_scale()[act]
    lo, hi = model.limits[act, 0] / js, model.limits[act, 1] / js
    prismatic, names = model.prismatic[act], model.actuated_names
    rev = MAX_REVOLUTE_DEG * ANGLE_TO_RAD["deg"] / ANGLE_TO_RAD[model.angle_unit]
    span = hi - lo
    margin = JOINT_MARGIN_FRACTION * np.where(np.isfinite(span), span, 0.0)
    a_lo = np.where(prismatic, lo - margin, np.maximum(lo - margin, -rev))
    a_hi = np.where(prismatic, hi + margin, np.minimum(hi + margin, rev))
    bad = (q < a_lo) | (q > a_hi)
    count = int(bad.sum())
    for i, j in np.argwhere(bad)[:MAX_ERRORS]:
        errors.append({"field": f"body.{field}[{i}][{j}]", "value": float(q[i, j]),
                       "message": f"{names[j]} = {q[i, j]:g} {model.joint_unit(act[j])} is far outside its "
                                  f"limits [{lo[j]:g}, {hi[j]:g}]; accepted: {a_lo[j]:g} to {a_hi[j]:g} "
                                  f"{model.joint_unit(act[j])} (the limits widened by "
                                  f"{JOINT_MARGIN_FRACTION:.0%} of the range)"})
    return max(0, count - MAX_ERRORS)


def _range_problems(name: str, v, lo: float, hi: float, unit: str, errors: list) -> int:
    """One value or a list of values outside [lo, hi], as errors naming body.name[i]; returns how many more
    there are than listed."""
    if v is None:
        return 0
    vals = np.atleast_1d(np.asarray(v, float))
    bad = np.flatnonzero((vals < lo) | (vals > hi))
    for i in bad[:MAX_ERRORS]:
        errors.append({"field": f"body.{name}" + (f"[{i}]" if isinstance(v, list) else ""),
                       "value": float(vals[i]), "message": f"{name} must be between {lo:g} and {hi:g} {unit}"})
    return max(0, len(bad) - MAX_ERRORS)


def _point_problems(targets, unit: str, errors: list) -> int:
    if not targets or any(len(t) != 3 for t in targets):
        return 0
    t = np.asarray(targets, float)
    bound = MAX_POINT_MM / LENGTH_TO_MM[unit]
    bad = np.abs(t) > bound
    for i, k in np.argwhere(bad)[:MAX_ERRORS]:
        errors.append({"field": f"body.targets[{i}][{k}]", "value": float(t[i, k]),
                       "message": f"implausible target: |{'xyz'[k]}| must be at most {bound:g} {unit} "
                                  f"({MAX_POINT_MM / 1000:g} m from the tracker origin)"})
    return max(0, int(bad.sum()) - MAX_ERRORS)


def _reject(detail: str, errors: list, hidden: int = 0):
    """A 422 listing the errors (the problem document shows the first MAX_ERRORS) with their total count."""
    if errors:
        raise ProblemError(422, detail, kind="validation", errors=errors[:MAX_ERRORS],
                           error_count=len(errors) + hidden)


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
            e = (d if d.tzinfo else d.replace(tzinfo=timezone.utc)).timestamp()
        except (ValueError, OverflowError):
            errors.append({"field": f"body.timestamp[{i}]", "value": t,
                           "message": "not an ISO 8601 timestamp (e.g. 2026-11-03T08:00:19+00:00)"})
            out.append(float("nan"))
            continue
        if not TIMESTAMP_RANGE_S[0] <= e < TIMESTAMP_RANGE_S[1]:
            errors.append({"field": f"body.timestamp[{i}]", "value": t, "message": f"timestamp outside "
                           f"{TIMESTAMP_RANGE_UTC[0][:10]} .. {TIMESTAMP_RANGE_UTC[1][:10]} (UTC)"})
        out.append(e)
    return out if isinstance(stamps, list) else (out[0] if out else None)


def _labels(model, state: dict, target, setup, n_rows: int, errors: list) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per row: the model target index (None: the first) and the calibration's setup index (None: the first)."""
    tix = six = None
    if target is not None:
        names = [target] * n_rows if isinstance(target, str) else list(target)
        if len(names) != n_rows:
            errors.append({"field": "body.target", "value": len(names), "message": "one target name per row, or one"})
        bad = [(i, t) for i, t in enumerate(names) if t not in model.target_names]
        errors += [{"field": f"body.target[{i}]" if not isinstance(target, str) else "body.target", "value": t,
                    "message": f"unknown target: one of {', '.join(model.target_names)}"} for i, t in bad[:MAX_ERRORS]]
        if not bad and len(names) == n_rows:
            tix = np.array([model.target_names.index(t) for t in names])
    if setup is not None:
        setups = list(state.get("setup_names", [""]))
        if setup not in setups:
            errors.append({"field": "body.setup", "value": setup, "message": "unknown setup: one of "
                           + (", ".join(setups) if setups != [""] else "none (the calibration has one setup)")})
        else:
            six = np.full(n_rows, setups.index(setup))
    return tix, six


def _tau(model, tau: dict | None, n_rows: int, errors: list) -> tuple[np.ndarray | None, int]:
    """Measured joint torques (n_rows, n) N*m or N from `tau_<joint>` keys (one value or one per row, None: the
    model's statics), NaN where not given; errors name body.tau.<key>[row] and the value. Also returns how
    many more errors there are than listed."""
    if not tau:
        return None, 0
    cols = {f"tau_{model.joint_names[j]}": int(j) for j in np.flatnonzero(model.moving)}
    out = np.full((n_rows, model.n_joints), np.nan)
    found = []
    for key, v in tau.items():
        if key not in cols:
            errors.append({"field": f"body.tau.{key}", "value": key, "message": "unknown joint torque: one of "
                           f"{', '.join(cols)} (tau_<joint> of a joint with a joint value)"})
            continue
        if isinstance(v, list) and len(v) != n_rows:
            errors.append({"field": f"body.tau.{key}", "value": len(v),
                           "message": f"one value per row ({n_rows}), or one value"})
            continue
        vals = v if isinstance(v, list) else [v] * n_rows
        found += [{"field": f"body.tau.{key}" + (f"[{i}]" if isinstance(v, list) else ""), "value": x,
                   "message": f"implausible joint load: at most {MAX_TAU:g} N*m (or N) in magnitude"}
                  for i, x in enumerate(vals) if x is not None and not abs(x) <= MAX_TAU]
        out[:, cols[key]] = [np.nan if x is None else float(x) for x in vals]
    errors += found[:MAX_ERRORS]
    return out, max(0, len(found) - MAX_ERRORS)


def _when(temperature, timestamp, sequence, n: int, errors: list) -> tuple:
    """A request's per-pose temperature (deg C), time (s since the epoch) and sequence number, each (n,) or None, and
    the count of range problems beyond those listed in `errors`."""
    temp = _per_pose("temperature", temperature, n, errors)
    stamps = _per_pose("timestamp", _epoch(timestamp, errors), n, errors)
    order = _per_pose("sequence", sequence, n, errors)
    more = _range_problems("sequence", sequence, -MAX_SEQUENCE, MAX_SEQUENCE, "(a place in the measurement order)",
                           errors)
    more += _range_problems("temperature", temperature, *TEMPERATURE_RANGE_C, "deg C", errors)
    return temp, stamps, order, more


def predict(model: RobotModel, c, joints: list[list[float]], payload, temperature=None, timestamp=None, target=None,
            setup=None, tau=None, sequence=None) -> tuple[list[list[float]], str, list[str]]:
    """Positions (model length unit) of the calibrated robot at actuated joints (model units), and notes on what
    they could not take into account (a load-driven cause without a load). tau: `tau_<joint>` -> N*m or N.
    `c`: the calibration, or anything with its `robot_state` (it crosses to a compute process: compute.py)."""
    n = len(model.actuated)
    errors = [{"field": f"body.joints[{i}]", "value": len(row), "message": f"expected {n} joint values "
               f"({', '.join(model.actuated_names)})"} for i, row in enumerate(joints) if len(row) != n]
    tix, six = _labels(model, c.robot_state, target, setup, len(joints), errors)
    if isinstance(payload, list) and len(payload) != len(joints):
        errors.append({"field": "body.payload", "value": len(payload), "message": "one payload per pose, or one number"})
    temp, stamps, order, more = _when(temperature, timestamp, sequence, len(joints), errors)
    more += _joint_range_problems(model, joints, "joints", errors)
    more += _range_problems("payload", payload, 0.0, MAX_PAYLOAD_KG, "kg", errors)
    torques, hidden = _tau(model, tau, len(joints), errors)
    _reject("the request does not fit the robot model", errors, more + hidden)
    q = model.expand_joints(np.asarray(joints, float) * model.joint_scale()[model.actuated])
    robot = restored(model, c)
    load = None if payload is None else np.broadcast_to(np.asarray(payload, float), (len(q),)).copy()
    columns = Measurements(joints=q, points=np.zeros((len(q), 3)), payload=load, temperature=temp,
                           timestamp=stamps, target=tix, setup=six, setup_names=robot.setup_names, tau=torques,
                           sequence=order)
    p_mm = robot.predict(q, columns)
    notes = robot.notes(columns)
    return (p_mm / LENGTH_TO_MM[model.length_unit]).tolist(), model.length_unit, notes


def compensate(model: RobotModel, c, body) -> dict:
    """Joint commands for targets (or for a joints-only program) with the calibrated model and its effects.
    `c`: the calibration, or anything with its `robot_state`."""
    n, names = len(model.actuated), model.actuated_names
    errors = []
    program = body.program_joints is not None
    if program == (body.targets is not None):
        errors.append({"field": "body", "value": None, "message": "give either targets with seed_joints, "
                                                                  "or program_joints"})
    rows = body.program_joints if program else body.seed_joints
    if not program and body.targets is not None and rows is None:
        errors.append({"field": "body.seed_joints", "value": None, "message": "seed_joints are required with targets"})
    errors += [{"field": f"body.{'program_joints' if program else 'seed_joints'}[{i}]", "value": len(r),
                "message": f"expected {n} joint values ({', '.join(names)})"}
               for i, r in enumerate(rows or []) if len(r) != n]
    if not program and body.targets is not None:
        errors += [{"field": f"body.targets[{i}]", "value": len(t), "message": "expected x, y, z"}
                   for i, t in enumerate(body.targets) if len(t) != 3]
        if rows is not None and len(rows) != len(body.targets):
            errors.append({"field": "body.seed_joints", "value": len(rows),
                           "message": f"one seed per target ({len(body.targets)})"})
    errors += [{"field": "body.locked_joints", "value": j, "message": (
                "follows its coupling (or is fixed) and cannot be locked" if j in model.joint_names else "unknown joint")
                + f"; the actuated joints are {', '.join(names)}"} for j in body.locked_joints if j not in names]
    tix, six = _labels(model, c.robot_state, body.target, body.setup, len(rows or []), errors)
    temp, stamps, order, more = _when(body.temperature, body.timestamp, body.sequence, len(rows or []), errors)
    more += _joint_range_problems(model, rows, "program_joints" if program else "seed_joints", errors)
    if not program:
        more += _point_problems(body.targets, model.length_unit, errors)
    more += _range_problems("payload", body.payload, 0.0, MAX_PAYLOAD_KG, "kg", errors)
    torques, hidden = _tau(model, body.tau, len(rows or []), errors)
    _reject("the request does not fit the robot model", errors, more + hidden)
    q = np.asarray(rows, float).reshape(-1, n) * model.joint_scale()[model.actuated]
    robot = restored(model, c)
    columns = Measurements(joints=model.expand_joints(q), points=np.zeros((len(q), 3)),
                           payload=None if body.payload is None else np.full(len(q), body.payload),
                           target=tix, setup=six, setup_names=robot.setup_names, tau=torques, temperature=temp,
                           timestamp=stamps, sequence=order)
    locked = tuple(body.locked_joints)
    if program:
        result = nominal_to_calibrated(robot, None, q, locked=locked, columns=columns)
    else:
        targets = np.asarray(body.targets, float).reshape(-1, 3) * LENGTH_TO_MM[model.length_unit]
        result = solve_compensation(robot, targets, q, locked=locked, columns=columns, max_iter=body.max_iter)
    out = result.to_dict(model)
    out["unit"] = {"length": model.length_unit, "angle": model.angle_unit}
    return out
