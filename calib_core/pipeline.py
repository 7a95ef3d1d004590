"""One call from measured data to the calibration answer: the entry point of a service job."""
from __future__ import annotations

from typing import Callable

from .diagnose import diagnose
from .select import select_geometry
from .io import Measurements
from .model import RobotModel

MODES = ("geometric", "auto")


def calibrate(model: RobotModel, meas: Measurements, mode: str = "geometric",
              progress: Callable[[float, str], None] | None = None) -> dict:
    """Identify the model from the measurements; returns the answer dict plus `robot_state` for persistence.

    mode 'geometric' identifies the geometric model, its size (which parameters, how much prior) chosen on
    held-out poses so it is never worse than registering base and tool alone (`model_selection` says which
    and whether calibration helps); 'auto' also diagnoses the residual and extends the model with every
    cause it finds (the answer then carries the contract's `diagnosis` block).
    """
    if mode not in MODES:
        raise ValueError(f"unknown model {mode!r}; use one of {MODES}")
    report = progress or (lambda fraction, message: None)
    if mode == "auto":
        d = diagnose(model, meas, progress=report)
        cal = d.calibration
        out = cal.to_dict()
        out["diagnosis"] = d.to_dict()
    else:
        report(0.05, "choosing the geometric model on held-out poses")
        selection = select_geometry(model, meas)
        cal = selection.calibration
        out = cal.to_dict()
        out["model_selection"] = selection.to_dict()
    report(1.0, "done")
    out["robot_state"] = cal.robot.to_state()
    return out
