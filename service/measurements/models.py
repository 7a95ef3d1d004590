from __future__ import annotations

from sqlalchemy import JSON, Float, ForeignKey, Integer, LargeBinary, String
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, new_id, now


class MeasurementSet(Base):
    __tablename__ = "measurement_sets"
    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    robot_id: Mapped[str] = mapped_column(ForeignKey("robots.id"), index=True)
    filename: Mapped[str | None] = mapped_column(String(500), nullable=True)
    n_poses: Mapped[int] = mapped_column(Integer)
    columns: Mapped[list] = mapped_column(JSON)
    size_bytes: Mapped[int] = mapped_column(Integer)
    sha256: Mapped[str] = mapped_column(String(64))
    raw: Mapped[bytes] = mapped_column(LargeBinary)  # the uploaded bytes; jobs re-parse them
    created_at: Mapped[float] = mapped_column(Float, default=now, index=True)
