from __future__ import annotations

from fastapi import APIRouter, Body, Depends, Path, Query
from fastapi.responses import HTMLResponse, Response
from sqlalchemy.orm import Session

from ..db import Database
from ..deps import get_db, get_read_session, get_settings, require_writer
from ..problems import problem_responses
from . import compute, service
from .schemas import CalibrationOut, CompensateIn, CompensateOut, PredictIn, PredictOut

router = APIRouter(tags=["calibrations"])


@router.get("/calibrations/{calibration_id}", response_model=CalibrationOut, responses=problem_responses(404),
            summary="Parameters, metrics and diagnosis of a calibration")
def get_calibration(calibration_id: str, s: Session = Depends(get_read_session, scope="function")) -> dict:
    return service.answer(service.get_calibration(s, calibration_id))


@router.get("/calibrations/{calibration_id}/report", response_class=HTMLResponse,
            responses={200: {"description": "the report page", "content": {"text/html": {"example": "<!DOCTYPE html>..."}}},
                       **problem_responses(404, 422)},
            summary="The calibration report: a page for people (parameters, error tables, diagnosis, plots)")
def get_report(calibration_id: str, inline: bool = Query(False, description="embed the plots in the page (a file "
                                                                            "that can be saved and mailed on its own)"),
               s: Session = Depends(get_read_session, scope="function")) -> HTMLResponse:
    """Everything on the page comes from the stored answer (`GET /calibrations/{id}`): the parameter table
    (value, std, unit), the error tables (mean, RMS, max; ISO 9283 AP), the diagnosis with its plots.
    Readable on a laptop, printable (A4)."""
    return HTMLResponse(service.report(service.get_calibration(s, calibration_id), inline=inline))


@router.get("/calibrations/{calibration_id}/plots/{name}.png", response_class=Response,
            responses={200: {"description": "the plot", "content": {"image/png": {
                "schema": {"type": "string", "format": "binary"}}}}, **problem_responses(404)},
            summary="A diagnosis plot as PNG (names listed in the calibration's `plots`)")
def get_plot(calibration_id: str, name: str = Path(..., description="`errors`, `distribution`, `finding-1`, ...",
                                                  examples=["errors"]),
             s: Session = Depends(get_read_session, scope="function")) -> Response:
    """`errors`: held-out error per pose, geometric and final model; `distribution`: their histograms;
    `finding-k`: the k-th finding's residual against its regressor, with the fitted effect."""
    png = service.plot_png(service.get_calibration(s, calibration_id), name)
    return Response(png, media_type="image/png", headers={"Cache-Control": "public, max-age=86400"})


@router.get("/calibrations/{calibration_id}/model", responses=problem_responses(404),
            summary="The calibrated model as contract model JSON (contract section 5)")
def get_calibrated_model(calibration_id: str, s: Session = Depends(get_read_session, scope="function")) -> dict:
    """The robot's model with the identified geometry and target points, in the model's units (MD-H rows, or
    xyz/rpy/axis rows in the model's own link frames when it was given so, e.g. imported from a URDF tree); a
    `calibration` object lists the identified effects the rows cannot hold and the identified base pose(s).
    It can be posted to `POST /robots` as it is."""
    return service.calibrated_model(s, service.get_calibration(s, calibration_id))


@router.get("/calibrations/{calibration_id}/urdf", response_class=Response,
            responses={200: {"description": "the URDF", "content": {"application/xml": {
                "schema": {"type": "string"}, "example": '<?xml version="1.0"?>\n<robot name="spray7">...'}}},
                **problem_responses(404, 422)},
            summary="The calibrated model as URDF (contract section 5)")
def get_calibrated_urdf(calibration_id: str,
                        base_joint: str | None = Query(None, description="a robot imported from a URDF: add a root "
                                                       "link of this name (`true`: `measurement_frame`) fixed to the "
                                                       "URDF's root by the identified base pose"),
                        form: str | None = Query(None, description="`original` (default for a robot imported from "
                                                 "a URDF): that file patched; `rows`: written from the model rows "
                                                 "(the default for any other model)"),
                        s: Session = Depends(get_read_session, scope="function")) -> Response:
    """A robot imported from a URDF: **the original file patched**. Only the `<origin xyz rpy>` of the joints the
    calibration moved are rewritten (full precision); every link and joint name, mesh, collision, inertial,
    transmission, gazebo tag and comment is kept as it was, and one comment after `<robot>` says what changed.
    What a URDF cannot hold (the measured target points in their links, the identified base poses, effects) is
    in `GET /calibrations/{id}/urdf/calibration.json`. `?base_joint=true` (or a link name) adds the measurement
    frame as a new root link with a fixed joint.

    Any other model (or `?form=rows`): each model row is a joint whose origin carries the identified geometry
    (MD-H rows: axis `0 0 1`; xyz/rpy rows: the row's own axis, fixed rows as fixed joints, coupled rows with
    `<mimic>`); each target is a link at its identified point; effects a URDF cannot hold are listed in a
    comment."""
    bj: str | bool | None = base_joint
    if base_joint is not None and base_joint.strip().lower() in ("", "false", "0", "no", "off"):
        bj = None
    elif base_joint is not None and base_joint.strip().lower() in ("true", "1", "yes", "on"):
        bj = True
    text = service.calibrated_urdf(s, service.get_calibration(s, calibration_id), bj, form)
    return Response(text, media_type="application/xml")


@router.get("/calibrations/{calibration_id}/urdf/calibration.json",
            responses=problem_responses(404),
            summary="What the patched URDF cannot hold: target points, base poses, effects (m, rad)")
def get_urdf_side_file(calibration_id: str, s: Session = Depends(get_read_session, scope="function")) -> dict:
    """The side file of `GET /calibrations/{id}/urdf` for a robot imported from a URDF: `targets` (each SMR point
    in its target link's frame, m), `base_poses` (per setup, the URDF base link in the measurement frame),
    `base_joint` (when asked for), `changed_joints`, `mimic` (multiplier / offset of each coupled row and where
    it is written), `effects` (identified effects with their values: predict and compensate include them, the
    URDF does not). 404 for a robot whose model did not come from a URDF."""
    return service.urdf_side_file(s, service.get_calibration(s, calibration_id))


@router.post("/calibrations/{calibration_id}/predict", response_model=PredictOut,
             dependencies=[Depends(require_writer)], responses=problem_responses(401, 404, 413, 422, 503),
             summary="Where the calibrated robot puts the measured point")
async def predict(calibration_id: str, body: PredictIn = Body(..., openapi_examples={"spray7": {
        "summary": "one pose of spray7 (mm, deg)",
        "value": {"joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]}}}),
        db: Database = Depends(get_db), settings=Depends(get_settings)) -> Response:
    """Joints in the model's units and joint order; positions in the measurement (tracker) frame, model length unit.
    Optional `tau` (measured joint torques, `tau_<joint>` as in the CSV) is the load of load-driven causes.
    Computed in one of `CALIB_COMPUTE_PROCESSES` processes, a few more waiting: beyond that, and for a request computing
    longer than `CALIB_COMPUTE_TIMEOUT_S`, the answer is 503 with `Retry-After`."""
    return Response(await compute.answer(db, settings, calibration_id, compute.predict_json, body),
                    media_type="application/json")


@router.post("/calibrations/{calibration_id}/compensate", response_model=CompensateOut,
             dependencies=[Depends(require_writer)], responses=problem_responses(401, 404, 413, 422, 503),
             summary="Joint commands that put the tool on targets, every identified effect included")
async def compensate(calibration_id: str, body: CompensateIn = Body(..., openapi_examples={
        "targets": {"summary": "one target with its nominal joint solution (spray7, mm, deg)",
                    "value": {"targets": [[-2821.34, 876.61, -16.36]],
                              "seed_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]}},
        "program": {"summary": "a program as joints only, telescopic J6 locked",
                    "value": {"program_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]],
                              "locked_joints": ["J6"]}}}),
        db: Database = Depends(get_db), settings=Depends(get_settings)) -> Response:
    """Per target, the joint command nearest the seed for which the calibrated model (effects included) puts
    the tool on the target, within the joint limits; an unreachable target is reported, not a failed batch.
    Computed in one of `CALIB_COMPUTE_PROCESSES` processes, a few more waiting: beyond that, and for a request computing
    longer than `CALIB_COMPUTE_TIMEOUT_S`, the answer is 503 with `Retry-After`."""
    return Response(await compute.answer(db, settings, calibration_id, compute.compensate_json, body),
                    media_type="application/json")
