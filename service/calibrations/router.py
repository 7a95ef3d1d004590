from __future__ import annotations

from fastapi import APIRouter, Body, Depends, Path, Query
from fastapi.responses import HTMLResponse, Response
from sqlalchemy.orm import Session

from ..deps import get_read_session, require_writer
from ..problems import problem_responses
from . import service
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
                **problem_responses(404)},
            summary="The calibrated model as URDF (contract section 5)")
def get_calibrated_urdf(calibration_id: str, s: Session = Depends(get_read_session, scope="function")) -> Response:
    """Each model row is a joint whose origin carries the identified geometry (MD-H rows: axis `0 0 1`; xyz/rpy
    rows: the row's own axis, fixed rows as fixed joints, coupled rows with `<mimic>`); each target is a link at
    its identified point; effects a URDF cannot hold are listed in a comment. A model imported from a URDF keeps
    its base, link and target names and frames."""
    text = service.calibrated_urdf(s, service.get_calibration(s, calibration_id))
    return Response(text, media_type="application/xml")


@router.post("/calibrations/{calibration_id}/predict", response_model=PredictOut,
             dependencies=[Depends(require_writer)], responses=problem_responses(401, 404, 413, 422),
             summary="Where the calibrated robot puts the measured point")
def predict(calibration_id: str, body: PredictIn = Body(..., openapi_examples={"spray7": {
        "summary": "one pose of spray7 (mm, deg)",
        "value": {"joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]}}}),
        s: Session = Depends(get_read_session, scope="function")) -> PredictOut:
    """Joints in the model's units and joint order; positions in the measurement (tracker) frame, model length unit.
    Optional `tau` (measured joint torques, `tau_<joint>` as in the CSV) is the load of load-driven causes."""
    c = service.get_calibration(s, calibration_id)
    positions, unit, notes = service.predict(s, c, body.joints, body.payload, body.temperature, body.timestamp,
                                             body.target, body.setup, body.tau)
    return PredictOut(positions=positions, unit=unit, notes=notes)


@router.post("/calibrations/{calibration_id}/compensate", response_model=CompensateOut,
             dependencies=[Depends(require_writer)], responses=problem_responses(401, 404, 413, 422),
             summary="Joint commands that put the tool on targets, every identified effect included")
def compensate(calibration_id: str, body: CompensateIn = Body(..., openapi_examples={
        "targets": {"summary": "one target with its nominal joint solution (spray7, mm, deg)",
                    "value": {"targets": [[-2821.34, 876.61, -16.36]],
                              "seed_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]]}},
        "program": {"summary": "a program as joints only, telescopic J6 locked",
                    "value": {"program_joints": [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]],
                              "locked_joints": ["J6"]}}}),
        s: Session = Depends(get_read_session, scope="function")) -> dict:
    """Per target, the joint command nearest the seed for which the calibrated model (effects included) puts
    the tool on the target, within the joint limits; an unreachable target is reported, not a failed batch."""
    return service.compensate(s, service.get_calibration(s, calibration_id), body)
