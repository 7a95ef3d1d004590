"""RFC 9457 problem documents: every error the API returns is application/problem+json."""
from __future__ import annotations

import logging
import math
import re
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


MAX_ERRORS = 50
"""A problem document lists at most this many errors; `error_count` gives the total, `errors_truncated` says so."""
MAX_VALUE_CHARS = 200
"""Echoed input (a value, a column name, a message) is cut to about this many characters."""
MAX_MESSAGE_CHARS = 1000
"""A message or detail (the service's own words, which may quote input) is cut to this many characters."""
MAX_VALUE_DEPTH = 4
MAX_VALUE_ITEMS = 10


def json_safe(v: Any, limit: int = MAX_VALUE_CHARS) -> Any:
    """Echoed input may hold NaN, inf, bytes, huge strings or deep nesting, which a response must not carry
    as is: make it printable and bounded (about `limit` characters per value, a few levels deep)."""
    return _bounded(v, 0, [limit])


def encodable(text: str) -> str:
    """`text` as UTF-8 can carry it: a lone surrogate (which JSON's `\\ud800` escapes can put into a string)
    written as the escape it came from (`\\ud800`), so an echo of it never breaks the answer."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def encodable_doc(doc: Any) -> Any:
    """A parsed JSON document with every string (value or key) made `encodable`; the document itself when it needs
    nothing (the usual case: one C-speed dump finds no surrogate escape). For models stored before lone surrogates
    were refused (issue 33), so `GET /robots` can still answer them."""
    import json

    if not LONE_SURROGATE_ESCAPE.search(json.dumps(doc).encode("ascii")):
        return doc

    def fix(v: Any) -> Any:
        if isinstance(v, str):
            return encodable(v)
        if isinstance(v, dict):
            return {encodable(str(k)): fix(x) for k, x in v.items()}
        if isinstance(v, list):
            return [fix(x) for x in v]
        return v

    return fix(doc)


def _bounded(v: Any, depth: int, budget: list[int]) -> Any:
    """v made JSON-safe within budget[0] characters (shared by everything inside one value)."""
    if isinstance(v, float) and not math.isfinite(v):
        v = str(v)
    elif isinstance(v, (bytes, bytearray)):
        v = repr(bytes(v[:64]))
    if isinstance(v, str):
        v = encodable(v)
        room = max(budget[0], 16)
        budget[0] -= min(len(v), room)
        return v if len(v) <= room else v[:room] + f"... ({len(v)} characters)"
    if v is None or isinstance(v, (int, float, bool)):
        budget[0] -= 8
        return v
    if isinstance(v, (dict, list, tuple)):
        n = len(v)
        if depth >= MAX_VALUE_DEPTH or budget[0] <= 0:
            return f"({'an object' if isinstance(v, dict) else 'a list'} of {n} item{'s' * (n != 1)}, not shown)"
        items = list(v.items())[:MAX_VALUE_ITEMS] if isinstance(v, dict) else list(v[:MAX_VALUE_ITEMS])
        out: Any = {} if isinstance(v, dict) else []
        shown = 0
        for item in items:
            if budget[0] <= 0:
                break
            if isinstance(v, dict):
                k, x = item
                key = encodable(str(k)[:64])
                budget[0] -= len(key)
                out[key] = _bounded(x, depth + 1, budget)
            else:
                out.append(_bounded(item, depth + 1, budget))
            shown += 1
        if n > shown:
            if isinstance(out, dict):
                out["..."] = f"{n - shown} more"
            else:
                out.append(f"... {n - shown} more")
        return out
    return _bounded(str(v), depth, budget)


def cap_errors(errors: list | None, total: int | None = None) -> tuple[list | None, dict]:
    """At most MAX_ERRORS bounded errors, and the fields that say how many there were."""
    if errors is None:
        return None, {}
    total = len(errors) if total is None else max(total, len(errors))
    shown = []
    for e in errors[:MAX_ERRORS]:
        shown.append({encodable(str(k)[:64]): json_safe(x, MAX_MESSAGE_CHARS if k == "message" else MAX_VALUE_CHARS)
                      for k, x in e.items()} if isinstance(e, dict) else json_safe(e))
    return shown, {"error_count": total, "errors_truncated": total > len(shown)}


def problem_response(request: Request | None, status: int, detail: str | None, *, kind: str | None = None,
                     title: str | None = None, errors: list | None = None, headers: dict | None = None,
                     error_count: int | None = None, **extra: Any) -> JSONResponse:
    """`errors` is capped at MAX_ERRORS entries of bounded size; `error_count` (the total, default the length
    of `errors`) and `errors_truncated` are added whenever errors are given."""
    body: dict[str, Any] = {
        "type": TYPE_BASE + kind if kind else "about:blank",
        "title": title or HTTPStatus(status).phrase,
        "status": status,
        "detail": None if detail is None else json_safe(str(detail), MAX_MESSAGE_CHARS),
    }
    if request is not None:
        body["instance"] = json_safe(request.url.path)
    shown, counts = cap_errors(errors, error_count)
    if shown is not None:
        body["errors"] = shown
    body.update({encodable(str(k)): json_safe(v, MAX_MESSAGE_CHARS) for k, v in extra.items()})
    body.update(counts)
    return JSONResponse(body, status_code=status, media_type=PROBLEM, headers=headers)


def _plain(e: dict) -> str:
    """pydantic's message in plain words (JSON decoding errors name the position, not Python internals)."""
    msg = str(e.get("msg", "invalid"))
    if e.get("type") == "json_invalid":
        ctx = e.get("ctx") or {}
        return f"the body is not valid JSON ({ctx.get('error', 'syntax error')})"
    return msg


def _loc(loc) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header"):
        where = parts[0]
        rest = parts[1:]
        return where + ("." + ".".join(rest) if rest else "")
    return ".".join(parts)


LONE_SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89a-fA-F][0-9a-fA-F]{2}")
"""A JSON escape of a UTF-16 surrogate (`\\ud800`..`\\udfff`) in a request body: only a body with one can hold a
string UTF-8 cannot encode (a pair makes one character; a lone one stays a surrogate)."""


def lone_surrogates(doc: Any, path: str = "body", limit: int = MAX_ERRORS) -> list[dict]:
    """Every string (value or key) of a parsed JSON document that holds a lone surrogate, as `{field, value,
    message}` errors (value: the text with the surrogate written as its escape), at most `limit`."""
    out: list[dict] = []
    stack: list[tuple[str, Any]] = [(path, doc)]
    while stack and len(out) < limit:
        where, v = stack.pop()
        if isinstance(v, str):
            if encodable(v) is not v:
                out.append({"field": where, "value": encodable(v), "message": _SURROGATE_MESSAGE})
        elif isinstance(v, dict):
            for k, x in reversed(list(v.items())):
                key = str(k)
                if encodable(key) is not key:
                    out.append({"field": where, "value": encodable(key), "message": "a key: " + _SURROGATE_MESSAGE})
                stack.append((f"{where}.{encodable(key)}", x))
        elif isinstance(v, list):
            stack.extend((f"{where}[{k}]", x) for k, x in reversed(list(enumerate(v))))
    return out[:limit]


_SURROGATE_MESSAGE = ("the text holds a lone UTF-16 surrogate (an escape \\ud800..\\udfff without its pair), which is "
                      "no character and cannot be stored or answered as UTF-8: send the text as UTF-8, or the escape "
                      "with its pair")


async def no_lone_surrogates(request: Request) -> None:
    """App-wide dependency: a JSON body with a string UTF-8 cannot encode (a lone surrogate) is a 422 naming the
    field, before any route stores or echoes it (issue 33: a robot was stored with one and every later
    `GET /robots` answered 500). The body FastAPI already read and parsed is reused; it is only walked when its
    bytes hold a surrogate escape at all."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if request.method not in ("POST", "PUT", "PATCH") or not (ctype == "application/json" or ctype.endswith("+json")):
        return
    body = await request.body()
    if not LONE_SURROGATE_ESCAPE.search(body):
        return
    try:
        doc = await request.json()
    except ValueError:
        return  # not JSON: FastAPI's own answer
    errors = lone_surrogates(doc)
    if errors:
        n = len(errors)
        raise ProblemError(422, f"the request has {n} text{'s' * (n != 1)} that cannot be encoded as UTF-8 (a lone "
                           "surrogate escape); nothing was stored", kind="validation", errors=errors)


def install(app: FastAPI) -> None:
    problem_openapi(app)

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        return problem_response(request, exc.status, exc.detail, kind=exc.kind, title=exc.title,
                                errors=exc.errors, headers=exc.headers, **exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        raw = exc.errors()
        n = len(raw)
        errors = [{"field": _loc(e.get("loc", ())), "value": e.get("input"), "message": _plain(e)}
                  for e in raw[:MAX_ERRORS]]
        more = f" (the first {MAX_ERRORS} are listed)" if n > MAX_ERRORS else ""
        return problem_response(request, 422, f"the request has {n} invalid field{'s' * (n != 1)}{more}",
                                kind="validation", errors=errors, error_count=n)

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
    if not isinstance(key, str) or len(key) > 64 or "\x00" in key:  # ids are 36-character UUIDs
        raise not_found(what, key[:64] + "..." if isinstance(key, str) and len(key) > 64 else key)
    row = s.get(model_cls, key)
    if row is None:
        raise not_found(what, key)
    return row
