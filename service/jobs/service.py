"""Jobs: the row is written in the same transaction that answers 202; workers pick it up from the database
(woken at commit: queue/notify.py). Cancelling is a status change in one transaction; the worker running a
cancelled job stops its process."""
from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from ..measurements.models import MeasurementSet
from ..measurements.service import get_measurement_set
from ..problems import ProblemError, get_or_404, not_found
from ..queue import notify, store
from .models import CANCELLED, QUEUED, RUNNING, Job


def enqueue(s: Session, measurement_set_id: str, mode: str, max_attempts: int) -> Job:
    try:
        get_measurement_set(s, measurement_set_id)
        # DELETE /measurements/{id} (or its robot's) may be under way: on PostgreSQL this waits for it and then
        # finds no set (422) instead of failing on the foreign key; a delete that comes later sees this job (409)
        locked = select(MeasurementSet.id).where(MeasurementSet.id == measurement_set_id)
        if s.scalars(locked.with_for_update(key_share=True)).first() is None:
            raise not_found("measurement set", measurement_set_id)
    except ProblemError:
        raise ProblemError(422, f"measurement set {measurement_set_id!r} does not exist", kind="validation",
                           errors=[{"field": "body.measurement_set_id", "value": measurement_set_id,
                                    "message": "no such measurement set"}]) from None
    j = Job(measurement_set_id=measurement_set_id, mode=mode, max_attempts=max_attempts, message="queued")
    s.add(j)
    s.flush()
    notify.wake_after_commit(s, "queued")
    return j


def get_job(s: Session, job_id: str) -> Job:
    return get_or_404(s, Job, job_id, "job")


def cancel(s: Session, job_id: str) -> Job:
    """queued -> cancelled (never claimed after the commit); running -> cancelled, its process stopped by its
    worker within a moment; cancelled -> unchanged (idempotent); succeeded or failed -> 409."""
    j = s.scalars(select(Job).where(Job.id == job_id).with_for_update()).first()
    if j is None:
        raise not_found("job", job_id)
    if j.status == CANCELLED:
        return j
    if j.status not in (QUEUED, RUNNING):
        raise ProblemError(409, f"job {job_id!r} already {j.status}; only a queued or running job can be cancelled",
                           kind="conflict", job_status=j.status)
    store.cancel(s, j)
    s.flush()
    notify.wake_after_commit(s, "cancel")
    return j
