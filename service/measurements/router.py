from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, File, Query, Request, Response, UploadFile
from sqlalchemy.orm import Session

from calib_core.instruments import INSTRUMENTS

from ..db import Database
from ..deps import get_db, get_read_session, get_settings, require_writer
from ..problems import ProblemError, problem_responses
from . import service
from .schemas import MeasurementSetOut

Instrument = Literal[tuple(INSTRUMENTS)]  # type: ignore[valid-type]
"""The names of calib_core.instruments.INSTRUMENTS: an enum in the OpenAPI, a 422 naming the choices otherwise."""

router = APIRouter(tags=["measurements"])

CSV_EXAMPLE = ("point,J1,J2,J3,J4,J5,J6,J7,x,y,z,timestamp\n"
               "P001,3098.611678,54.315206,-45.791980,73.781843,-76.455800,1757.014212,-70.779606,"
               "-2821.3401,876.6147,-16.3583,2026-11-03T08:00:19+00:00\n")


async def one_file_part(request: Request) -> None:
    """Exactly one multipart part named `file`: a second one would otherwise be silently ignored."""
    if not request.headers.get("content-type", "").lower().startswith("multipart/"):
        return
    form = await request.form()  # already parsed by FastAPI for `file`; cached on the request
    n = len(form.getlist("file"))
    if n > 1:
        raise ProblemError(422, f"the upload has {n} parts named 'file'; send exactly one CSV per upload",
                           kind="invalid-csv", errors=[{"row": None, "column": None, "value": n, "field": "file",
                                                        "message": "only one 'file' part is allowed"}])


@router.post("/robots/{robot_id}/measurements", status_code=201, response_model=MeasurementSetOut,
             dependencies=[Depends(require_writer), Depends(one_file_part)],
             responses=problem_responses(401, 404, 413, 422, 503),
             summary="Upload a measurement CSV (contract section 2, multipart field `file`)",
             openapi_extra={"requestBody": {"content": {"multipart/form-data": {
                 "schema": {"type": "object", "required": ["file"],
                            "properties": {"file": {"type": "string", "format": "binary"}}},
                 "examples": {"spray7": {"summary": "one pose of spray7", "value": {"file": CSV_EXAMPLE}}}}}}})
async def upload(robot_id: str, response: Response, file: UploadFile = File(..., description="the measurement CSV"),
                 instrument: Instrument | None = Query(None, description="the noise model where the CSV has no `sigma` "
                                                       "column (calib_core.instruments); default: a laser tracker, and "
                                                       "the answer's `noise_model` says it was assumed"),
                 limits: Literal["reject", "warn"] = Query("reject", description="joint values outside the model's "
                                                           "limits: `reject` (422 naming each) or `warn` (accepted; "
                                                           "the answer's `out_of_limits` gives the extent per joint)"),
                 db: Database = Depends(get_db), settings=Depends(get_settings)) -> MeasurementSetOut:
    """The CSV is checked all-or-nothing against the robot's model (joint names, limits, numbers, timestamps).
    On any problem nothing is stored and the 422 problem document lists every error as
    `{row, column, value, message}` (row = line number in the file). Bodies above the size limit get 413.
    `instrument` and `limits` are stored with the set and used by every job on it.
    The CSV is checked in a parse process: uploads up to 1 MiB in a lane of their own (a small upload never waits
    behind a large one), larger ones in `CALIB_PARSE_PROCESSES`, with a waiting room of `CALIB_PARSE_ROOM_BYTES`
    bytes (default 8 uploads of the maximum size); a full waiting room, a check running longer than
    `CALIB_PARSE_TIMEOUT_S` or a parse process that died is a 503 with `Retry-After`, nothing stored."""
    raw = await file.read(settings.max_upload_bytes + 1)
    if len(raw) > settings.max_upload_bytes:
        raise ProblemError(413, f"the upload exceeds {settings.max_upload_bytes} bytes", kind="too-large")
    m = await service.create_measurement_set_async(db, robot_id, raw, file.filename, instrument, limits,
                                                   settings.parse_processes, settings.parse_timeout_s,
                                                   settings.parse_room_bytes)
    response.headers["Location"] = f"/measurements/{m.id}"
    return MeasurementSetOut.of(m)


@router.get("/robots/{robot_id}/measurements", response_model=list[MeasurementSetOut],
            responses=problem_responses(404), summary="The measurement sets of a robot, oldest first")
def list_sets(robot_id: str, limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=2**31),
              s: Session = Depends(get_read_session, scope="function")) -> list[MeasurementSetOut]:
    return [MeasurementSetOut.of(m) for m in service.list_for_robot(s, robot_id, limit, offset)]


@router.get("/measurements/{measurement_set_id}", response_model=MeasurementSetOut,
            responses=problem_responses(404), summary="A stored measurement set's summary")
def get_set(measurement_set_id: str, s: Session = Depends(get_read_session, scope="function")) -> MeasurementSetOut:
    return MeasurementSetOut.of(service.get_measurement_set(s, measurement_set_id))


DELETE_DOC = """Deletes the measurement set with everything made from it: its finished jobs, the calibrations made from
it and their plots (export what you keep first, e.g. `GET /calibrations/{id}/model`). `409` (nothing deleted) while
a queued or running job uses it: the problem document's `jobs` lists them; cancel them (`POST /jobs/{id}/cancel`)
or wait, then delete again. `404` when there is no such set (a second DELETE). The robot stays."""


@router.delete("/measurements/{measurement_set_id}", status_code=204, response_class=Response,
               dependencies=[Depends(require_writer)], responses=problem_responses(401, 404, 409),
               summary="Delete a measurement set and everything made from it", description=DELETE_DOC)
def delete_set(measurement_set_id: str, db: Database = Depends(get_db)) -> Response:
    service.delete_measurement_set(db, measurement_set_id)
    return Response(status_code=204)
