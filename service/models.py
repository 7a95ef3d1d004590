"""All ORM models in one import (Alembic's target metadata)."""
from .calibrations.models import Calibration
from .db import Base
from .jobs.models import Job
from .measurements.models import MeasurementSet
from .report.models import CalibrationPlot
from .robots.models import Robot

__all__ = ["Base", "Calibration", "CalibrationPlot", "Job", "MeasurementSet", "Robot"]
