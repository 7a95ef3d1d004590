from __future__ import annotations

from sqlalchemy import JSON, Float, ForeignKey, String
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, new_id, now


class Calibration(Base):
    __tablename__ = "calibrations"
    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), unique=True)  # a result is written once per job
    robot_id: Mapped[str] = mapped_column(ForeignKey("robots.id"), index=True)
    measurement_set_id: Mapped[str] = mapped_column(ForeignKey("measurement_sets.id"), index=True)
    result: Mapped[dict] = mapped_column(JSON)  # the contract answer without id
    robot_state: Mapped[dict] = mapped_column(JSON)  # calib_core CalibratedRobot state, for predict
    worker: Mapped[str | None] = mapped_column(String(200), nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=now)
