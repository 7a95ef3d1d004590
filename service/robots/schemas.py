from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from calib_core.model import parse_model
from calib_core.robots import spray7

from ..problems import encodable, encodable_doc

SPRAY7_EXAMPLE = spray7()


def iso(t: float | None) -> str | None:
    return None if t is None else datetime.fromtimestamp(t, timezone.utc).isoformat()


class RobotOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {
        "id": "0b6f4f3e-4a0e-4a39-9d8e-2f6d5c3b1a90", "name": "spray7", "joint_names": [f"J{i}" for i in range(1, 8)],
        "n_joints": 7, "units": {"length": "mm", "angle": "deg"}, "created_at": "2026-11-03T08:00:19+00:00",
        "model": SPRAY7_EXAMPLE, "actuated_joints": [f"J{i}" for i in range(1, 8)], "targets": ["tool"]}})
    id: str
    name: str
    joint_names: list[str]
    n_joints: int
    units: dict[str, Any] = Field(description="the model's length and angle units")
    created_at: str
    model: dict[str, Any] = Field(description="the robot model JSON exactly as posted (contract section 1)")
    actuated_joints: list[str] = Field(description="the joints a measurement CSV and a predict / compensate "
                                                   "request carry, in this order (coupled and fixed rows follow "
                                                   "the model)")
    targets: list[str] = Field(description="the measured targets (a CSV `target` column names one per row)")

    @classmethod
    def of(cls, r) -> "RobotOut":
        doc = encodable_doc(r.model_json)  # a model stored with a lone surrogate before they were refused: answered
        units = doc.get("units") if isinstance(doc.get("units"), dict) else {}
        model = parse_model(doc)
        return cls(id=r.id, name=encodable(r.name), joint_names=encodable_doc(r.joint_names),
                   n_joints=len(r.joint_names), units=units, created_at=iso(r.created_at), model=doc,
                   actuated_joints=list(model.actuated_names), targets=list(model.target_names))
