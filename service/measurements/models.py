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
    # how jobs re-parse them (migration 0003): the noise preset where the CSV has no `sigma` (None: the default,
    # said so in the answer) and the joint-limits mode (None: "reject"); `out_of_limits` is what "warn" accepted
    instrument: Mapped[str | None] = mapped_column(String(32), nullable=True)
    limits: Mapped[str | None] = mapped_column(String(16), nullable=True)
    out_of_limits: Mapped[list | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=now, index=True)
