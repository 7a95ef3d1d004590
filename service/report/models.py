"""The stored plots of a calibration: PNGs drawn once, by the worker, when the job finished (migration 0002)."""
from __future__ import annotations

from sqlalchemy import Float, ForeignKey, LargeBinary, String
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, now


class CalibrationPlot(Base):
    __tablename__ = "calibration_plots"
    calibration_id: Mapped[str] = mapped_column(ForeignKey("calibrations.id"), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), primary_key=True)  # `errors`, `distribution`, `finding-k`
    png: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[float] = mapped_column(Float, default=now)
