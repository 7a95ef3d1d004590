"""`calib serve | worker | db upgrade | demo` (contract section 4)."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from .config import Settings

ROOT = Path(__file__).resolve().parent.parent


def alembic_config(url: str):
    from alembic.config import Config

    cfg = Config(str(ROOT / "alembic.ini")) if (ROOT / "alembic.ini").exists() else Config()
    cfg.set_main_option("script_location", str(ROOT / "migrations"))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    cfg.attributes["configure_logger"] = False
    return cfg


def db_upgrade(url: str, revision: str = "head") -> None:
    from alembic import command

    command.upgrade(alembic_config(url), revision)


def _logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def cmd_serve(args) -> int:
    import uvicorn

    from .app import create_app

    settings = Settings.from_env()
    if settings.is_sqlite:  # the embedded default: apply migrations on start
        db_upgrade(settings.database_url)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.log_level.lower(),
                timeout_graceful_shutdown=10)
    return 0


def cmd_worker(args) -> int:
    from .db import Database
    from .queue.worker import Worker

    settings = Settings.from_env()
    if args.concurrency:
        from dataclasses import replace
        settings = replace(settings, worker_concurrency=args.concurrency)
    db = Database(settings.database_url)
    w = Worker(db, settings)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: w.stop())
    print(f"calib worker {w.id} on {db.engine.url.render_as_string(hide_password=True)}", flush=True)
    w.run()
    db.dispose()
    return 0


def cmd_db(args) -> int:
    settings = Settings.from_env()
    db_upgrade(settings.database_url, args.revision)
    print(f"database at {args.revision}")
    return 0


def cmd_demo(args) -> int:
    print("calib demo: not yet implemented", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="calib", description="Robot calibration service")
    p.add_argument("--log-level", default="INFO")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve", help="API plus embedded workers")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.set_defaults(fn=cmd_serve)
    w = sub.add_parser("worker", help="a stand-alone worker (scale-out)")
    w.add_argument("--concurrency", type=int, default=0, help="pool processes (default CALIB_WORKER_CONCURRENCY)")
    w.set_defaults(fn=cmd_worker)
    d = sub.add_parser("db", help="database maintenance")
    dsub = d.add_subparsers(dest="db_cmd", required=True)
    up = dsub.add_parser("upgrade", help="apply migrations")
    up.add_argument("revision", nargs="?", default="head")
    up.set_defaults(fn=cmd_db)
    demo = sub.add_parser("demo", help="the whole story on bundled example data (not yet implemented)")
    demo.set_defaults(fn=cmd_demo)
    args = p.parse_args(argv)
    _logging(args.log_level)
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
