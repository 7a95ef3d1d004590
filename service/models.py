"""All ORM models in one import (Alembic's target metadata)."""
from .calibrations.models import Calibration
from .db import Base
from .jobs.models import Job
from .measurements.models import MeasurementSet
from .robots.models import Robot

__all__ = ["Base", "Calibration", "Job", "MeasurementSet", "Robot"]
