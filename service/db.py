"""Engine, sessions, SQLite pragmas (WAL, busy timeout, BEGIN IMMEDIATE), the declarative base, and the guard
that turns a database that went away into `DatabaseUnavailable` (answered 503, never a silent loss).

SQLite: the file is stat-ed on every connection checkout and before every commit. If it is gone (its
directory deleted, the file removed) or replaced by another file, every session fails with
`DatabaseUnavailable`: a pooled connection would otherwise keep writing into the unlinked file (201/202 for
data lost at restart) and a new one would silently create an empty database. After the first open, new
connections never create the file.
"""
from __future__ import annotations

import os
import sqlite3
import time
import uuid
from contextlib import contextmanager
from typing import Iterator
from urllib.parse import quote, unquote

from sqlalchemy import MetaData, create_engine, event, make_url
from sqlalchemy.engine import Engine
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}
SQLITE_BUSY_TIMEOUT_MS = 30000


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


def new_id() -> str:
    return str(uuid.uuid4())


class DatabaseUnavailable(OperationalError):
    """The database cannot be used safely (the SQLite file vanished or was replaced). An OperationalError, so
    everything that copes with a database outage (the API's 503, the workers' retry loops) copes with it too."""

    def __init__(self, reason: str):
        super().__init__("(database check)", None, Exception(reason))
        self.reason = reason

    def __str__(self) -> str:
        return self.reason

    def __reduce__(self):
        return (type(self), (self.reason,))


def sqlite_file(url: str) -> tuple[str | None, bool]:
    """(absolute path of the SQLite database file, opened read-only) for a SQLite URL; (None, False) for an
    in-memory database or another dialect. Understands `sqlite:///file:PATH?mode=ro&uri=true`."""
    if not url.startswith("sqlite"):
        return None, False
    u = make_url(url)
    name, q = u.database or "", dict(u.query)
    if str(q.get("uri", "")).lower() in ("true", "1") and name.startswith("file:"):
        name, _, inner = name[5:].partition("?")
        name = unquote(name)
        for kv in inner.split("&"):
            k, _, v = kv.partition("=")
            if k:
                q.setdefault(k, v)
        if name.startswith("//"):  # file://host/path: only an empty host or localhost is legal
            name = "/" + name[2:].partition("/")[2]
    if not name or name == ":memory:" or q.get("mode") == "memory":
        return None, False
    return os.path.abspath(name), q.get("mode") == "ro" or str(q.get("immutable", "")) in ("1", "true")


def now() -> float:
    """Wall-clock seconds since the epoch; all stored times use it (portable across SQLite and PostgreSQL)."""
    return time.time()


def make_engine(url: str, *, immediate: bool = True) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000},
                               pool_size=20, max_overflow=40)

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn, _record):
            dbapi_conn.isolation_level = None  # let SQLAlchemy's begin event emit BEGIN IMMEDIATE
            cur = dbapi_conn.cursor()
            try:
                cur.execute("PRAGMA journal_mode=WAL")
            except sqlite3.OperationalError:  # a read-only database: keep its journal mode, reads still work
                pass
            cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.close()

        @event.listens_for(engine, "begin")
        def _begin(conn):
            # Immediate transactions: take the write lock at BEGIN, so two writers never deadlock on upgrade
            # and the queue's select-then-update claim is atomic. Read-only sessions use a plain BEGIN
            # (WAL readers never block and are never blocked).
            conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")
    else:
        args = {"connect_timeout": 5} if "connect_timeout" not in url else {}  # a dead host: 503 in 5 s, not minutes
        engine = create_engine(url, pool_size=10, max_overflow=20, pool_pre_ping=True, connect_args=args)
    return engine


class Database:
    def __init__(self, url: str):
        self.url = url
        self.engine = make_engine(url)
        self.sessionmaker = sessionmaker(self.engine, expire_on_commit=False)
        self.read_engine = make_engine(url, immediate=False) if url.startswith("sqlite") else self.engine
        self.read_sessionmaker = sessionmaker(self.read_engine, expire_on_commit=False)
        self.sqlite_path, self.read_only = sqlite_file(url)
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the SQLite file once opened
        if self.sqlite_path is not None:
            for engine in {self.engine, self.read_engine}:
                event.listen(engine, "do_connect", self._before_connect)
                event.listen(engine, "connect", self._remember_file)
                event.listen(engine, "checkout", lambda *_: self.verify())
                event.listen(engine, "commit", lambda *_: self.verify())

    def _before_connect(self, _dialect, _rec, cargs, cparams) -> None:
        if self._identity is None:
            return  # the first open may create the file (a fresh database, as before)
        self.verify()
        # never create the file again: open it read-write only if it exists (closes the race with verify)
        if cargs and isinstance(cargs[0], str) and not cparams.get("uri"):
            cargs[0] = "file:" + quote(self.sqlite_path) + "?mode=rw"
            cparams["uri"] = True

    def _remember_file(self, _dbapi_conn, _rec) -> None:
        if self._identity is None:
            try:
                st = os.stat(self.sqlite_path)
            except OSError:
                return
            self._identity = (st.st_dev, st.st_ino)

    def verify(self) -> None:
        """Raise DatabaseUnavailable if the SQLite file is no longer the one this process opened."""
        if self.sqlite_path is None:
            return
        try:
            st = os.stat(self.sqlite_path)
        except FileNotFoundError:
            raise DatabaseUnavailable(f"the SQLite database file {self.sqlite_path} is gone (deleted, or its "
                                      "directory was); nothing is read or written until it is restored") from None
        except OSError as exc:
            raise DatabaseUnavailable(f"the SQLite database file {self.sqlite_path} cannot be reached: "
                                      f"{exc.strerror}") from None
        if self._identity is not None and (st.st_dev, st.st_ino) != self._identity:
            raise DatabaseUnavailable(f"the SQLite database file {self.sqlite_path} was replaced by another "
                                      "file since it was opened; restart the service to use the new one")

    def problems(self) -> list[str]:
        """What keeps the database from taking writes, as far as the file system tells (SQLite); [] if nothing."""
        if self.sqlite_path is None:
            return []
        try:
            self.verify()
        except DatabaseUnavailable as exc:
            return [exc.reason]
        if self.read_only:
            return [f"the SQLite database {self.sqlite_path} is opened read-only (mode=ro): writes are refused"]
        out = []
        if not os.access(self.sqlite_path, os.W_OK):
            out.append(f"the SQLite database file {self.sqlite_path} is not writable")
        if not os.access(os.path.dirname(self.sqlite_path), os.W_OK | os.X_OK):
            out.append(f"the directory of the SQLite database {self.sqlite_path} is not writable")
        return out

    @contextmanager
    def session(self) -> Iterator[Session]:
        """One transaction: commit on success, roll back on any error."""
        with self.sessionmaker() as s:
            with s.begin():
                yield s

    @contextmanager
    def read_session(self) -> Iterator[Session]:
        """A read-only transaction (on SQLite: no write lock taken)."""
        with self.read_sessionmaker() as s:
            yield s  # autobegins on first use, rolled back on close

    def dispose(self) -> None:
        self.engine.dispose()
        self.read_engine.dispose()
