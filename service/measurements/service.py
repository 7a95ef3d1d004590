"""Measurement sets: parse the CSV all-or-nothing with calib_core, store the raw bytes plus a summary."""
from __future__ import annotations

import csv
import hashlib
import logging
import multiprocessing as mp
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from calib_core.identify import DISTINCT_DECIMALS
from calib_core.io import MeasurementError, Measurements, parse_measurements
from calib_core.units_check import unit_problems

from ..db import Database
from ..problems import MAX_ERRORS, ProblemError, get_or_404, not_found
from ..robots.models import Robot
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


def _invalid(errors: list[dict], total: int) -> ProblemError:
    shown = min(len(errors), MAX_ERRORS)
    more = f" (the first {shown} are listed)" if total > shown else ""
    return ProblemError(422, f"the CSV has {total} error{'s' * (total != 1)}{more}; nothing was stored",
                        kind="invalid-csv", errors=errors, error_count=total, total_errors=total)


def _unreadable() -> ProblemError:
    return ProblemError(422, "the CSV cannot be read; nothing was stored", kind="invalid-csv",
                        errors=[{"row": None, "column": None, "value": None,
                                 "message": "the file cannot be read as a contract measurement CSV"}])


def _too_few(n_poses: int, distinct: int) -> ProblemError:
    what = (f"{n_poses} pose{'s' * (n_poses != 1)}" if distinct == n_poses else
            f"{n_poses} poses but only {distinct} different joint configuration{'s' * (distinct != 1)}")
    return ProblemError(422, f"the CSV holds {what}; a calibration needs at least {MIN_POSES} different poses "
                        "(better: dozens spread over every joint's range); nothing was stored", kind="invalid-csv",
                        errors=[{"row": None, "column": None, "value": n_poses,
                                 "message": f"too few poses: {what}, a calibration needs at least {MIN_POSES} "
                                            "different ones"}])


def _wrong_units(errors: list[dict]) -> ProblemError:
    cols = list(dict.fromkeys(str(e["column"]) for e in errors))
    return ProblemError(422, f"the CSV's {', '.join(cols)} cannot be in the model's units (see each error for the "
                        "likely unit and what to do); nothing was stored", kind="invalid-csv", errors=errors,
                        error_count=len(errors), total_errors=len(errors))


def parse_or_reject(raw: bytes, model, instrument: str | None = None, limits: str = "reject") -> Measurements:
    try:
        meas = parse_measurements(raw, model, instrument=instrument, limits=limits)
    except MeasurementError as exc:
        raise _invalid(exc.errors, exc.total) from None
    except (ValueError, TypeError, IndexError, UnicodeError, ArithmeticError, csv.Error):
        log.info("unreadable CSV", exc_info=True)
        raise _unreadable() from None
    distinct = len(np.unique(np.round(meas.joints, DISTINCT_DECIMALS), axis=0))
    if distinct < MIN_POSES:
        raise _too_few(meas.n_poses, distinct)
    return meas


def check_upload(raw: bytes, model, instrument: str | None = None, limits: str = "reject") -> dict:
    """What an upload needs of its CSV, as plain data (it crosses a process boundary): {"n_poses",
    "out_of_limits", "columns"}, or {"problem": (kind, args)} for the 422 parse_or_reject would raise, or the
    422 of calib_core.units_check (points or joint columns that look written in another unit than the model's)."""
    try:
        meas = parse_measurements(raw, model, instrument=instrument, limits=limits)
    except MeasurementError as exc:
        return {"problem": ("invalid", (exc.errors, exc.total))}
    except (ValueError, TypeError, IndexError, UnicodeError, ArithmeticError, csv.Error) as exc:
        return {"problem": ("unreadable", ()), "why": f"{type(exc).__name__}: {exc}"[:1000]}
    distinct = len(np.unique(np.round(meas.joints, DISTINCT_DECIMALS), axis=0))
    if distinct < MIN_POSES:
        return {"problem": ("too_few", (meas.n_poses, distinct))}
    try:  # issue 33: points or joint columns in another unit than the model's, named before anything is stored
        wrong = unit_problems(model, meas)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):  # a check that cannot judge says nothing
        log.warning("the units check failed; the upload is judged without it", exc_info=True)
        wrong = []
    if wrong:
        return {"problem": ("units", (wrong,))}
    return {"n_poses": meas.n_poses, "out_of_limits": meas.out_of_limits, "columns": _header(raw)}


_PROBLEMS = {"invalid": _invalid, "unreadable": _unreadable, "too_few": _too_few, "units": _wrong_units}


class _Parsers:
    """The CSV parse processes (CALIB_PARSE_PROCESSES): an upload's CSV is checked there, not in the API process,
    whose GIL the event loop, /health and every other route share (issue 10: parsing was half of it under the
    red team's load). A pool that broke (a parse process died) is replaced; the upload that saw it gets 503."""

    def __init__(self):
        self.lock = threading.Lock()
        self.pool: ProcessPoolExecutor | None = None
        self.size = 0

    def get(self, size: int) -> ProcessPoolExecutor:
        with self.lock:
            if self.pool is None or self.size != size:
                if self.pool is not None:
                    self.pool.shutdown(wait=False, cancel_futures=True)
                self.pool = ProcessPoolExecutor(size, mp_context=mp.get_context("spawn"),
                                                initializer=_parser_init)
                self.size = size
            return self.pool

    def broken(self, pool: ProcessPoolExecutor) -> None:
        with self.lock:
            if self.pool is pool:
                self.pool = None
        pool.shutdown(wait=False, cancel_futures=True)

    def warm(self, size: int) -> None:
        """Start the processes and import the parser in them now, not on the first upload."""
        if size > 0:
            pool = self.get(size)
            try:
                for f in [pool.submit(_parser_ready) for _ in range(size)]:
                    f.result(timeout=120)
            except Exception:  # noqa: BLE001 - serve anyway: a broken pool is replaced at the next upload
                log.warning("the CSV parse processes did not start; uploads will try again", exc_info=True)

    def shutdown(self) -> None:
        with self.lock:
            pool, self.pool = self.pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


PARSERS = _Parsers()


def _parser_init() -> None:
    import signal

    from ..queue.runner import _watch_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when its parse processes end
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    _watch_parent(os.getppid())  # a server killed outright (SIGKILL) leaves no parse process behind


def _parser_ready() -> int:
    return os.getpid()


def checked_upload(raw: bytes, model, instrument: str | None = None, limits: str = "reject",
                   processes: int = 0) -> dict:
    """check_upload in a parse process (processes > 0) or here (0); raises the 422 ProblemError it names."""
    if processes > 0:
        pool = PARSERS.get(processes)
        try:
            out = pool.submit(check_upload, raw, model, instrument, limits).result()
        except BrokenProcessPool:
            PARSERS.broken(pool)
            log.warning("a CSV parse process died; the parse pool is restarted")
            raise ProblemError(503, "the CSV could not be checked (its parse process died); nothing was stored; "
                               "try again", kind="unavailable", headers={"Retry-After": "1"}) from None
    else:
        out = check_upload(raw, model, instrument, limits)
    if "problem" in out:
        kind, args = out["problem"]
        if kind == "unreadable":
            log.info("unreadable CSV: %s", out.get("why"))
        raise _PROBLEMS[kind](*args)
    return out


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
                           instrument: str | None = None, limits: str = "reject",
                           parse_processes: int = 0) -> MeasurementSet:
    """Parse outside any write transaction (robots are immutable; in a parse process when parse_processes > 0),
    then insert in one short transaction; nothing is stored unless the whole CSV is good.
    `instrument` and `limits` are stored with the set: its jobs re-parse the CSV with them."""
    with db.read_session() as s:
        model = model_of(get_robot(s, robot_id))
    filename = check_filename(filename)
    out = checked_upload(raw, model, instrument, limits, parse_processes)
    m = MeasurementSet(robot_id=robot_id, filename=filename, n_poses=out["n_poses"], columns=out["columns"],
                       size_bytes=len(raw), sha256=hashlib.sha256(raw).hexdigest(), raw=raw,
                       instrument=instrument, limits=limits, out_of_limits=out["out_of_limits"])
    with db.session() as s:
        # the robot may have been deleted while the CSV was checked: 404, not a foreign-key error (on PostgreSQL
        # the key-share lock keeps a DELETE /robots/{id} waiting until this set is stored, then it sees the set)
        if s.scalars(select(Robot.id).where(Robot.id == robot_id).with_for_update(key_share=True)).first() is None:
            raise not_found("robot", robot_id)
        s.add(m)
    return m


def get_measurement_set(s: Session, ms_id: str) -> MeasurementSet:
    return get_or_404(s, MeasurementSet, ms_id, "measurement set")


def delete_measurement_set(db: Database, ms_id: str) -> dict[str, int]:
    """DELETE /measurements/{id}: the set, its finished jobs, the calibrations made from it and their plots, in one
    transaction; 409 (nothing deleted) while a queued or running job uses it. What was deleted, counted."""
    with db.session() as s:
        get_measurement_set(s, ms_id)
        n = delete_sets(s, MeasurementSet.id == ms_id, f"measurement set {ms_id!r}")
    log_deleted(f"measurement set {ms_id!r}", n)
    return n


def delete_sets(s: Session, which, what: str, lock=None) -> dict[str, int]:
    """Delete the measurement sets matching the condition `which` with everything made from them (jobs,
    calibrations, plots) in the session's transaction, or a 409 naming the queued or running jobs that use them.

    Locks on PostgreSQL (SQLite serialises writers anyway), in the order a finishing job takes them (its job row,
    then the rows its calibration refers to), so neither waits on the other for ever: the jobs of the sets, then
    `lock()` (the robot, for DELETE /robots/{id}) and the sets themselves (a job queued meanwhile holds a key-share
    lock on its set until it commits), then the jobs again."""
    from ..calibrations.models import Calibration
    from ..jobs.models import QUEUED, RUNNING, Job
    from ..report.models import CalibrationPlot

    sets = select(MeasurementSet.id).where(which)
    jobs_q = (select(Job.id, Job.status, Job.measurement_set_id).where(Job.measurement_set_id.in_(sets))
              .order_by(Job.id).with_for_update())

    def refuse_busy() -> None:
        busy = [j for j in s.execute(jobs_q).all() if j.status in (QUEUED, RUNNING)]
        if busy:
            listed = ", ".join(f"{j.id} ({j.status})" for j in busy[:10]) + (" ..." if len(busy) > 10 else "")
            raise ProblemError(409, f"{what} is used by {len(busy)} queued or running job{'s' * (len(busy) != 1)}: "
                               f"{listed}; cancel {'them' if len(busy) > 1 else 'it'} (POST /jobs/{{id}}/cancel) "
                               "or wait until finished, then delete again; nothing was deleted", kind="conflict",
                               jobs=[{"id": j.id, "status": j.status, "measurement_set_id": j.measurement_set_id}
                                     for j in busy[:MAX_ERRORS]])

    refuse_busy()
    if lock is not None:
        lock()
    s.execute(sets.order_by(MeasurementSet.id).with_for_update()).all()
    refuse_busy()
    cals = select(Calibration.id).where(Calibration.measurement_set_id.in_(sets))
    quick = {"synchronize_session": False}
    n = {"calibration_plots": s.execute(delete(CalibrationPlot).where(CalibrationPlot.calibration_id.in_(cals)),
                                        execution_options=quick).rowcount,
         "calibrations": s.execute(delete(Calibration).where(Calibration.measurement_set_id.in_(sets)),
                                   execution_options=quick).rowcount,
         "jobs": s.execute(delete(Job).where(Job.measurement_set_id.in_(sets)), execution_options=quick).rowcount}
    n["measurement_sets"] = s.execute(delete(MeasurementSet).where(which), execution_options=quick).rowcount
    return n


def log_deleted(what: str, n: dict[str, int]) -> None:
    log.info("deleted %s: %s", what, ", ".join(f"{v} {k}" for k, v in n.items()))


def list_for_robot(s: Session, robot_id: str, limit: int, offset: int) -> list[MeasurementSet]:
    get_robot(s, robot_id)
    q = (select(MeasurementSet).where(MeasurementSet.robot_id == robot_id)
         .order_by(MeasurementSet.created_at, MeasurementSet.id).limit(limit).offset(offset))
    return list(s.scalars(q))
