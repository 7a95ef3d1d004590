from __future__ import annotations

from fastapi import APIRouter, Body, Depends, Response
from sqlalchemy.orm import Session

from ..deps import WriteRoute, get_read_session, get_session, get_settings, require_writer
from ..problems import problem_responses
from . import service
from .schemas import JobIn, JobOut

router = APIRouter(tags=["jobs"], route_class=WriteRoute)


@router.post("/jobs", status_code=202, response_model=JobOut, dependencies=[Depends(require_writer)],
             responses=problem_responses(401, 413, 422), summary="Queue a calibration of a measurement set")
def create_job(response: Response, body: JobIn = Body(..., openapi_examples={
        "geometric": {"summary": "geometric model only",
                      "value": {"measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21", "model": "geometric"}},
        "auto": {"summary": "geometric model plus diagnosis",
                 "value": {"measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21", "model": "auto"}}}),
        s: Session = Depends(get_session, scope="function"), settings=Depends(get_settings)) -> JobOut:
    """The job is durable once this answers 202 (same transaction); poll `Location`."""
    j = service.enqueue(s, body.measurement_set_id, body.model, settings.max_attempts)
    response.headers["Location"] = f"/jobs/{j.id}"
    return JobOut.of(j)


@router.get("/jobs/{job_id}", response_model=JobOut, responses=problem_responses(404),
            summary="A job's status and progress")
def get_job(job_id: str, s: Session = Depends(get_read_session, scope="function")) -> JobOut:
    return JobOut.of(service.get_job(s, job_id))


_CANCEL_DOC = """A queued job is cancelled at once and never runs; a running job is cancelled at once (no result will
be stored) and its worker stops its process within a moment (`message` then says so). Cancelling a cancelled
job again answers it unchanged; a job that already succeeded or failed is a 409."""


@router.post("/jobs/{job_id}/cancel", response_model=JobOut, dependencies=[Depends(require_writer)],
             responses=problem_responses(401, 404, 409), summary="Cancel a queued or running job",
             description=_CANCEL_DOC)
@router.delete("/jobs/{job_id}", response_model=JobOut, dependencies=[Depends(require_writer)],
               responses=problem_responses(401, 404, 409), name="delete_job",
               summary="Cancel a queued or running job (same as POST /jobs/{id}/cancel; the record stays)",
               description=_CANCEL_DOC)
def cancel_job(job_id: str, s: Session = Depends(get_session, scope="function")) -> JobOut:
    return JobOut.of(service.cancel(s, job_id))
