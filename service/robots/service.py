"""Robots: validate a model with calib_core and store it as given."""
from __future__ import annotations

import json
import logging
import threading
from collections import OrderedDict

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from calib_core.model import ModelError, RobotModel, parse_model

from ..problems import ProblemError, get_or_404, not_found
from .models import Robot

log = logging.getLogger("service")


MAX_MODEL_JOINTS = 100
"""At most this many joints (revolute and prismatic rows, coupled ones included) in a stored model (issue 33). Real
robots have far fewer: a 6- or 7-axis arm, Agile Justin's torso and two arms 17 (+ fixed rows), a two-arm humanoid
with two hands 60-80. Larger models are refused at `POST /robots` (JSON or URDF): a 1000-joint model used to be
stored, and a 3-pose plan on it took 51 s and 5 GB. A serial chain's 50-pose plan (measured on one busy core):
50 joints 3.1 s / 370 MB, 100 joints 13.5 s / 640 MB, 200 joints 53 s / 1.2 GB."""
MAX_MODEL_ROWS = 150
"""At most this many rows in all (joints and `fixed` rows: mount plates, URDF fixed joints on the chains), whose
constants are parameters too."""
MAX_MODEL_TARGETS = 64
"""At most this many measured targets (SMRs, markers) in `targets`."""


def check_size(doc: dict) -> None:
    """A 422 naming each count of the model over its maximum, before the model is parsed at all (a model of a
    million rows is refused in microseconds)."""
    rows, targets = doc.get("joints"), doc.get("targets")
    errors = []
    if isinstance(rows, list):
        joints = sum(1 for r in rows if not (isinstance(r, dict) and r.get("type") == "fixed"))
        if len(rows) > MAX_MODEL_ROWS:
            errors.append({"field": "joints", "value": len(rows), "message": f"the model has {len(rows)} rows; "
                           f"at most {MAX_MODEL_ROWS} are taken (joints and fixed rows)"})
        if joints > MAX_MODEL_JOINTS:
            errors.append({"field": "joints", "value": joints, "message": f"the model has {joints} joints "
                           f"(revolute and prismatic, coupled ones included); at most {MAX_MODEL_JOINTS} are taken"})
    if isinstance(targets, list) and len(targets) > MAX_MODEL_TARGETS:
        errors.append({"field": "targets", "value": len(targets), "message": f"the model has {len(targets)} "
                       f"targets; at most {MAX_MODEL_TARGETS} are taken"})
    if errors:
        raise ProblemError(422, f"the robot model is larger than this service takes ({MAX_MODEL_JOINTS} joints, "
                           f"{MAX_MODEL_ROWS} rows, {MAX_MODEL_TARGETS} targets; a two-arm humanoid with hands has "
                           "60-80 joints): model only the chains that are measured (a URDF upload's `base` and "
                           "`targets` choose them); nothing was stored", kind="invalid-model", errors=errors,
                           max_joints=MAX_MODEL_JOINTS, max_rows=MAX_MODEL_ROWS, max_targets=MAX_MODEL_TARGETS)


def validate_model(doc) -> RobotModel:
    if not isinstance(doc, dict):
        raise ProblemError(422, "the robot model must be a JSON object", kind="invalid-model",
                           errors=[{"field": "", "value": type(doc).__name__, "message": "must be a JSON object"}])
    check_size(doc)
    try:
        return parse_model(doc)
    except ModelError as exc:
        n = len(exc.errors)
        raise ProblemError(422, f"the robot model has {n} error{'s' * (n != 1)}; nothing was stored",
                           kind="invalid-model", errors=exc.errors) from None
    except (TypeError, ValueError, KeyError, AttributeError, IndexError, ArithmeticError, RecursionError):
        # malformed beyond what parse_model names: say so in plain words, never Python's own message
        log.info("unreadable robot model", exc_info=True)
        raise ProblemError(422, "the robot model cannot be read: a value has the wrong kind (a list where a "
                           "number or a text is expected, or the like); compare it with the contract, section 1",
                           kind="invalid-model", errors=[{"field": "", "value": None, "message":
                                                          "a value has the wrong kind; see the contract, section 1"}]
                           ) from None


def create_robot(s: Session, doc: dict) -> Robot:
    model = validate_model(doc)
    r = Robot(name=model.name, model_json=doc, joint_names=list(model.joint_names))
    s.add(r)
    s.flush()
    return r


def create_robot_from_urdf(s: Session, body: bytes, base: str | None, targets: str | None,
                           length_unit: str = "m", angle_unit: str = "rad", smr: str | None = None) -> Robot:
    """A URDF (contract section 5) converted to the contract model JSON (calib_core.urdf) and stored like a JSON
    upload; a bad URDF (or `smr`, the targets' nominal SMR offsets `x,y,z;x,y,z` in m) is a 422 naming the element
    and attribute (or the parameter) and nothing is stored. The model keeps its `urdf` extension: `notes` (what
    was ignored or read leniently) and `source` (the URDF text), so the 201 answer shows the notes."""
    from calib_core.urdf import UrdfError, parse_urdf

    try:
        doc = parse_urdf(body, base or None, targets or None, length_unit=length_unit, angle_unit=angle_unit,
                         smr_m=smr or None)
    except UrdfError as exc:
        n = len(exc.errors)
        raise ProblemError(422, f"the URDF has {n} error{'s' * (n != 1)}; nothing was stored", kind="invalid-urdf",
                           errors=exc.errors) from None
    return create_robot(s, doc)


def get_robot(s: Session, robot_id: str) -> Robot:
    return get_or_404(s, Robot, robot_id, "robot")


def delete_robot(db, robot_id: str) -> dict[str, int]:
    """DELETE /robots/{id}: the robot with its measurement sets and everything made from them (finished jobs,
    calibrations, plots), in one transaction; 409 (nothing deleted) while a queued or running job uses one of its
    sets. What was deleted, counted."""
    from ..measurements.models import MeasurementSet
    from ..measurements.service import delete_sets, log_deleted

    with db.session() as s:
        get_robot(s, robot_id)

        def lock() -> None:  # no set can be added to it from here on (an upload takes a key-share lock)
            if s.scalars(select(Robot.id).where(Robot.id == robot_id).with_for_update()).first() is None:
                raise not_found("robot", robot_id)

        n = delete_sets(s, MeasurementSet.robot_id == robot_id, f"robot {robot_id!r}", lock=lock)
        n["robots"] = s.execute(delete(Robot).where(Robot.id == robot_id),
                                execution_options={"synchronize_session": False}).rowcount
    _cache.drop(str(robot_id))
    log_deleted(f"robot {robot_id!r}", n)
    return n


PAGE_MAX_BYTES = 8 * 1024 * 1024
"""A page of `GET /robots` stops early (with at least one model) once its models' JSON passes this size."""


def list_robots(s: Session, limit: int, offset: int, max_bytes: int = PAGE_MAX_BYTES) -> list[Robot]:
    """At most `limit` robots from `offset`, oldest first, and fewer once their model JSON passes `max_bytes`."""
    out, size = [], 0
    result = s.scalars(select(Robot).order_by(Robot.created_at, Robot.id).limit(limit).offset(offset)
                       .execution_options(yield_per=16))
    try:
        for r in result:
            size += len(json.dumps(r.model_json))
            if out and size > max_bytes:
                break
            out.append(r)
    finally:
        result.close()
    return out


def count_robots(s: Session) -> int:
    return int(s.scalar(select(func.count()).select_from(Robot)))


class ModelCache:
    """Parsed models by robot id (stored models never change), least recently used dropped first, bounded by
    the size of the models' JSON text rather than by their number: a few huge models cannot fill the memory."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.bytes = 0
        self._items: OrderedDict[str, tuple[RobotModel, int]] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: str) -> RobotModel | None:
        with self._lock:
            hit = self._items.get(key)
            if hit is None:
                return None
            self._items.move_to_end(key)
            return hit[0]

    def put(self, key: str, model: RobotModel, nbytes: int) -> None:
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.bytes -= old[1]
            if nbytes > self.max_bytes:
                return  # larger than the whole cache: parsed on every use
            self._items[key] = (model, nbytes)
            self.bytes += nbytes
            while self.bytes > self.max_bytes:
                _, (_, n) = self._items.popitem(last=False)
                self.bytes -= n

    def drop(self, key: str) -> None:
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.bytes -= old[1]

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.bytes = 0


MODEL_CACHE_BYTES = 32 * 1024 * 1024
_cache = ModelCache(MODEL_CACHE_BYTES)


def model_of(r: Robot) -> RobotModel:
    """The parsed calib_core model of a stored robot (cached by id: models are immutable once stored)."""
    key = str(r.id)
    model = _cache.get(key)
    if model is None:
        text = json.dumps(r.model_json, sort_keys=True)
        model = parse_model(json.loads(text))
        _cache.put(key, model, len(text))
    return model
