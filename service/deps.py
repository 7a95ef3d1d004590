"""FastAPI dependencies: settings, a session per request (one transaction), and the API token.

Auth (CALIB_API_TOKEN): unset, nothing is asked (a laptop, a closed cell network). Set, every call but
`GET /health` needs it (reads, reports, plots, jobs, the docs and /openapi.json too), enforced for the whole
app by `TokenAuthMiddleware`; `require_writer` stays on the writing routes as a second check and to document
the scheme in the OpenAPI. The token goes as `Authorization: Bearer <token>`, or as the password of HTTP
Basic (any user name) so a browser can open /docs and the reports. Tokens are compared as UTF-8 bytes on both
sides, in constant time: a non-ASCII token works when the client sends it UTF-8 encoded. Set but empty (or
only white space, or with white space around it, which no HTTP header can carry) is a misconfiguration:
`config.check_token_setting` refuses to start (before any import or process) rather than silently run without auth.
"""
from __future__ import annotations

import base64
import binascii
import functools
import hashlib
import hmac
import inspect
from typing import Any, Callable, Iterable, Iterator

from fastapi import Depends, Request
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session
from starlette.types import ASGIApp, Receive, Scope, Send

from .config import Settings
from .db import Database
from .limits import header
from .problems import ProblemError, problem_response

bearer = HTTPBearer(auto_error=False, description="Needed on every call but /health when the server sets "
                    "CALIB_API_TOKEN (HTTP Basic with the token as password works too).")

AUTH_CHALLENGE = 'Bearer realm="calib", Basic realm="calib", charset="UTF-8"'
AUTH_DETAIL = ("this service needs 'Authorization: Bearer <token>' (CALIB_API_TOKEN) on every call but /health; "
               "a browser may give the token as the password of HTTP Basic")


def _digest(b: bytes) -> bytes:
    return hashlib.sha256(b).digest()


def token_matches(authorization: bytes | None, token: str) -> bool:
    """Whether a raw Authorization header value (bytes as sent) carries `token`: `Bearer <token>` or HTTP Basic
    with the token as password. Compared as UTF-8 bytes, in constant time (digests: no length leak either)."""
    if not authorization:
        return False
    scheme, _, rest = authorization.strip().partition(b" ")
    rest, scheme = rest.strip(), scheme.lower()
    if scheme == b"bearer":
        given = rest
    elif scheme == b"basic":
        try:
            given = base64.b64decode(rest, validate=True).partition(b":")[2]
        except (binascii.Error, ValueError):
            return False
    else:
        return False
    return hmac.compare_digest(_digest(given), _digest(token.encode("utf-8")))


def unauthorized(request: Request | None):
    return problem_response(request, 401, AUTH_DETAIL, kind="unauthorized",
                            headers={"WWW-Authenticate": AUTH_CHALLENGE})


class TokenAuthMiddleware:
    """Every HTTP call needs the token, except the paths in `open_paths` (GET/HEAD /health)."""

    def __init__(self, app: ASGIApp, token: str | None, open_paths: Iterable[str] = ("/health",)):
        self.app, self.token, self.open_paths = app, token, frozenset(open_paths)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (self.token is None or scope["type"] != "http" or scope["path"] in self.open_paths
                or token_matches(header(scope, b"authorization"), self.token)):
            await self.app(scope, receive, send)
            return
        await unauthorized(Request(scope))(scope, receive, send)


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_db(request: Request) -> Database:
    return request.app.state.db


_COMMIT_IN_ENDPOINT = "calib_commit_in_endpoint"  # in Session.info: get_session's, committed by WriteRoute


def get_session(db: Database = Depends(get_db)) -> Iterator[Session]:
    """One write transaction per request. Routes use it with scope="function", so the commit happens
    before the response is sent: a 201/202 is only ever answered for data that is durably stored.

    On a `WriteRoute` the commit happens in the endpoint's own thread as soon as it returns, not at this
    dependency's exit: FastAPI validates a sync route's response model in the shared thread pool before it
    closes function-scoped dependencies, so a commit left to this exit holds the SQLite write lock (BEGIN
    IMMEDIATE) while waiting for a pool thread; under load every pool thread can be a writer waiting for that
    lock (busy timeout 30 s): no thread ever frees up, and the waiters end in 503s (the red-team load,
    benchmarks/bench_redteam.py). Errors still roll back here."""
    with db.session() as s:
        s.info[_COMMIT_IN_ENDPOINT] = True
        yield s


def _committing(endpoint: Callable[..., Any]) -> Callable[..., Any]:
    """`endpoint`, committing its `get_session` session in the same thread once it has returned."""
    if inspect.iscoroutinefunction(endpoint):
        return endpoint

    @functools.wraps(endpoint)  # FastAPI reads the signature (and annotations) of the wrapped endpoint
    def call(**kwargs: Any) -> Any:
        out = endpoint(**kwargs)
        for v in kwargs.values():
            if isinstance(v, Session) and v.info.get(_COMMIT_IN_ENDPOINT):
                v.commit()
        return out

    return call


class WriteRoute(APIRoute):
    """The route class of routers whose routes write through `get_session`: the session is committed right
    after the endpoint returns, in its thread (see get_session)."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        super().__init__(path, _committing(endpoint), **kwargs)


def get_read_session(db: Database = Depends(get_db)) -> Iterator[Session]:
    with db.read_session() as s:
        yield s


def require_writer(request: Request, settings: Settings = Depends(get_settings),
                   cred: HTTPAuthorizationCredentials | None = Depends(bearer)) -> None:
    """The writing routes' own check (TokenAuthMiddleware already gates every call); documents the scheme."""
    if settings.api_token is None:
        return
    if not token_matches(header(request.scope, b"authorization"), settings.api_token):
        raise ProblemError(401, AUTH_DETAIL, kind="unauthorized", headers={"WWW-Authenticate": AUTH_CHALLENGE})
