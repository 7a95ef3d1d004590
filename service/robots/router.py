from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends, Query, Request, Response
from starlette.routing import Match
from sqlalchemy.orm import Session

from ..db import Database
from ..deps import WriteRoute, get_db, get_read_session, get_session, require_writer
from ..problems import ProblemError, problem_responses
from . import service
from .schemas import SPRAY7_EXAMPLE, RobotOut

router = APIRouter(tags=["robots"], route_class=WriteRoute)

XML_TYPES = (b"application/xml", b"text/xml", b"application/urdf+xml")


class XmlBodyRoute(WriteRoute):
    """Matches only requests whose Content-Type is XML, so `POST /robots` with a URDF reaches its own handler
    and every JSON request the contract's route below, unchanged."""

    def matches(self, scope):
        match, child = super().matches(scope)
        if match != Match.NONE:
            ctype = dict(scope.get("headers") or []).get(b"content-type", b"").split(b";")[0].strip().lower()
            if ctype not in XML_TYPES:
                return Match.NONE, {}
        return match, child


async def _raw_body(request: Request) -> bytes:
    return await request.body()


URDF_QUERY = ("base", "targets", "length_unit", "angle_unit", "smr")
"""The URDF upload's options: any other query parameter is a 422 (a misspelt `target=` must not fall back to the
default target silently)."""


def _known_query(request: Request) -> None:
    """422 naming every query parameter the URDF upload does not take, with the nearest one it does."""
    import difflib

    errors = []
    for k in request.query_params:
        if k not in URDF_QUERY:
            near = difflib.get_close_matches(k, URDF_QUERY, n=1, cutoff=0.6)
            errors.append({"field": f"query.{k}", "value": request.query_params[k],
                           "message": f"unknown option; {f'did you mean {near[0]!r}? ' if near else ''}the URDF "
                                      f"upload takes {', '.join(URDF_QUERY)}"})
    if errors:
        raise ProblemError(422, f"{len(errors)} unknown option{'s' * (len(errors) != 1)}; nothing was stored",
                           kind="invalid-urdf", errors=errors)


def create_robot_urdf(response: Response, body: bytes = Depends(_raw_body),
                      base: str | None = Query(None, max_length=200, description="the base link (default: the "
                                               "URDF's root link)"),
                      targets: str | None = Query(None, max_length=1000, description="the measured points' links, "
                                                  "comma-separated (default: the only leaf link)"),
                      length_unit: str = Query("m", pattern="^(m|mm)$"),
                      angle_unit: str = Query("rad", pattern="^(rad|deg)$"),
                      smr: str | None = Query(None, max_length=2000, description="the nominal SMR offset of each "
                                              "target in its link's frame, metres: `x,y,z` per target, in the order "
                                              "of `targets`, separated by `;` (default: each target at its link's "
                                              "origin)"),
                      s: Session = Depends(get_session, scope="function")) -> RobotOut:
    """`Content-Type: application/xml`: the URDF joints from `base` to `targets` as contract model JSON (with its
    `urdf` extension object; calib_core.urdf: MD-H rows for one serial chain, xyz/rpy/axis rows for a tree or a
    chain with mimic joints), stored and validated like a JSON upload. The stored model's `urdf.notes` list what
    was ignored or read leniently (a fixed joint's mimic, a limit without range, a mimic of no joint) and
    `urdf.source` keeps the URDF text."""
    r = service.create_robot_from_urdf(s, body, base, targets, length_unit, angle_unit, smr)
    response.headers["Location"] = f"/robots/{r.id}"
    return RobotOut.of(r)


# registered before the JSON route of the same path: XmlBodyRoute lets every non-XML request through to it
router.add_api_route("/robots", create_robot_urdf, methods=["POST"], status_code=201, response_model=RobotOut,
                     dependencies=[Depends(require_writer), Depends(_known_query)], route_class_override=XmlBodyRoute,
                     include_in_schema=False, summary="Store a robot model given as URDF (contract section 5)")


@router.post("/robots", status_code=201, response_model=RobotOut, dependencies=[Depends(require_writer)],
             responses=problem_responses(401, 413, 422), summary="Store a robot model (contract section 1)")
def create_robot(response: Response, doc: dict[str, Any] = Body(..., openapi_examples={
        "spray7": {"summary": "7-DoF spray robot, MD-H, mm/deg", "value": SPRAY7_EXAMPLE}}),
        s: Session = Depends(get_session, scope="function")) -> RobotOut:
    """Validates the model (joint names, types, limits, units) and stores it exactly as posted.
    Every problem is listed in the 422 problem document as `{field, value, message}`.
    With `Content-Type: application/xml` the body is a URDF instead (contract section 5;
    `?base=LINK&targets=LINK[,LINK]`, optional `smr=x,y,z[;x,y,z]` (m), `length_unit=m|mm`, `angle_unit=rad|deg`),
    stored as the model JSON it converts to."""
    r = service.create_robot(s, doc)
    response.headers["Location"] = f"/robots/{r.id}"
    return RobotOut.of(r)


PAGE_HEADERS = {
    "X-Total-Count": {"description": "how many robots are stored in all", "schema": {"type": "integer"}},
    "Link": {"description": 'RFC 8288 links to the `rel="next"` and `rel="prev"` pages, when there are',
             "schema": {"type": "string"}, "example": '</robots?limit=100&offset=100>; rel="next"'},
}


@router.get("/robots", response_model=list[RobotOut], summary="The stored robot models, oldest first, one page",
            responses={200: {"description": "one page of the stored models", "headers": PAGE_HEADERS}})
def list_robots(request: Request, response: Response,
                limit: int = Query(100, ge=1, le=1000, description="page size (a page also ends once its models' "
                                   "JSON passes 8 MiB; follow the `Link` header)"),
                offset: int = Query(0, ge=0, le=2**31, description="how many robots to skip"),
                s: Session = Depends(get_read_session, scope="function")) -> list[RobotOut]:
    """The body is the list of models (contract section 3); the `X-Total-Count` header gives the total and
    `Link` the next and previous pages."""
    robots = service.list_robots(s, limit, offset)
    total = service.count_robots(s)
    response.headers["X-Total-Count"] = str(total)
    links = []
    if offset + len(robots) < total:
        links.append(f'<{request.url.path}?limit={limit}&offset={offset + len(robots)}>; rel="next"')
    if offset > 0:
        links.append(f'<{request.url.path}?limit={limit}&offset={max(0, offset - limit)}>; rel="prev"')
    if links:
        response.headers["Link"] = ", ".join(links)
    return [RobotOut.of(r) for r in robots]


@router.get("/robots/{robot_id}", response_model=RobotOut, responses=problem_responses(404),
            summary="One stored robot model")
def get_robot(robot_id: str, s: Session = Depends(get_read_session, scope="function")) -> RobotOut:
    return RobotOut.of(service.get_robot(s, robot_id))


DELETE_DOC = """Deletes the robot with everything made from it: its measurement sets, their finished jobs, the
calibrations made from them and their plots (the answers of `GET /calibrations/{id}`, predict, compensate and the
reports of those calibrations are gone too: export what you keep first, e.g. `GET /calibrations/{id}/model`).
`409` (nothing deleted) while a queued or running job uses one of its measurement sets: the problem document's
`jobs` lists them; cancel them (`POST /jobs/{id}/cancel`) or wait, then delete again. `404` when there is no such
robot (a second DELETE)."""


@router.delete("/robots/{robot_id}", status_code=204, response_class=Response, dependencies=[Depends(require_writer)],
               responses=problem_responses(401, 404, 409), summary="Delete a robot and everything made from it",
               description=DELETE_DOC)
def delete_robot(robot_id: str, db: Database = Depends(get_db)) -> Response:
    service.delete_robot(db, robot_id)
    return Response(status_code=204)
