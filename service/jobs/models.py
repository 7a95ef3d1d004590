from __future__ import annotations

from sqlalchemy import Float, ForeignKey, Index, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, new_id, now

QUEUED, RUNNING, SUCCEEDED, FAILED = "queued", "running", "succeeded", "failed"
CANCELLED = "cancelled"
FINISHED = (SUCCEEDED, FAILED, CANCELLED)


class Job(Base):
    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    measurement_set_id: Mapped[str] = mapped_column(ForeignKey("measurement_sets.id"), index=True)
    mode: Mapped[str] = mapped_column(String(20))  # "auto" | "geometric"
    status: Mapped[str] = mapped_column(String(20), default=QUEUED, index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str | None] = mapped_column(Text, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    calibration_id: Mapped[str | None] = mapped_column(String(36), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer, default=3)
    available_at: Mapped[float] = mapped_column(Float, default=now)  # not claimable before (retry back-off)
    lease_owner: Mapped[str | None] = mapped_column(String(200), nullable=True)
    lease_expires_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    heartbeat_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=now, index=True)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    # seconds the job has run, summed over its attempts (a graceful restart gives the attempt back, not the time):
    # CALIB_JOB_TIMEOUT_S bounds this sum
    run_seconds: Mapped[float] = mapped_column(Float, default=0.0, server_default="0")

    # the claim order (migration 0002): queued jobs in creation order, available_at read from the index
    __table_args__ = (Index("ix_jobs_claim", "status", "created_at", "id", "available_at"),)
