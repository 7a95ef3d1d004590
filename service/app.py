"""create_app(): routers, problem+json handlers, the body-size limit and the embedded dispatcher."""
from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI
from pydantic import BaseModel
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from . import problems
from .calibrations.router import router as calibrations_router
from .config import Settings
from .db import Database
from .deps import get_read_session
from .jobs.models import Job
from .jobs.router import router as jobs_router
from .limits import BodyLimitMiddleware
from .measurements.router import router as measurements_router
from .robots.router import router as robots_router

DESCRIPTION = """Robot calibration service (contract: model JSON, measurement CSV, REST API).

Flow: `POST /robots` (model) → `POST /robots/{id}/measurements` (CSV) → `POST /jobs` → poll `GET /jobs/{id}` →
`GET /calibrations/{id}` → `POST /calibrations/{id}/predict`.

Every error is an RFC 9457 `application/problem+json` document; input problems are listed in `errors`.
Writing calls need `Authorization: Bearer <token>` when the server sets `CALIB_API_TOKEN`."""


class Health(BaseModel):
    model_config = {"json_schema_extra": {"example": {"status": "ok", "database": "sqlite",
                                                      "jobs": {"queued": 0, "running": 1}, "dispatcher": True}}}
    status: str
    database: str
    jobs: dict[str, int]
    dispatcher: bool


def create_app(settings: Settings | None = None, *, dispatcher: bool | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    run_dispatcher = settings.embedded_workers if dispatcher is None else dispatcher

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        d = None
        if run_dispatcher:
            from .queue.worker import Dispatcher
            d = Dispatcher(app.state.db, settings)
            d.start()
        app.state.dispatcher = d
        try:
            yield
        finally:
            if d is not None:
                d.stop()
            app.state.db.dispose()

    app = FastAPI(title="calib", version="0.1.0", description=DESCRIPTION, lifespan=lifespan)
    app.state.settings = settings
    app.state.db = Database(settings.database_url)
    app.state.dispatcher = None
    problems.install(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_upload_bytes)
    for r in (robots_router, measurements_router, jobs_router, calibrations_router):
        app.include_router(r)

    @app.get("/health", response_model=Health, tags=["health"], summary="Liveness and queue depth")
    def health(s: Session = Depends(get_read_session, scope="function")) -> Health:
        rows = s.execute(select(Job.status, func.count()).where(Job.status.in_(["queued", "running"]))
                         .group_by(Job.status)).all()
        jobs = {"queued": 0, "running": 0} | {k: int(v) for k, v in rows}
        return Health(status="ok", database=s.get_bind().dialect.name, jobs=jobs,
                      dispatcher=app.state.dispatcher is not None)

    return app
