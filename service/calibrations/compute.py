"""Predict and compensate off the API's route threads (issue 33): the calibration and its model are read on a route
thread, then the answer is computed, validated and written as JSON in a compute process (CALIB_COMPUTE_PROCESSES, a
lane of service/lanes.py, as plans are): bounded in number (ROOM_PER_PROCESS more waiting per process, beyond that
503 with Retry-After at once) and in time (CALIB_COMPUTE_TIMEOUT_S: the process is killed and replaced, 503 naming
the bound). A request waiting for its process holds no route thread; the API process only moves bytes.
`CALIB_COMPUTE_PROCESSES=0` computes on a route thread, as before."""
from __future__ import annotations

from typing import NamedTuple

import anyio
import anyio.to_thread

from ..db import Database
from ..lanes import Lane, Words
from ..robots.models import Robot
from ..robots.service import model_of
from . import service
from .schemas import CompensateIn, CompensateOut, PredictIn, PredictOut

COMPUTERS = Lane("compute", __name__, Words(
    "prediction or compensation", "CALIB_COMPUTE_TIMEOUT_S",
    advice="fewer rows (or a lower max_iter), or a retry when the server is less busy, answer faster"))
ROOM_PER_PROCESS = 8
"""Requests waiting for a compute process at most, per process (a 10 000-row predict takes well under a second)."""


class Stored(NamedTuple):
    """What predict and compensate use of a stored calibration, as plain data (it crosses to a compute process)."""
    robot_state: dict


def load(db: Database, calibration_id: str):
    """The calibration's robot model and state (404 when there is no such calibration)."""
    with db.read_session() as s:
        c = service.get_calibration(s, calibration_id)
        return model_of(s.get(Robot, c.robot_id)), Stored(c.robot_state)


def predict_json(model, stored: Stored, body: PredictIn) -> bytes:
    positions, unit, notes = service.predict(model, stored, body.joints, body.payload, body.temperature,
                                             body.timestamp, body.target, body.setup, body.tau, body.sequence)
    return PredictOut(positions=positions, unit=unit, notes=notes).model_dump_json().encode()


def compensate_json(model, stored: Stored, body: CompensateIn) -> bytes:
    return CompensateOut.model_validate(service.compensate(model, stored, body)).model_dump_json().encode()


def configure(processes: int, timeout_s: float) -> Lane:
    COMPUTERS.configure(processes, ROOM_PER_PROCESS * processes, timeout_s)
    return COMPUTERS


async def answer(db: Database, settings, calibration_id: str, fn, body) -> bytes:
    """fn(model, stored, body) for the calibration: in a compute process (or a route thread when there are none)."""
    model, stored = await anyio.to_thread.run_sync(load, db, calibration_id)
    if settings.compute_processes > 0:
        return await configure(settings.compute_processes, settings.compute_timeout_s).arun(fn, (model, stored, body))
    return await anyio.to_thread.run_sync(fn, model, stored, body)
