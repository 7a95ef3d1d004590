from __future__ import annotations

from sqlalchemy import JSON, Float, String
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, new_id, now


class Robot(Base):
    __tablename__ = "robots"
    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    model_json: Mapped[dict] = mapped_column(JSON)  # the model exactly as posted
    joint_names: Mapped[list] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float, default=now, index=True)
