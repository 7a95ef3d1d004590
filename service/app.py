"""create_app(): routers, problem+json handlers, the HTTP edge (token, body-size limit, HEAD, 500s, database
faults as 503), offline docs, /health and the embedded dispatcher."""
from __future__ import annotations

import logging
import sys
import time
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
import anyio.to_thread
from fastapi import Depends, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from sqlalchemy import func, select, text
from sqlalchemy.exc import InterfaceError, OperationalError, SQLAlchemyError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError

from . import problems
from .calibrations.compute import COMPUTERS, ROOM_PER_PROCESS
from .calibrations.router import router as calibrations_router
from .config import Settings, check_token_setting
from .db import Database, DatabaseUnavailable
from .deps import TokenAuthMiddleware
from .jobs.models import Job
from .jobs.router import router as jobs_router
from .limits import (MAX_PREDICT_BYTES, MAX_PREDICT_ROWS, BatchLimitMiddleware, BodyLimitMiddleware, HeadMiddleware,
                     InternalErrorMiddleware)
from .measurements.router import router as measurements_router
from .measurements.service import PARSERS
from .plans.pool import PLANNERS
from .plans.router import router as plans_router
from .robots.router import router as robots_router

DESCRIPTION = """Robot calibration service (contract: model JSON, measurement CSV, REST API).

Flow: `POST /robots` (model) → `POST /robots/{id}/measurements` (CSV) → `POST /jobs` → poll `GET /jobs/{id}` →
`GET /calibrations/{id}` → `POST /calibrations/{id}/predict`.

Every error is an RFC 9457 `application/problem+json` document; input problems are listed in `errors`.
When the server sets `CALIB_API_TOKEN`, every call but `GET /health` (reads, reports, these docs included) needs
`Authorization: Bearer <token>` (or HTTP Basic with the token as password, for a browser).
A database that is down, read-only or gone answers `503` with `Retry-After`; `GET /health` says `unavailable`.
`GET /robots` is paged (`limit`, `offset`; `X-Total-Count` and `Link: rel="next"` headers).
""" + (f"`predict` and `compensate` take at most {MAX_PREDICT_ROWS} rows (poses, targets) and "
       f"{MAX_PREDICT_BYTES // 2**20} MiB per request: more is `413`, naming the field, its count and the maximum; "
       "send the rest in further requests.")

log = logging.getLogger("service")
RETRY_AFTER_S = 5
HEALTH_THREADS = 2
"""/health runs in threads of its own (at most this many at once), not in the routes' shared pool."""
DOCS_ASSETS = "/docs-assets"


def docs_assets_dir() -> Path:
    """Swagger UI and ReDoc (JS, CSS, favicon) as shipped by the fastapi-offline package: no CDN needed."""
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


class Health(BaseModel):
    model_config = {"json_schema_extra": {"example": {"status": "ok", "database": "sqlite",
                                                      "jobs": {"queued": 0, "running": 1}, "dispatcher": True}}}
    status: str = Field(description='"ok", or "unavailable" (answered with 503) when the database cannot be used')
    database: str
    jobs: dict[str, int] = Field(description="queued and running jobs (empty when the database is unreachable)")
    dispatcher: bool
    detail: str | None = Field(None, description="what is wrong, when the status is not ok")


def create_app(settings: Settings | None = None, *, dispatcher: bool | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    check_token_setting(settings)  # CALIB_API_TOKEN set but empty: refuse to start (config.py)
    run_dispatcher = settings.embedded_workers if dispatcher is None else dispatcher

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # the sync routes' shared thread pool (anyio's default limiter, 40): under load its threads are CSV
        # parsing and validation, Python holding the GIL; the more at once, the longer the event loop and
        # /health wait for the GIL between two steps, for no more throughput (one process: one core of Python)
        anyio.to_thread.current_default_thread_limiter().total_tokens = settings.route_threads
        # how long a thread holding the GIL keeps it while another waits (CPython's default 5 ms): the event loop
        # and /health take a dozen GIL turns per request, each up to one interval behind the route threads
        sys.setswitchinterval(settings.switch_interval_ms / 1000)
        import asyncio

        t_start = time.monotonic()
        warming = []  # the lanes' processes (service/lanes.py), started alongside the job processes and awaited as
        # long as they are (CALIB_WARMUP_TIMEOUT_S in all): on a busy machine the server serves meanwhile, and a call
        # that comes before its process is ready waits for it (not counted in its time bound)
        if settings.parse_processes > 0:  # the CSV checks (service/measurements)
            warming.append(asyncio.to_thread(PARSERS.warm, settings.parse_processes, settings.parse_timeout_s,
                                             settings.parse_room_bytes))
        if settings.plan_processes > 0:  # plans (service/plans)
            warming.append(asyncio.to_thread(PLANNERS.warm, settings.plan_processes, settings.plan_room,
                                             settings.plan_timeout_s))
        if settings.compute_processes > 0:  # predict and compensate (service/calibrations/compute.py)
            warming.append(asyncio.to_thread(COMPUTERS.warm, settings.compute_processes,
                                             ROOM_PER_PROCESS * settings.compute_processes,
                                             settings.compute_timeout_s))
        warming = [asyncio.ensure_future(w) for w in warming]
        d = None
        if run_dispatcher:
            from .queue.worker import Dispatcher
            d = Dispatcher(app.state.db, settings)
            d.start()
            if settings.warm_pool:  # serve once the job processes are warm: the first job is as fast as any
                if not await asyncio.to_thread(d.wait_ready, settings.warmup_timeout_s):
                    log.warning("the job processes were not warm after %.0f s; serving anyway",
                                settings.warmup_timeout_s)
        if warming:
            left = settings.warmup_timeout_s - (time.monotonic() - t_start)
            _, late = await asyncio.wait(warming, timeout=max(1.0, left))
            if late:
                log.warning("%d lane(s) of processes were not warm after %.0f s; serving anyway", len(late),
                            settings.warmup_timeout_s)
        app.state.dispatcher = d
        try:
            yield
        finally:
            if d is not None:
                d.stop()
            PARSERS.shutdown()
            PLANNERS.shutdown()
            COMPUTERS.shutdown()
            app.state.db.dispose()

    app = FastAPI(title="calib", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None,  # served below from local assets
                  dependencies=[Depends(problems.no_lone_surrogates)])  # issue 33: 422, never a 500 after storing
    app.state.settings = settings
    app.state.db = Database(settings.database_url)
    app.state.dispatcher = None
    problems.install(app)
    _document_health(app)

    async def database_unavailable(request: Request, exc: Exception):
        text = str(getattr(exc, "orig", None) or exc).lower()
        read_only = "readonly" in text or "read-only" in text or app.state.db.read_only
        log.warning("database unavailable on %s %s: %s", request.method, request.url.path,
                    str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        detail = ("the database is read-only: nothing can be stored now; try again later" if read_only else
                  "the database is unavailable (nothing was read or stored); try again later")
        return problems.problem_response(request, 503, detail, kind="database-unavailable",
                                         headers={"Retry-After": str(RETRY_AFTER_S)})

    for exc_class in (OperationalError, InterfaceError, PoolTimeoutError):
        app.add_exception_handler(exc_class, database_unavailable)
    # the edge, innermost first (each add wraps the previous): predict/compensate size, token, 500s, body limit, HEAD
    app.add_middleware(BatchLimitMiddleware)
    app.add_middleware(TokenAuthMiddleware, token=settings.api_token, open_paths=("/health",))
    app.add_middleware(InternalErrorMiddleware, handler=app.exception_handlers[Exception])
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_upload_bytes)
    app.add_middleware(HeadMiddleware)
    for r in (robots_router, measurements_router, jobs_router, calibrations_router):
        app.include_router(r)
    app.include_router(plans_router)
    _install_docs(app)

    health_threads = anyio.CapacityLimiter(HEALTH_THREADS)

    @app.get("/health", response_model=Health, tags=["health"], summary="Liveness, database and queue depth",
             responses={503: {"description": "the database is unreachable, gone or read-only"}})
    async def health():
        """`ok`, or `unavailable` with 503 and `Retry-After`: the database does not answer, or (SQLite) its file
        is no longer where it was opened or cannot be written. Never needs the API token."""
        return await anyio.to_thread.run_sync(check_health, limiter=health_threads)

    def check_health():
        """/health's work, in a thread of its own limiter: the routes' shared thread pool (CALIB_ROUTE_THREADS)
        can be all busy under load, and /health must not queue behind them (issue 10, the red team's load)."""
        db: Database = app.state.db
        trouble = db.problems()
        jobs: dict[str, int] = {}
        try:
            with db.read_session() as s:
                rows = s.execute(select(Job.status, func.count()).where(Job.status.in_(["queued", "running"]))
                                 .group_by(Job.status)).all()
                if db.engine.dialect.name == "postgresql" and s.execute(text("SHOW transaction_read_only")).scalar() == "on":
                    trouble.append("the PostgreSQL database is read-only (a standby, or default_transaction_read_only "
                                   "on): writes are refused")
            jobs = {"queued": 0, "running": 0} | {k: int(v) for k, v in rows}
        except SQLAlchemyError as exc:
            reason = exc.reason if isinstance(exc, DatabaseUnavailable) else "the database does not answer"
            if reason not in trouble:
                trouble.append(reason)
            log.warning("health: %s", str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        out = Health(status="unavailable" if trouble else "ok", database=db.engine.dialect.name, jobs=jobs,
                     dispatcher=app.state.dispatcher is not None, detail="; ".join(trouble) or None)
        if trouble:
            return JSONResponse(out.model_dump(), status_code=503, headers={"Retry-After": str(RETRY_AFTER_S)})
        return out

    return app


def _install_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc from the package's own copies of their JS and CSS: they work offline."""
    app.mount(DOCS_ASSETS, StaticFiles(directory=docs_assets_dir()), name="docs-assets")

    def root(request: Request) -> str:
        return request.scope.get("root_path", "").rstrip("/")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        r = root(request)
        return get_swagger_ui_html(openapi_url=r + app.openapi_url, title="calib - API docs",
                                   swagger_js_url=f"{r}{DOCS_ASSETS}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{r}{DOCS_ASSETS}/swagger-ui.css",
                                   swagger_favicon_url=f"{r}{DOCS_ASSETS}/favicon.png",
                                   oauth2_redirect_url=r + "/docs/oauth2-redirect",
                                   swagger_ui_parameters={"validatorUrl": None})  # no call to an online validator

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def redoc(request: Request) -> HTMLResponse:
        r = root(request)
        return get_redoc_html(openapi_url=r + app.openapi_url, title="calib - API reference",
                              redoc_js_url=f"{r}{DOCS_ASSETS}/redoc.standalone.js",
                              redoc_favicon_url=f"{r}{DOCS_ASSETS}/favicon.png", with_google_fonts=False)


def _document_health(app: FastAPI) -> None:
    """/health answers 503 with its own JSON (status "unavailable"), not a problem document: say so in the
    OpenAPI (problems.problem_openapi marks every 5xx as problem+json)."""
    inner = app.openapi

    def openapi() -> dict:
        spec = inner()
        op = spec.get("paths", {}).get("/health", {}).get("get")
        if op and "503" in op.get("responses", {}):
            op["responses"]["503"]["content"] = {"application/json": {
                "schema": {"$ref": "#/components/schemas/Health"},
                "example": {"status": "unavailable", "database": "sqlite", "jobs": {}, "dispatcher": True,
                            "detail": "the SQLite database file /srv/calib/calib.db is gone (deleted, or its "
                                      "directory was); nothing is read or written until it is restored"}}}
        return spec

    app.openapi = openapi
