"""Jobs: the row is written in the same transaction that answers 202; workers pick it up from the database."""
from __future__ import annotations

from sqlalchemy.orm import Session

from ..measurements.service import get_measurement_set
from ..problems import ProblemError, get_or_404
from .models import Job


def enqueue(s: Session, measurement_set_id: str, mode: str, max_attempts: int) -> Job:
    try:
        get_measurement_set(s, measurement_set_id)
    except ProblemError:
        raise ProblemError(422, f"measurement set {measurement_set_id!r} does not exist", kind="validation",
                           errors=[{"field": "body.measurement_set_id", "value": measurement_set_id,
                                    "message": "no such measurement set"}]) from None
    j = Job(measurement_set_id=measurement_set_id, mode=mode, max_attempts=max_attempts, message="queued")
    s.add(j)
    s.flush()
    return j


def get_job(s: Session, job_id: str) -> Job:
    return get_or_404(s, Job, job_id, "job")
