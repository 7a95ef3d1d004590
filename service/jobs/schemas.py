from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ..robots.schemas import iso


class JobIn(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21", "model": "geometric"}]})
    measurement_set_id: str = Field(description="id from POST /robots/{id}/measurements")
    model: Literal["auto", "geometric"] = Field("auto", description="'geometric' identifies the geometric model only; "
                                                 "'auto' also runs the diagnosis and adds every effect it finds")


class JobOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {
        "id": "c1e7a0d2-6b55-4f0e-a1c3-3a9d7b2e8f10", "status": "succeeded", "progress": 1.0,
        "message": "done", "calibration_id": "e2b9c4d1-7a63-4c1f-9e0a-4b5d6c7e8f90", "error": None,
        "measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21", "model": "geometric", "attempts": 1,
        "created_at": "2026-11-03T08:00:19+00:00", "started_at": "2026-11-03T08:00:19.2+00:00",
        "finished_at": "2026-11-03T08:00:20+00:00", "updated_at": "2026-11-03T08:00:20+00:00", "run_seconds": 0.52}})
    id: str
    status: Literal["queued", "running", "succeeded", "failed", "cancelled"] = Field(
        description="queued -> running -> succeeded | failed; `cancelled` after POST /jobs/{id}/cancel (or DELETE)")
    progress: float = Field(description="0..1")
    message: str | None = Field(None, description="what the worker is doing now, with the job's run time; "
                                "written at least twice a second while the job runs")
    calibration_id: str | None
    error: str | None = Field(description="why the job failed (numerical failures and time-outs are not retried; "
                              "a job whose process dies is retried up to CALIB_MAX_ATTEMPTS)")
    measurement_set_id: str
    model: str
    attempts: int = Field(description="how many times a worker claimed it (>1 after a worker died)")
    created_at: str
    started_at: str | None
    finished_at: str | None
    updated_at: str | None = Field(None, description="when the worker last wrote progress (or the job finished)")
    run_seconds: float = Field(0.0, description="time the job has run, summed over its attempts; "
                               "CALIB_JOB_TIMEOUT_S bounds it")

    @classmethod
    def of(cls, j) -> "JobOut":
        return cls(id=j.id, status=j.status, progress=j.progress, message=j.message, calibration_id=j.calibration_id,
                   error=j.error, measurement_set_id=j.measurement_set_id, model=j.mode, attempts=j.attempts,
                   created_at=iso(j.created_at), started_at=iso(j.started_at), finished_at=iso(j.finished_at),
                   updated_at=iso(j.finished_at or j.heartbeat_at), run_seconds=float(j.run_seconds or 0.0))
