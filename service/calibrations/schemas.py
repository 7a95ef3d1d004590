from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from calib_core.compensate import MAX_ADVISED_ITER

from ..limits import MAX_PREDICT_ROWS

Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
"""A JSON number, finite; strict: the string "1" is not a number."""
MAX_POSES = MAX_PREDICT_ROWS  # enforced before parsing by limits.BatchLimitMiddleware (413); here for the OpenAPI
MAX_ROW = 256
"""At most this many values in one row of joints (a robot has a handful of joints)."""
MAX_COMPENSATE_ITER = MAX_ADVISED_ITER
"""Gauss-Newton iterations a compensation may ask per target (30 by default): bounds the request's work, and is the
most an unreached target's reason advises (calib_core.compensate)."""
Row = Annotated[list[Finite], Field(max_length=MAX_ROW)]
PerPose = Annotated[list[Finite], Field(max_length=MAX_POSES)]
Label = Annotated[str, Field(max_length=200)]
"""A target or setup name of the model / the measurement set."""
TauValues = Finite | Annotated[list[Finite | None], Field(max_length=MAX_POSES)]
TAU_DESCRIPTION = ("measured joint torques, keyed by the CSV's column names `tau_<joint>`: N*m (N for a prismatic "
                   "joint), one value or one per row (null: that row uses the model's statics). The load of "
                   "load-driven causes (joint compliance, backlash), as in the CSV: what the joint applies to hold "
                   "the arm, so the gravity load is -tau. Without it the model's statics are used; a model without "
                   "masses then has no load, and the answer's `notes` say which cause acts as zero")
NOTES_DESCRIPTION = ("what the answer could not take into account, in words (e.g. a load-driven cause without a "
                     "load: no masses in the model and no tau given)")


class PlotRef(BaseModel):
    name: str = Field(description="`errors`, `distribution` or `finding-k` (the k-th finding, 1-based)")
    title: str
    url: str = Field(description="GET it for the PNG")


class CalibrationOut(BaseModel):
    """The contract answer: parameters, metrics, diagnosis, plus what calib_core adds (identifiability,
    base pose, calibrated model, units) and what the service derives from it: `accuracy` (the error table of
    the report: mean, RMS, max per model, fit and held-out), `plots` (with `plot_url` on each finding that
    has one) and `report_url` (the HTML report)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"example": {
        "id": "e2b9c4d1-7a63-4c1f-9e0a-4b5d6c7e8f90", "job_id": "c1e7a0d2-6b55-4f0e-a1c3-3a9d7b2e8f10",
        "robot_id": "0b6f4f3e-4a0e-4a39-9d8e-2f6d5c3b1a90", "measurement_set_id": "5d1c2a8e-8f1b-4d55-bb1e-0b1a7f6c9e21",
        "model": ["geometric"],
        "parameters": [{"name": "J4.theta", "value": 0.0123, "nominal": 0.0, "std": 0.0004, "unit": "deg"}],
        "metrics": {"n_poses": 150, "rms_mm": 0.05, "max_mm": 0.14, "holdout_rms_mm": 0.06},
        "created_at": "2026-11-03T08:00:20+00:00",
        "accuracy": {"unit": "mm", "models": [{"model": "geometric", "final": True,
                                               "fit": {"mean_mm": 0.045, "rms_mm": 0.05, "max_mm": 0.14},
                                               "holdout": {"n": 150, "mean_mm": None, "rms_mm": 0.06, "max_mm": 0.16}}],
                     "note": "held-out: ..."},
        "plots": [], "report_url": "/calibrations/e2b9c4d1-7a63-4c1f-9e0a-4b5d6c7e8f90/report"}})
    id: str
    job_id: str
    robot_id: str
    measurement_set_id: str
    model: list[str]
    parameters: list[dict[str, Any]]
    metrics: dict[str, Any]
    created_at: str
    accuracy: dict[str, Any] = Field(description="error table (mm): per model, fit and held-out mean / RMS / max; "
                                     "held-out mean and max are ISO 9283 AP mean and max (one measurement per pose)")
    plots: list[PlotRef] = Field(description="the diagnosis plots (PNG); empty for a geometric-only calibration")
    report_url: str = Field(description="the HTML report of this calibration")


class PredictIn(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]}]})
    joints: list[Row] = Field(min_length=1, max_length=MAX_POSES,
                                       description="N poses x n joints, model units, in the order of the model's "
                                                   "actuated joints (coupled and fixed rows follow the model)")
    target: Label | list[Label] | None = Field(None, max_length=MAX_POSES,
                                               description="which of the model's targets each pose places (one name "
                                                           "or one per pose; default the first target)")
    setup: Label | None = Field(None, description="the setup (tracker station) whose measurement frame the "
                                                  "answer is in (default the first setup of the calibration)")
    payload: Finite | PerPose | None = Field(None, description="kg at the tool (0 to 10000), one value or one "
                                             "per pose; used only by calibrations that identified load effects")
    temperature: Finite | PerPose | None = Field(None,
                                                 description="deg C (-60 to 200), one value or one per pose; used "
                                                      "only by a calibration that identified thermal drift "
                                                      "(absent: the calibration's mean temperature)")
    timestamp: str | list[str] | None = Field(None, description="ISO 8601, one or one per pose; used only by a "
                                              "calibration that identified a drift over time", max_length=MAX_POSES)
    sequence: Finite | PerPose | None = Field(None, description="each pose's place in the measurement order of the "
                                              "calibration's data (its `sequence` column), one or one per pose; "
                                              "used only by a calibration with a step in that order (absent: "
                                              "after every step, the robot's current state)")
    tau: dict[Label, TauValues] | None = Field(None, max_length=MAX_ROW, description=TAU_DESCRIPTION,
                                               examples=[{"tau_J2": [412.5], "tau_J3": -88.0}])


class PredictOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {"positions": [[-2821.3401, 876.6147, -16.3583]],
                                                             "unit": "mm"}})
    positions: list[list[float]] = Field(description="measured point in the measurement frame, model length unit")
    unit: str
    notes: list[str] = Field(default_factory=list, description=NOTES_DESCRIPTION)


class CompensateIn(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"targets": [[-2821.34, 876.61, -16.36]], "seed_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]},
        {"program_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]], "locked_joints": ["J6"]}]})
    targets: list[Row] | None = Field(None, min_length=1, max_length=MAX_POSES,
                                               description="N x 3 points in the measurement frame, model length unit")
    seed_joints: list[Row] | None = Field(None, min_length=1, max_length=MAX_POSES,
                                                   description="N x n joints the program would use (the nominal "
                                                               "solution), model units: the answer stays nearest them")
    program_joints: list[Row] | None = Field(
        None, min_length=1, max_length=MAX_POSES, description="instead of targets: a program as joints only; the answer makes the "
        "real robot reach where the nominal model puts the tool (nominal model in the calibrated base frame)")
    locked_joints: list[str] = Field(default_factory=list, max_length=MAX_ROW, description="joint names held at the seed (for a "
                                     "redundant robot, e.g. the telescopic J6 of the spray robot)")
    payload: Finite | None = Field(None, description="kg at the tool during the program (0 to 10000)")
    target: Label | list[Label] | None = Field(None, max_length=MAX_POSES,
                                               description="which of the model's targets each row places (one name "
                                                           "or one per row; default the first target)")
    setup: Label | None = Field(None, description="the setup whose measurement frame the targets are in "
                                                  "(default the first setup of the calibration)")
    tau: dict[Label, TauValues] | None = Field(None, max_length=MAX_ROW, description=TAU_DESCRIPTION + "; one "
                                               "per target or program row", examples=[{"tau_J2": [412.5]}])
    temperature: Finite | PerPose | None = Field(None, description="deg C (-60 to 200) when the program runs, one "
                                                 "value or one per row; used only by a calibration that identified "
                                                 "thermal drift (absent: the calibration's mean temperature)")
    timestamp: str | list[str] | None = Field(None, description="ISO 8601 when the program runs, one or one per row; "
                                              "used only by a calibration that identified a drift or a step in "
                                              "time (absent: after every step)", max_length=MAX_POSES)
    sequence: Finite | PerPose | None = Field(None, description="each row's place in the measurement order of the "
                                              "calibration's data, one or one per row; used only by a calibration "
                                              "with a step in that order (absent: after every step, the robot's "
                                              "current state)")
    max_iter: int = Field(30, ge=1, le=MAX_COMPENSATE_ITER, description="Gauss-Newton iterations per target before "
                          "it is reported as not reached (a reason 'still converging' asks for more)")


class CompensateOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"example": {
        "joints": [[2000.1, 10.02, -19.97, 30.01, -40.0, 2000.0, 15.01]], "residual_mm": [0.0004],
        "reachable": [True], "reason": [None], "unit": {"length": "mm", "angle": "deg"}}})
    joints: list[list[float]] = Field(description="commands of the actuated joints, model units and their order "
                                                  "(coupled joints follow the model and are not listed)")
    residual_mm: list[float | None] = Field(description="the calibrated model's remaining distance to each target")
    reachable: list[bool]
    reason: list[str | None] = Field(description="why a target could not be reached (None where it was)")
    unit: dict[str, str]
    notes: list[str] = Field(default_factory=list, description=NOTES_DESCRIPTION)
