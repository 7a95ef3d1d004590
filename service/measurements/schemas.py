from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ..robots.schemas import iso


class OutOfLimits(BaseModel):
    """One joint's values beyond its limits, accepted with `?limits=warn` (model units)."""
    joint: str
    unit: str = Field(description="the model's unit of this joint")
    limits: list[float | None] = Field(description="the model's [lower, upper] limit")
    rows: int = Field(description="how many rows have this joint outside its limits")
    min: float = Field(description="the smallest value of this joint in the CSV")
    max: float = Field(description="the largest value of this joint in the CSV")
    first_rows: list[int] = Field(description="line numbers of the first (at most 10) such rows")


class MeasurementSetOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {
        "id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21", "robot_id": "0b6f4f3e-4a0e-4a39-9d8e-2f6d5c3b1a90",
        "n_poses": 150, "columns": ["point", "J1", "J2", "J3", "J4", "J5", "J6", "J7", "x", "y", "z", "timestamp"],
        "filename": "cell3-2026-11-03.csv", "size_bytes": 18144,
        "sha256": "9f2b5c0e1d7a4b3c8e6f0a1b2c3d4e5f60718293a4b5c6d7e8f9011223344556",
        "created_at": "2026-11-03T08:00:19+00:00", "instrument": "laser_tracker", "limits": "warn",
        "out_of_limits": [{"joint": "J2", "unit": "deg", "limits": [-70.0, 70.0], "rows": 3, "min": -64.2,
                           "max": 73.9, "first_rows": [18, 44, 97]}]}})
    id: str
    robot_id: str
    n_poses: int
    columns: list[str] = Field(description="the CSV header as uploaded")
    filename: str | None
    size_bytes: int
    sha256: str = Field(description="SHA-256 of the stored bytes")
    created_at: str
    instrument: str | None = Field(None, description="the noise preset the jobs use where the CSV has no `sigma` "
                                   "column (`?instrument=`); null: none given, the laser tracker is assumed and the "
                                   "answer's `noise_model` says so")
    limits: Literal["reject", "warn"] = Field("reject", description="`?limits=`: how joint values outside the "
                                              "model's limits were treated")
    out_of_limits: list[OutOfLimits] = Field(default_factory=list, description="with `limits=warn`: per joint "
                                             "with values beyond its limits, how many rows and the column's range")

    @classmethod
    def of(cls, m) -> "MeasurementSetOut":
        return cls(id=m.id, robot_id=m.robot_id, n_poses=m.n_poses, columns=m.columns, filename=m.filename,
                   size_bytes=m.size_bytes, sha256=m.sha256, created_at=iso(m.created_at),
                   instrument=m.instrument, limits=m.limits or "reject", out_of_limits=m.out_of_limits or [])
