"""One call from measured data to the calibration answer: the entry point of a service job."""
from __future__ import annotations

from typing import Callable

from .identify import identify
from .io import Measurements
from .model import RobotModel

MODES = ("geometric", "auto")


def calibrate(model: RobotModel, meas: Measurements, mode: str = "geometric",
              progress: Callable[[float, str], None] | None = None) -> dict:
    """Identify the model from the measurements; returns the answer dict plus `robot_state` for persistence.

    mode 'geometric' identifies the geometric model; 'auto' also runs the diagnosis (not yet available).
    """
    if mode not in MODES:
        raise ValueError(f"unknown model {mode!r}; use one of {MODES}")
    if mode == "auto":
        raise NotImplementedError("model 'auto' (diagnosis of hidden effects) is not available yet; use 'geometric'")
    report = progress or (lambda fraction, message: None)
    report(0.05, "identifying the geometric model")
    cal = identify(model, meas)
    report(1.0, "done")
    out = cal.to_dict()
    out["robot_state"] = cal.robot.to_state()
    return out
