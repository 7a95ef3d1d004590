"""Pose planning (contract section 5): the request and the answer."""
from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
MAX_PLAN_POSES = 1000
"""At most this many poses per plan (a calibration campaign is 50 to a few hundred poses)."""


class PlanIn(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"n_poses": 50, "purpose": "geometric"},
        {"n_poses": 30, "purpose": "diagnosis", "measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21"}]})
    n_poses: Annotated[int, Field(strict=True, ge=3, le=MAX_PLAN_POSES)] = Field(
        50, description=f"how many poses to plan (3 to {MAX_PLAN_POSES})")
    purpose: Literal["geometric", "diagnosis"] = Field(
        "geometric", description="`geometric`: D-optimal poses for the geometric parameters (and load variety for "
        "gravity causes); `diagnosis`: the next poses that best tell apart the look-alike causes the latest `auto` "
        "calibration of `measurement_set_id` lists as `indistinguishable_from`")
    measurement_set_id: str | None = Field(None, max_length=64, description="a measurement set of this robot: "
                                           "required for `diagnosis`; with `geometric`, the poses that add most to "
                                           "what the set already identifies")
    seed: Annotated[int, Field(strict=True, ge=0, le=2**32 - 1)] = Field(0, description="seed of the candidate poses")
    tracker: list[Finite] | None = Field(None, min_length=3, max_length=3, description="tracker position [x, y, z] "
                                         "in the robot base frame, model length unit (default: where the set's "
                                         "calibration found it, else 3 m from the workspace centre, level with it, "
                                         "across the workspace's thinnest horizontal extent)")
    max_incidence_deg: Finite | None = Field(None, gt=0, le=180, description="largest angle between a target's "
                                             "outward direction and its line of sight to the tracker (default 60)")


class PlanOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {
        "joints": [[2968.5, 15.3, -21.3, -31.1, 151.6, 2255.2, 104.6]],
        "joint_names": ["J1", "J2", "J3", "J4", "J5", "J6", "J7"], "unit": {"length": "mm", "angle": "deg"},
        "targets": None, "payload_kg": None,
        "observability": {
            "criterion": "D-optimal: log det of the information matrix of the identifiable geometric parameters "
                         "(weight 0.8) and of a compliance per loaded joint given the geometry (weight 0.2), each "
                         "per parameter", "loaded_joints": ["J3", "J4", "J6"],
            "geometry": {"n_parameters": 27,
                         "planned": {"log_det": 81.9, "condition_number": 29.8, "observability_index": 0.0438,
                                     "rank": 27},
                         "random": {"log_det": 61.4, "condition_number": 61.4, "observability_index": 0.0348,
                                    "rank": 27},
                         "information_gain_per_parameter": 2.14},
            "purpose": "geometric", "n_poses": 50, "candidates": 20000, "visible_candidates": 4534,
            "tracker_mm": [4055.7, 52.7, 2018.9], "max_incidence_deg": 60.0, "seed": 0}}})
    joints: list[list[float]] = Field(description="the poses, model units, in the order of `joint_names` (the "
                                      "model's actuated joints; coupled joints follow the model)")
    joint_names: list[str]
    unit: dict[str, str]
    targets: list[str] | None = Field(description="which target each pose measures (models with several targets)")
    payload_kg: list[float] | None = Field(description="the payload to carry at each pose (a diagnosis plan on a "
                                           "set measured with several payloads)")
    observability: dict[str, Any] = Field(description="the criterion used; `geometry`: what the planned poses "
                                          "(with the measured set, if any) identify against random visible poses of "
                                          "the same number (drawn uniformly within the limits): log det of the "
                                          "information matrix, condition number, observability index; `rivals` "
                                          "(diagnosis): each look-alike pair's expected separation (chi-square "
                                          "units), by the plan and by random poses, against what the diagnosis "
                                          "needs to tell them apart")
