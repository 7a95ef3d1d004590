"""Measurement sets: parse the CSV all-or-nothing with calib_core, store the raw bytes plus a summary."""
from __future__ import annotations

import csv
import hashlib
import logging

import numpy as np

from sqlalchemy import select
from sqlalchemy.orm import Session

from calib_core.identify import DISTINCT_DECIMALS
from calib_core.io import MeasurementError, Measurements, parse_measurements

from ..db import Database
from ..problems import MAX_ERRORS, ProblemError, get_or_404
from ..robots.service import get_robot, model_of
from .models import MeasurementSet

log = logging.getLogger("service")


def _header(raw: bytes) -> list[str]:
    text = raw.decode("utf-8-sig")
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith(("#", "//")):
            return [h.strip() for h in next(csv.reader([line], skipinitialspace=True))]
    return []


MIN_POSES = 3
"""A calibration needs at least three different poses (calib_core.identify; better: dozens)."""
MAX_FILENAME_CHARS = 255


def parse_or_reject(raw: bytes, model, instrument: str | None = None, limits: str = "reject") -> Measurements:
    try:
        meas = parse_measurements(raw, model, instrument=instrument, limits=limits)
    except MeasurementError as exc:
        shown = min(len(exc.errors), MAX_ERRORS)
        more = f" (the first {shown} are listed)" if exc.total > shown else ""
        raise ProblemError(422, f"the CSV has {exc.total} error{'s' * (exc.total != 1)}{more}; nothing was stored",
                           kind="invalid-csv", errors=exc.errors, error_count=exc.total,
                           total_errors=exc.total) from None
    except (ValueError, TypeError, IndexError, UnicodeError, ArithmeticError, csv.Error):
        log.info("unreadable CSV", exc_info=True)
        raise ProblemError(422, "the CSV cannot be read; nothing was stored", kind="invalid-csv",
                           errors=[{"row": None, "column": None, "value": None,
                                    "message": "the file cannot be read as a contract measurement CSV"}]) from None
    distinct = len(np.unique(np.round(meas.joints, DISTINCT_DECIMALS), axis=0))
    if distinct < MIN_POSES:
        what = (f"{meas.n_poses} pose{'s' * (meas.n_poses != 1)}" if distinct == meas.n_poses else
                f"{meas.n_poses} poses but only {distinct} different joint configuration{'s' * (distinct != 1)}")
        raise ProblemError(422, f"the CSV holds {what}; a calibration needs at least {MIN_POSES} different poses "
                           "(better: dozens spread over every joint's range); nothing was stored", kind="invalid-csv",
                           errors=[{"row": None, "column": None, "value": meas.n_poses,
                                    "message": f"too few poses: {what}, a calibration needs at least {MIN_POSES} "
                                               "different ones"}])
    return meas


def check_filename(filename: str | None) -> str | None:
    """The upload's filename as stored, or a 422 naming the field."""
    if filename is None:
        return None
    why = None
    if len(filename) > MAX_FILENAME_CHARS:
        why = f"the filename is {len(filename)} characters long; at most {MAX_FILENAME_CHARS} are allowed"
    elif any(c < " " or c == "\x7f" for c in filename):
        why = "the filename must not contain control characters (NUL, line breaks)"
    if why:
        raise ProblemError(422, why + "; nothing was stored", kind="invalid-csv",
                           errors=[{"row": None, "column": None, "value": filename, "message": why,
                                    "field": "file.filename"}])
    return filename


def create_measurement_set(db: Database, robot_id: str, raw: bytes, filename: str | None,
                           instrument: str | None = None, limits: str = "reject") -> MeasurementSet:
    """Parse outside any write transaction (robots are immutable), then insert in one short transaction.
    `instrument` and `limits` are stored with the set: its jobs re-parse the CSV with them."""
    with db.read_session() as s:
        model = model_of(get_robot(s, robot_id))
    filename = check_filename(filename)
    meas = parse_or_reject(raw, model, instrument, limits)
    m = MeasurementSet(robot_id=robot_id, filename=filename, n_poses=meas.n_poses, columns=_header(raw),
                       size_bytes=len(raw), sha256=hashlib.sha256(raw).hexdigest(), raw=raw,
                       instrument=instrument, limits=limits, out_of_limits=meas.out_of_limits)
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
