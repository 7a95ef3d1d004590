"""Measurement sets: parse the CSV all-or-nothing with calib_core, store the raw bytes plus a summary."""
from __future__ import annotations

import csv
import hashlib

from sqlalchemy import select
from sqlalchemy.orm import Session

from calib_core.io import MeasurementError, Measurements, parse_measurements

from ..db import Database
from ..problems import ProblemError, get_or_404
from ..robots.service import get_robot, model_of
from .models import MeasurementSet


def _header(raw: bytes) -> list[str]:
    text = raw.decode("utf-8-sig")
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith(("#", "//")):
            return [h.strip() for h in next(csv.reader([line], skipinitialspace=True))]
    return []


def parse_or_reject(raw: bytes, model) -> Measurements:
    try:
        return parse_measurements(raw, model)
    except MeasurementError as exc:
        shown = len(exc.errors)
        more = f" (the first {shown} are listed)" if exc.total > shown else ""
        raise ProblemError(422, f"the CSV has {exc.total} error{'s' * (exc.total != 1)}{more}; nothing was stored",
                           kind="invalid-csv", errors=exc.errors, total_errors=exc.total) from None
    except (ValueError, TypeError, IndexError, UnicodeError) as exc:
        raise ProblemError(422, f"the CSV cannot be read: {exc}; nothing was stored", kind="invalid-csv",
                           errors=[{"row": None, "column": None, "value": None, "message": str(exc)}]) from None


def create_measurement_set(db: Database, robot_id: str, raw: bytes, filename: str | None) -> MeasurementSet:
    """Parse outside any write transaction (robots are immutable), then insert in one short transaction."""
    with db.read_session() as s:
        model = model_of(get_robot(s, robot_id))
    meas = parse_or_reject(raw, model)
    m = MeasurementSet(robot_id=robot_id, filename=filename, n_poses=meas.n_poses, columns=_header(raw),
                       size_bytes=len(raw), sha256=hashlib.sha256(raw).hexdigest(), raw=raw)
    with db.session() as s:
        s.add(m)
    return m


def get_measurement_set(s: Session, ms_id: str) -> MeasurementSet:
    return get_or_404(s, MeasurementSet, ms_id, "measurement set")


def list_for_robot(s: Session, robot_id: str, limit: int, offset: int) -> list[MeasurementSet]:
    get_robot(s, robot_id)
    q = (select(MeasurementSet).where(MeasurementSet.robot_id == robot_id)
         .order_by(MeasurementSet.created_at, MeasurementSet.id).limit(limit).offset(offset))
    return list(s.scalars(q))
