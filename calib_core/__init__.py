"""calib_core: robot kinematic calibration as a pure numeric library (numpy, scipy; no web code).

The small public front: parse a model and measurements, identify, simulate.
"""
from .identify import CalibratedRobot, Calibration, evaluate, identify
from .io import MeasurementError, Measurements, parse_measurements, write_measurements
from .model import ModelError, RobotModel, parse_model
from .pipeline import calibrate
from .plan import plan
from .twin import Twin

load_model = parse_model

__all__ = ["CalibratedRobot", "Calibration", "MeasurementError", "Measurements", "ModelError", "RobotModel",
           "Twin", "calibrate", "evaluate", "identify", "load_model", "parse_measurements", "parse_model", "plan", "write_measurements"]
