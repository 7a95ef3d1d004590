"""One call from measured data to the calibration answer: the entry point of a service job."""
from __future__ import annotations

from typing import Callable

import numpy as np

from . import kinematics as K
from .diagnosis import diagnose
from .orientation import LEVER_MM, MARK, with_orientation, without_virtual
from .select import select_geometry
from .io import Measurements
from .model import RobotModel

MODES = ("geometric", "auto")


def calibrate(model: RobotModel, meas: Measurements, mode: str = "geometric",
              progress: Callable[[float, str], None] | None = None, deadline: float | None = None,
              workers: int = 1) -> dict:
    """Identify the model from the measurements; returns the answer dict plus `robot_state` for persistence.

    mode 'geometric' identifies the geometric model, its size (which parameters, how much prior) chosen on
    held-out poses so it is never worse than registering base and tool alone (`model_selection` says which
    and whether calibration helps); 'auto' also diagnoses the residual and extends the model with every
    cause it finds (the answer then carries the contract's `diagnosis` block). `deadline` (time.monotonic()):
    past it the diagnosis fits no further model and answers with what it has confirmed (see diagnose). `workers`:
    processes for the diagnosis's independent parts (the same answer as one, to rounding).
    """
    if mode not in MODES:
        raise ValueError(f"unknown model {mode!r}; use one of {MODES}")
    report = progress or (lambda fraction, message: None)
    given, rows = model, meas
    model, meas = with_orientation(model, meas)
    if mode == "auto":
        d = diagnose(model, meas, progress=report, deadline=deadline, workers=workers)
        cal = d.calibration
        out = cal.to_dict()
        out["diagnosis"] = d.to_dict()
        _mark_plannable(given, rows, cal.robot.effects, out["diagnosis"].get("findings") or [])
    else:
        report(0.05, "choosing the geometric model on held-out poses")
        selection = select_geometry(model, meas, workers=workers)
        cal = selection.calibration
        out = cal.to_dict()
        out["model_selection"] = selection.to_dict()
    report(1.0, "done")
    state = cal.robot.to_state()
    if model is not given:  # 6-D rows: the virtual targets served the fit; the answer is about the robot's model
        for key in ("x", "x_basis"):
            if key in state:
                state[key] = without_virtual(model, np.array(state[key])).tolist()
        lay = K.layout(given, np.array(state["x"]))
        x = np.array(state["x"])
        out["calibrated_model"] = given.to_dict(x[lay.geometry].reshape(given.n_joints, -1),
                                                x[lay.tools].reshape(-1, 3))
        n6 = sum(MARK in str(i) for i in meas.point_ids) // 3
        out["orientation"] = {"rows": n6, "lever_mm": LEVER_MM,
                              "note": f"{n6} rows carried an orientation; each entered the fit as three virtual "
                                      f"points {LEVER_MM:g} mm from the target along its measured axes (poses and "
                                      "metrics count them), weighted by the instrument's orientation noise"}
    out["robot_state"] = state
    return out


def _mark_plannable(model: RobotModel, meas: Measurements, effects, findings: list[dict]) -> None:
    """Each look-alike of a finding gets `plannable`: whether `POST /robots/{id}/plan {"purpose": "diagnosis"}`
    can plan poses that split it from the finding (calib_core.plan.plannable, on the model and rows the plan
    service reads: the uploaded ones, not the 6-D rows' virtual points)."""
    from .plan import plannable  # plan imports the diagnosis; imported here, only when a finding lists look-alikes

    if not any(f.get("indistinguishable_from") for f in findings):
        return
    for f, flags in zip(findings, plannable(model, meas, effects, findings)):
        for a, ok in zip(f.get("indistinguishable_from") or [], flags):
            a["plannable"] = bool(ok)
