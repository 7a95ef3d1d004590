"""Queue operations on the jobs table. Every function is one short transaction.

Claim is atomic: on PostgreSQL `SELECT ... FOR UPDATE SKIP LOCKED` lets N workers claim N different jobs
without waiting on each other; on SQLite the transaction starts with BEGIN IMMEDIATE (see db.py), which
serialises writers, so the select-then-update cannot interleave.  A job belongs to the worker named in
`lease_owner` until `lease_expires_at`; every write a worker makes is conditional on still owning the lease,
so a worker that lost its lease (it stalled and another took over) can never write a second result.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from sqlalchemy import and_, select, update

from ..calibrations.models import Calibration
from ..db import Database, new_id, now
from ..jobs.models import CANCELLED, FAILED, QUEUED, RUNNING, SUCCEEDED, Job
from ..measurements.models import MeasurementSet
from ..report.models import CalibrationPlot
from ..robots.models import Robot


@dataclass(frozen=True)
class Claimed:
    job_id: str
    attempt: int
    mode: str
    model_json: dict
    raw: bytes
    robot_id: str
    measurement_set_id: str
    run_seconds: float = 0.0  # run time of the earlier attempts (the time limit counts all of them)
    instrument: str | None = None  # how the job re-parses the CSV: as it was uploaded (measurement_sets)
    limits: str = "reject"


def claim(db: Database, worker_id: str, lease_seconds: float) -> Claimed | None:
    with db.session() as s:
        t = now()
        q = (select(Job).where(Job.status == QUEUED, Job.available_at <= t)  # ix_jobs_claim
             .order_by(Job.created_at, Job.id).limit(1).with_for_update(skip_locked=True))
        j = s.scalars(q).first()
        if j is None:
            return None
        j.status, j.lease_owner, j.lease_expires_at, j.heartbeat_at = RUNNING, worker_id, t + lease_seconds, t
        j.attempts += 1
        j.started_at = j.started_at or t
        j.progress, j.message = 0.0, f"claimed by {worker_id} (attempt {j.attempts})"
        ms = s.get(MeasurementSet, j.measurement_set_id)
        robot = s.get(Robot, ms.robot_id)
        return Claimed(j.id, j.attempts, j.mode, robot.model_json, ms.raw, robot.id, ms.id, float(j.run_seconds or 0.0),
                       ms.instrument, ms.limits or "reject")


def _owned(job_id: str, worker_id: str):
    return and_(Job.id == job_id, Job.lease_owner == worker_id, Job.status == RUNNING)


def heartbeat(db: Database, job_id: str, worker_id: str, lease_seconds: float,
              progress: float | None = None, message: str | None = None, run_seconds: float | None = None) -> bool:
    """Renew the lease (and record progress and run time); False if this worker no longer owns the job (it was
    cancelled, or its lease expired and another worker took it)."""
    t = now()
    values = {"lease_expires_at": t + lease_seconds, "heartbeat_at": t}
    if run_seconds is not None and math.isfinite(run_seconds):
        values["run_seconds"] = run_seconds
    if progress is not None and math.isfinite(progress):
        values["progress"] = max(0.0, min(1.0, progress))
    if message is not None:
        values["message"] = message[:2000]
    with db.session() as s:
        return s.execute(update(Job).where(_owned(job_id, worker_id)).values(**values)).rowcount == 1


def complete(db: Database, c: Claimed, worker_id: str, result: dict, robot_state: dict,
             plots: dict[str, bytes] | None = None, run_seconds: float | None = None) -> str | None:
    """Write the result once: the job flips to succeeded and the calibration row (and its plots, drawn by the
    job's process) are inserted in one transaction, only if this worker still owns the lease (a cancelled job
    is not). Returns the calibration id, or None."""
    cid = new_id()
    with db.session() as s:
        t = now()
        values = dict(status=SUCCEEDED, progress=1.0, message="done", calibration_id=cid, finished_at=t,
                      heartbeat_at=t, lease_expires_at=None)
        if run_seconds is not None:
            values["run_seconds"] = run_seconds
        n = s.execute(update(Job).where(_owned(c.job_id, worker_id)).values(**values)).rowcount
        if n != 1:
            return None
        s.add(Calibration(id=cid, job_id=c.job_id, robot_id=c.robot_id, measurement_set_id=c.measurement_set_id,
                          result=result, robot_state=robot_state, worker=worker_id, created_at=t))
        s.flush()  # the calibration row before its plots (foreign key)
        for name, png in (plots or {}).items():
            s.add(CalibrationPlot(calibration_id=cid, name=name, png=png, created_at=t))
    return cid


def fail(db: Database, job_id: str, worker_id: str, error: str, *, retry: bool, backoff_seconds: float = 1.0,
         run_seconds: float | None = None) -> bool:
    """Numerical failures and time-outs (retry=False) fail at once; infrastructure failures go back to the queue
    until max_attempts is spent."""
    with db.session() as s:
        j = s.scalars(select(Job).where(_owned(job_id, worker_id)).with_for_update()).first()
        if j is None:
            return False
        t = now()
        j.heartbeat_at = t
        if run_seconds is not None and math.isfinite(run_seconds):
            j.run_seconds = run_seconds
        if retry and j.attempts < j.max_attempts:
            j.status, j.lease_owner, j.lease_expires_at = QUEUED, None, None
            j.available_at = t + backoff_seconds * 2 ** (j.attempts - 1)
            j.message = f"re-queued after attempt {j.attempts}: {error}"[:2000]
        else:
            j.status, j.error, j.finished_at, j.lease_expires_at = FAILED, error[:4000], t, None
            j.message = "failed"
        return True


def release(db: Database, job_id: str, worker_id: str, run_seconds: float | None = None) -> bool:
    """Give a job back without spending an attempt (the worker is shutting down cleanly). The time it ran is
    kept (`run_seconds`): a job that never ends still meets CALIB_JOB_TIMEOUT_S across any number of restarts."""
    values = dict(status=QUEUED, lease_owner=None, lease_expires_at=None, attempts=Job.attempts - 1,
                  available_at=now(), message="released by a stopping worker")
    if run_seconds is not None and math.isfinite(run_seconds):
        values["run_seconds"] = run_seconds
    with db.session() as s:
        return s.execute(update(Job).where(_owned(job_id, worker_id)).values(**values)).rowcount == 1


def still_owned(db: Database, worker_id: str, job_ids: list[str]) -> set[str]:
    """Which of these jobs this worker still runs (a read: the others were cancelled or taken over)."""
    if not job_ids:
        return set()
    with db.read_session() as s:
        return set(s.scalars(select(Job.id).where(Job.id.in_(job_ids), Job.lease_owner == worker_id,
                                                  Job.status == RUNNING)))


def ack_cancel(db: Database, job_id: str, worker_id: str) -> bool:
    """The worker stopped the process of a job cancelled while it ran: say so on the job."""
    with db.session() as s:
        return s.execute(update(Job).where(Job.id == job_id, Job.lease_owner == worker_id, Job.status == CANCELLED)
                         .values(lease_owner=None, message="cancelled; its process was stopped")).rowcount == 1


def cancel(s, job: Job) -> Job:
    """Cancel a queued or running job in the caller's transaction (the job row locked by the caller). A queued
    job is never claimed after this commits; the worker running a running one sees it no longer owns it (its
    next progress write, or at once when woken) and kills the job's process. Finished jobs are the caller's
    409."""
    t = now()
    running = job.status == RUNNING
    job.status, job.finished_at, job.lease_expires_at = CANCELLED, t, None
    job.message = "cancelled; stopping its process" if running else "cancelled before it started"
    return job


def reap(db: Database) -> tuple[int, int]:
    """Re-queue running jobs whose lease expired (their worker died or hung); fail those out of attempts.
    Returns (re-queued, failed)."""
    t = now()
    expired = and_(Job.status == RUNNING, Job.lease_expires_at < t)
    with db.session() as s:
        requeued = s.execute(update(Job).where(expired, Job.attempts < Job.max_attempts).values(
            status=QUEUED, lease_owner=None, lease_expires_at=None, available_at=t,
            message="re-queued: the worker's lease expired")).rowcount
        failed = s.execute(update(Job).where(expired, Job.attempts >= Job.max_attempts).values(
            status=FAILED, lease_expires_at=None, finished_at=t, message="failed",
            error="the worker running this job was lost on every attempt (infrastructure failure)")).rowcount
    return requeued, failed
