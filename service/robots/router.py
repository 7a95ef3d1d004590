from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends, Query, Response
from sqlalchemy.orm import Session

from ..deps import get_read_session, get_session, require_writer
from ..problems import problem_responses
from . import service
from .schemas import SPRAY7_EXAMPLE, RobotOut

router = APIRouter(tags=["robots"])


@router.post("/robots", status_code=201, response_model=RobotOut, dependencies=[Depends(require_writer)],
             responses=problem_responses(401, 413, 422), summary="Store a robot model (contract section 1)")
def create_robot(response: Response, doc: dict[str, Any] = Body(..., openapi_examples={
        "spray7": {"summary": "7-DoF spray robot, MD-H, mm/deg", "value": SPRAY7_EXAMPLE}}),
        s: Session = Depends(get_session, scope="function")) -> RobotOut:
    """Validates the model (joint names, types, limits, units) and stores it exactly as posted.
    Every problem is listed in the 422 problem document as `{field, value, message}`."""
    r = service.create_robot(s, doc)
    response.headers["Location"] = f"/robots/{r.id}"
    return RobotOut.of(r)


@router.get("/robots", response_model=list[RobotOut], summary="The stored robot models, oldest first")
def list_robots(limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=2**31),
                s: Session = Depends(get_read_session, scope="function")) -> list[RobotOut]:
    return [RobotOut.of(r) for r in service.list_robots(s, limit, offset)]


@router.get("/robots/{robot_id}", response_model=RobotOut, responses=problem_responses(404),
            summary="One stored robot model")
def get_robot(robot_id: str, s: Session = Depends(get_read_session, scope="function")) -> RobotOut:
    return RobotOut.of(service.get_robot(s, robot_id))
