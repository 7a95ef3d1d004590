"""RFC 9457 problem documents: every error the API returns is application/problem+json."""
from __future__ import annotations

import logging
import math
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("service")
PROBLEM = "application/problem+json"
TYPE_BASE = "https://calib.example/problems/"


class ProblemError(Exception):
    """Raised by the service layer; turned into a problem document by the app's handler."""

    def __init__(self, status: int, detail: str, *, kind: str | None = None, title: str | None = None,
                 errors: list[dict] | None = None, headers: dict | None = None, **extra: Any):
        super().__init__(detail)
        self.status, self.detail, self.kind, self.title = status, detail, kind, title
        self.errors, self.headers, self.extra = errors, headers, extra


def not_found(what: str, id_: str) -> ProblemError:
    return ProblemError(404, f"{what} {id_!r} does not exist", kind="not-found")


class ProblemDoc(BaseModel):
    """RFC 9457 problem details. `errors` lists every problem found (CSV: row/column/value/message;
    model: field/value/message; request validation: field/value/message)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"example": {
        "type": TYPE_BASE + "invalid-csv", "title": "Unprocessable Content", "status": 422,
        "detail": "the CSV has 1 error; nothing was stored", "instance": "/robots/3f.../measurements",
        "errors": [{"row": 7, "column": "J3", "value": "95.2", "message": "outside the joint limits [-80, 80] deg"}]}})
    type: str = "about:blank"
    title: str
    status: int
    detail: str | None = None
    instance: str | None = None
    errors: list[dict[str, Any]] | None = Field(default=None)


def problem_responses(*codes: int) -> dict:
    """OpenAPI `responses` entries for problem documents (content filled in by `problem_openapi`)."""
    return {c: {"description": HTTPStatus(c).phrase} for c in codes}


def problem_openapi(app: FastAPI) -> None:
    """Document every error response as application/problem+json with the ProblemDoc schema, and 422 on every
    operation that takes input (FastAPI's default 422 schema is replaced: it never answers with it)."""
    base_openapi = app.openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        spec = base_openapi()
        comps = spec.setdefault("components", {}).setdefault("schemas", {})
        comps.pop("HTTPValidationError", None)
        comps.pop("ValidationError", None)
        comps["ProblemDoc"] = ProblemDoc.model_json_schema(ref_template="#/components/schemas/{model}")
        ref = {"$ref": "#/components/schemas/ProblemDoc"}
        example = ProblemDoc.model_config["json_schema_extra"]["example"]
        for path, ops in spec.get("paths", {}).items():
            for method, op in ops.items():
                responses = op.setdefault("responses", {})
                if op.get("parameters") or op.get("requestBody"):
                    responses.setdefault("422", {"description": HTTPStatus(422).phrase})
                for code, resp in responses.items():
                    if code[0] in "45":
                        ex = example if code == "422" else {"type": "about:blank", "title": HTTPStatus(int(code)).phrase,
                                                            "status": int(code), "detail": "...", "instance": path}
                        resp["content"] = {PROBLEM: {"schema": ref, "example": ex}}
                        if resp.get("description") == "Validation Error":
                            resp["description"] = HTTPStatus(422).phrase
        app.openapi_schema = spec
        return spec

    app.openapi = openapi


def json_safe(v: Any) -> Any:
    """Echoed input may hold NaN, inf or bytes, which JSON cannot carry: make it printable."""
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, (bytes, bytearray)):
        return repr(bytes(v[:64]))
    if isinstance(v, dict):
        return {str(k): json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_safe(x) for x in v]
    if v is None or isinstance(v, (str, int, float, bool)):
        return v
    return str(v)


def problem_response(request: Request | None, status: int, detail: str | None, *, kind: str | None = None,
                     title: str | None = None, errors: list | None = None, headers: dict | None = None,
                     **extra: Any) -> JSONResponse:
    body: dict[str, Any] = {
        "type": TYPE_BASE + kind if kind else "about:blank",
        "title": title or HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
    }
    if request is not None:
        body["instance"] = request.url.path
    if errors is not None:
        body["errors"] = json_safe(errors)
    body.update(json_safe(extra))
    return JSONResponse(body, status_code=status, media_type=PROBLEM, headers=headers)


def _loc(loc) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header"):
        where = parts[0]
        rest = parts[1:]
        return where + ("." + ".".join(rest) if rest else "")
    return ".".join(parts)


def install(app: FastAPI) -> None:
    problem_openapi(app)

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        return problem_response(request, exc.status, exc.detail, kind=exc.kind, title=exc.title,
                                errors=exc.errors, headers=exc.headers, **exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = [{"field": _loc(e.get("loc", ())), "value": e.get("input"), "message": e.get("msg", "invalid")}
                  for e in exc.errors()]
        n = len(errors)
        return problem_response(request, 422, f"the request has {n} invalid field{'s' * (n != 1)}",
                                kind="validation", errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        kind = {404: "not-found", 405: "method-not-allowed", 413: "too-large", 401: "unauthorized"}.get(exc.status_code)
        return problem_response(request, exc.status_code, str(exc.detail), kind=kind, headers=exc.headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(request, 500, "internal error; it was logged", kind="internal")


def get_or_404(s, model_cls, key: str, what: str):
    """The row of model_cls with primary key `key`, or a 404 problem naming `what`."""
    row = s.get(model_cls, key)
    if row is None:
        raise not_found(what, key)
    return row
