"""FastAPI dependencies: settings, a session per request (one transaction), bearer-token auth for writes."""
from __future__ import annotations

import hmac
from typing import Iterator

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from .config import Settings
from .db import Database
from .problems import ProblemError

bearer = HTTPBearer(auto_error=False, description="Needed on writing calls when the server sets CALIB_API_TOKEN.")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_db(request: Request) -> Database:
    return request.app.state.db


def get_session(db: Database = Depends(get_db)) -> Iterator[Session]:
    """One write transaction per request. Routes use it with scope="function", so the commit happens
    before the response is sent: a 201/202 is only ever answered for data that is durably stored."""
    with db.session() as s:
        yield s


def get_read_session(db: Database = Depends(get_db)) -> Iterator[Session]:
    with db.read_session() as s:
        yield s


def require_writer(settings: Settings = Depends(get_settings),
                   cred: HTTPAuthorizationCredentials | None = Depends(bearer)) -> None:
    if settings.api_token is None:
        return
    if cred is None or not hmac.compare_digest(cred.credentials.encode(), settings.api_token.encode()):
        raise ProblemError(401, "this call needs 'Authorization: Bearer <token>' (CALIB_API_TOKEN)",
                           kind="unauthorized", headers={"WWW-Authenticate": "Bearer"})
