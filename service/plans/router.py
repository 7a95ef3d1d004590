from __future__ import annotations

from fastapi import APIRouter, Body, Depends

from ..db import Database
from ..deps import get_db, get_settings, require_writer
from ..problems import problem_responses
from . import service
from .schemas import PlanIn, PlanOut

router = APIRouter(tags=["plans"])


@router.post("/robots/{robot_id}/plan", response_model=PlanOut, dependencies=[Depends(require_writer)],
             responses=problem_responses(401, 404, 413, 422, 503),
             summary="Which poses to measure: for the geometry, or to tell look-alike causes apart (contract "
                     "section 5)")
async def create_plan(robot_id: str, body: PlanIn = Body(..., openapi_examples={
        "geometric": {"summary": "50 poses for the geometric calibration", "value": {"n_poses": 50,
                                                                                   "purpose": "geometric"}},
        "diagnosis": {"summary": "30 poses that split the look-alike causes of a measured set",
                      "value": {"n_poses": 30, "purpose": "diagnosis",
                                "measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21"}}}),
        db: Database = Depends(get_db), settings=Depends(get_settings)) -> dict:
    """Poses within the joint limits whose target faces the tracker (`max_incidence_deg`, default 60), chosen
    among 20,000 random candidates: `geometric` maximises the information about the identifiable geometric
    parameters (D-optimal, with load variety for the gravity causes when the model has masses); `diagnosis`
    maximises the expected held-out difference between each pair of look-alike causes that the newest `auto`
    calibration of `measurement_set_id` could not tell apart (T-optimal), so that measuring them settles it.
    `observability` compares the plan with random visible poses of the same number. Nothing is stored.
    A plan runs in one of `CALIB_PLAN_PROCESSES` processes, at most `CALIB_PLAN_ROOM` more waiting (default 4 per
    process): beyond that, and for a plan running longer than `CALIB_PLAN_TIMEOUT_S`, the answer is 503 with
    `Retry-After`."""
    return await service.make_plan_async(db, robot_id, body, settings.plan_processes, settings.plan_timeout_s,
                                         settings.plan_room)
