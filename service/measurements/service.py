"""Measurement sets: parse the CSV all-or-nothing with calib_core, store the raw bytes plus a summary."""
from __future__ import annotations

import csv
import hashlib
import logging

import anyio
import anyio.to_thread
import numpy as np

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from calib_core.identify import DISTINCT_DECIMALS, prealign
from calib_core.io import MeasurementError, Measurements, parse_measurements
from calib_core.units_check import unit_problems

from ..config import PARSE_ROOM_UPLOADS
from ..db import Database
from ..lanes import Lane, Words
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
    few = setup_problems(model, meas)
    if few:
        return {"problem": ("setups", (few,))}
    try:  # issue 33: points or joint columns in another unit than the model's, named before anything is stored
        wrong = unit_problems(model, meas)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):  # a check that cannot judge says nothing
        log.warning("the units check failed; the upload is judged without it", exc_info=True)
        wrong = []
    if wrong:
        return {"problem": ("units", (wrong,))}
    return {"n_poses": meas.n_poses, "out_of_limits": meas.out_of_limits, "columns": _header(raw)}


def setup_problems(model, meas: Measurements) -> list[dict]:
    """Each setup's base pose is placed by a rigid fit of its own poses (calib_core.identify.prealign): a setup with
    fewer than three distinct measured positions cannot be calibrated. Named at upload (issue 33: one setup per row
    was accepted and failed only at job time)."""
    if meas.setup is None:
        return []
    try:
        prealign(model, meas)
    except ValueError as exc:
        counts = np.bincount(meas.setup, minlength=meas.n_setups)
        few = [meas.setup_names[s] for s in range(meas.n_setups) if counts[s] < MIN_POSES]
        more = (f" ({len(few)} of the {meas.n_setups} setups have fewer than {MIN_POSES} rows: "
                f"{', '.join(few[:5])}{' ...' if len(few) > 5 else ''})") if few else ""
        return [{"row": None, "column": "setup", "value": few[0] if few else None,
                 "message": f"{exc}; each setup has a base pose of its own, placed from at least {MIN_POSES} of its "
                            f"poses at distinct positions{more}"}]
    return []


def _bad_setups(errors: list[dict]) -> ProblemError:
    return ProblemError(422, "the CSV's setups cannot be calibrated (see the error); nothing was stored",
                        kind="invalid-csv", errors=errors, error_count=len(errors), total_errors=len(errors))


_PROBLEMS = {"invalid": _invalid, "unreadable": _unreadable, "too_few": _too_few, "units": _wrong_units,
             "setups": _bad_setups}


SMALL_UPLOAD_BYTES = 1024 * 1024
"""Uploads up to this size are checked in a lane of their own (service/lanes.py): a small upload never waits behind
a large one (issue 33: six concurrent 19 MB hostile CSVs made a valid 25 KB upload wait 69 s). A 150-pose CSV is about
25 KB, 5000 poses about 0.6 MB; a CSV that takes seconds to check is megabytes long."""
LARGE_NICE = 5
"""The large-upload lane's processes run this many nice steps below the API: a 19 MB CSV checked for half a minute
is batch work beside /health and the small uploads (whose lane keeps the API's priority)."""
SMALL_ROOM = 32
"""Small uploads waiting for their lane at most (each is checked in milliseconds); more: 503 with Retry-After."""
LARGE_ROOM_UPLOADS = PARSE_ROOM_UPLOADS
"""The large uploads' waiting room is counted in bytes (CALIB_PARSE_ROOM_BYTES, service/lanes.py), by default this many
uploads of the largest size allowed (CALIB_MAX_UPLOAD_BYTES): 8 x 20 MiB = 160 MiB, whatever the number of processes.
An upload is admitted while the uploads waiting hold at most that many bytes with it; more: 503 with Retry-After
(each is over SMALL_UPLOAD_BYTES: fewer than the room / 1 MiB of them wait, 160 by default).
Counting uploads (8 per process, before) refused the red team's 1.8 MB hostile CSVs while six 19 MB ones held the room
(issue 33); by bytes, six 19 MB CSVs waiting (114 MB) leave room for 50 MB more, and the smallest is checked
next. Memory: the waiting uploads' bytes are held in the API process (read whole by the route before it asks for the
lane), so the room bounds them; the time the last one waits is about the checking time of the bytes ahead of it."""
DEFAULT_ROOM_BYTES = LARGE_ROOM_UPLOADS * 20 * 1024 * 1024
"""The byte budget for the default maximum upload (service.config.Settings), for callers that name none."""


class _Parsers:
    """The CSV parse processes (CALIB_PARSE_PROCESSES): an upload's CSV is checked there, not in the API process,
    whose GIL the event loop, /health and every other route share (issue 10: parsing was half of it under the
    red team's load). Two lanes (service/lanes.py): CALIB_PARSE_PROCESSES processes for uploads larger than
    SMALL_UPLOAD_BYTES, with a waiting room of CALIB_PARSE_ROOM_BYTES bytes (LARGE_ROOM_UPLOADS), and half as many
    (at least one) of their own for the smaller ones, SMALL_ROOM of them waiting; in each the smallest CSV waiting is
    checked first. A check running longer than CALIB_PARSE_TIMEOUT_S is stopped, and a parse process that dies is
    replaced: either costs its upload a 503 with Retry-After, as does a full waiting room."""

    def __init__(self):
        words = dict(timeout_env="CALIB_PARSE_TIMEOUT_S", nothing="nothing was stored",
                     advice="a smaller CSV, or a retry when the server is less busy, is checked faster")
        self.small = Lane("parse-small", __name__, Words(noun="CSV check", **words))
        self.large = Lane("parse", __name__, Words(noun="CSV check", room_env="CALIB_PARSE_ROOM_BYTES", **words),
                          nice=LARGE_NICE)

    def configure(self, size: int, timeout_s: float = 120.0, room_bytes: int = DEFAULT_ROOM_BYTES) -> None:
        """`size` processes for large uploads, `room_bytes` bytes of them waiting; half as many processes (at least one)
        for small ones, SMALL_ROOM of them waiting."""
        self.small.configure(max(1, (size + 1) // 2), SMALL_ROOM, timeout_s)
        self.large.configure(size, 0, timeout_s, max(1, room_bytes))

    def warm(self, size: int, timeout_s: float = 120.0, room_bytes: int = DEFAULT_ROOM_BYTES) -> None:
        """Start the processes and import the parser in them now, not on the first upload."""
        if size > 0:
            self.configure(size, timeout_s, room_bytes)
            self.small.warm(self.small.size, SMALL_ROOM, timeout_s)
            self.large.warm(size, 0, timeout_s, max(1, room_bytes))

    def lane(self, raw: bytes, size: int, timeout_s: float, room_bytes: int = DEFAULT_ROOM_BYTES) -> Lane:
        self.configure(size, timeout_s, room_bytes)
        return self.small if len(raw) <= SMALL_UPLOAD_BYTES else self.large

    def shutdown(self) -> None:
        self.small.shutdown()
        self.large.shutdown()


PARSERS = _Parsers()


def _answer(out: dict) -> dict:
    if "problem" in out:
        kind, args = out["problem"]
        if kind == "unreadable":
            log.info("unreadable CSV: %s", out.get("why"))
        raise _PROBLEMS[kind](*args)
    return out


def checked_upload(raw: bytes, model, instrument: str | None = None, limits: str = "reject",
                   processes: int = 0, timeout_s: float = 120.0, room_bytes: int = DEFAULT_ROOM_BYTES) -> dict:
    """check_upload in a parse process (processes > 0) or here (0); raises the 422 ProblemError it names."""
    if processes > 0:
        out = PARSERS.lane(raw, processes, timeout_s, room_bytes).run(
            check_upload, (raw, model, instrument, limits), len(raw), len(raw))
    else:
        out = check_upload(raw, model, instrument, limits)
    return _answer(out)


async def checked_upload_async(raw: bytes, model, instrument: str | None = None, limits: str = "reject",
                               processes: int = 0, timeout_s: float = 120.0,
                               room_bytes: int = DEFAULT_ROOM_BYTES) -> dict:
    """checked_upload, waited for on the event loop (no route thread held while the CSV waits for its lane)."""
    args = (raw, model, instrument, limits)
    if processes > 0:
        out = await PARSERS.lane(raw, processes, timeout_s, room_bytes).arun(check_upload, args, len(raw), len(raw))
    else:
        out = await anyio.to_thread.run_sync(check_upload, *args)
    return _answer(out)


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
                           parse_processes: int = 0, parse_timeout_s: float = 120.0,
                           parse_room_bytes: int = DEFAULT_ROOM_BYTES) -> MeasurementSet:
    """Parse outside any write transaction (robots are immutable; in a parse process when parse_processes > 0),
    then insert in one short transaction; nothing is stored unless the whole CSV is good.
    `instrument` and `limits` are stored with the set: its jobs re-parse the CSV with them."""
    model = robot_model(db, robot_id)
    filename = check_filename(filename)
    out = checked_upload(raw, model, instrument, limits, parse_processes, parse_timeout_s, parse_room_bytes)
    return store_set(db, robot_id, raw, filename, instrument, limits, out)


async def create_measurement_set_async(db: Database, robot_id: str, raw: bytes, filename: str | None,
                                       instrument: str | None = None, limits: str = "reject",
                                       parse_processes: int = 0, parse_timeout_s: float = 120.0,
                                       parse_room_bytes: int = DEFAULT_ROOM_BYTES) -> MeasurementSet:
    """create_measurement_set for an async route: the database in route threads, the CSV's wait for its parse lane
    on the event loop (a large CSV waiting holds no route thread)."""
    model = await anyio.to_thread.run_sync(robot_model, db, robot_id)
    filename = check_filename(filename)
    out = await checked_upload_async(raw, model, instrument, limits, parse_processes, parse_timeout_s,
                                     parse_room_bytes)
    return await anyio.to_thread.run_sync(store_set, db, robot_id, raw, filename, instrument, limits, out)


def robot_model(db: Database, robot_id: str):
    with db.read_session() as s:
        return model_of(get_robot(s, robot_id))


def store_set(db: Database, robot_id: str, raw: bytes, filename: str | None, instrument: str | None, limits: str,
              out: dict) -> MeasurementSet:
    """The checked CSV stored in one short transaction."""
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
