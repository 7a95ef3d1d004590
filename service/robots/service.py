"""Robots: validate a model with calib_core and store it as given."""
from __future__ import annotations

import json
from functools import lru_cache

from sqlalchemy import select
from sqlalchemy.orm import Session

from calib_core.model import ModelError, RobotModel, parse_model

from ..problems import ProblemError, get_or_404
from .models import Robot


def validate_model(doc) -> RobotModel:
    if not isinstance(doc, dict):
        raise ProblemError(422, "the robot model must be a JSON object", kind="invalid-model",
                           errors=[{"field": "", "value": type(doc).__name__, "message": "must be a JSON object"}])
    try:
        return parse_model(doc)
    except ModelError as exc:
        n = len(exc.errors)
        raise ProblemError(422, f"the robot model has {n} error{'s' * (n != 1)}; nothing was stored",
                           kind="invalid-model", errors=exc.errors) from None
    except (TypeError, ValueError, KeyError, AttributeError, IndexError) as exc:  # malformed beyond what parse_model names
        raise ProblemError(422, f"the robot model is malformed: {exc}", kind="invalid-model",
                           errors=[{"field": "", "value": None, "message": str(exc)}]) from None


def create_robot(s: Session, doc: dict) -> Robot:
    model = validate_model(doc)
    r = Robot(name=model.name, model_json=doc, joint_names=list(model.joint_names))
    s.add(r)
    s.flush()
    return r


def get_robot(s: Session, robot_id: str) -> Robot:
    return get_or_404(s, Robot, robot_id, "robot")


def list_robots(s: Session, limit: int, offset: int) -> list[Robot]:
    return list(s.scalars(select(Robot).order_by(Robot.created_at, Robot.id).limit(limit).offset(offset)))


@lru_cache(maxsize=256)
def _parsed(text: str) -> RobotModel:
    return parse_model(json.loads(text))


def model_of(r: Robot) -> RobotModel:
    """The parsed calib_core model of a stored robot (cached: models are immutable once stored)."""
    return _parsed(json.dumps(r.model_json, sort_keys=True))
