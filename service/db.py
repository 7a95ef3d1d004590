"""Engine, sessions, SQLite pragmas (WAL, busy timeout, BEGIN IMMEDIATE), the declarative base, and the guard
that turns a database that went away into `DatabaseUnavailable` (answered 503, never a silent loss).

SQLite: the file is stat-ed on every connection checkout and before every commit. If it is gone (its
directory deleted, the file removed) or replaced by another file, every session fails with
`DatabaseUnavailable`: a pooled connection would otherwise keep writing into the unlinked file (201/202 for
data lost at restart) and a new one would silently create an empty database. After the first open, new
connections never create the file.

Read-only or failed windows (issue 33) leave nothing behind, and writes agree with /health:
- SQLite: a write transaction is refused (`DatabaseUnavailable`, "read-only") whenever `problems()` names
  something, the very test /health answers with: a connection opened before the file became read-only could still
  write, so /health said 503 while writes succeeded. A connection opened while the file was not writable is
  read-only for good (SQLite falls back to read-only): it is replaced at its next checkout once the file is
  writable again; before, such connections stayed pooled and about 75 % of the writes after the window kept
  answering 503 while /health said 200. The -wal and -shm files SQLite made read-only during the window (it gives
  an empty -wal the database file's mode) get the database file's mode back before a new connection opens them.
- Any backend: an error saying the database is read-only (SQLite SQLITE_READONLY, PostgreSQL SQLSTATE 25006: a
  standby, `default_transaction_read_only`) or that its file cannot be read or opened (SQLite I/O errors) discards
  the pool's connections (each is replaced at its next checkout) and is answered as `DatabaseUnavailable` (503).
"""
from __future__ import annotations

import os
import sqlite3
import stat
import time
import uuid
from contextlib import contextmanager
from typing import Iterator
from urllib.parse import quote, unquote

from sqlalchemy import MetaData, create_engine, event, make_url
from sqlalchemy.engine import Engine
from sqlalchemy.exc import DisconnectionError, OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}
SQLITE_BUSY_TIMEOUT_MS = 30000
SQLITE_FAULTS = ("SQLITE_READONLY", "SQLITE_IOERR", "SQLITE_CANTOPEN", "SQLITE_FULL")
"""SQLite errors after which a connection is not trusted again: it is discarded and replaced."""
PG_READ_ONLY = "25006"
"""PostgreSQL's read_only_sql_transaction: the session was opened read-only (a standby, or
`default_transaction_read_only` on); it stays so, so it is discarded and replaced."""
READ_ONLY_RECENT_S = 5.0
"""PostgreSQL: for this long after a session or a write was found read-only, /health asks a new session of its own
whether it is read-only (the sessions opened before the database went read-only may still write, the new ones
cannot); otherwise its pooled session says."""


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
        self.read_only_seen = -1e9  # when a PostgreSQL session or write was last found read-only (monotonic)
        self._probe: Engine | None = None
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the SQLite file once opened
        if self.sqlite_path is not None:
            for engine in {self.engine, self.read_engine}:
                event.listen(engine, "do_connect", self._before_connect)
                event.listen(engine, "connect", self._remember_file)
                event.listen(engine, "checkout", self._checkout_writer if engine is self.engine else self._checkout)
                event.listen(engine, "commit", lambda *_: self.verify())
        elif self.engine.dialect.name == "postgresql":
            event.listen(self.engine, "connect", self._pg_session_mode)
            event.listen(self.engine, "checkout", self._pg_checkout)
        for engine in {self.engine, self.read_engine}:
            event.listen(engine, "handle_error", self._fault)

    def _before_connect(self, _dialect, rec, cargs, cparams) -> None:
        rec.info["opened_writable"] = self.writable()
        if rec.info["opened_writable"]:
            self._repair_side_files()
        if self._identity is None:
            return  # the first open may create the file (a fresh database, as before)
        self.verify()
        # never create the file again: open it read-write only if it exists (closes the race with verify)
        if cargs and isinstance(cargs[0], str) and not cparams.get("uri"):
            cargs[0] = "file:" + quote(self.sqlite_path) + "?mode=rw"
            cparams["uri"] = True

    def _remember_file(self, _dbapi_conn, rec) -> None:
        # SQLite opens a file it may not write read-only, for good: remember whether it could have been (before
        # and after the open, so a chmod in between counts as not writable)
        rec.info["opened_writable"] = rec.info.get("opened_writable", True) and self.writable()
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

    def _repair_side_files(self) -> None:
        """Give the -wal and -shm files the database file's mode again after a read-only window. SQLite sets an
        empty -wal's mode to the database file's when it opens it: during the window it became 0444, and the next
        connection would open it read-only (its writes failing for good)."""
        try:
            mode = stat.S_IMODE(os.stat(self.sqlite_path).st_mode)
        except OSError:
            return
        for side in (self.sqlite_path + "-wal", self.sqlite_path + "-shm"):
            try:
                if os.path.exists(side) and not os.access(side, os.W_OK):
                    os.chmod(side, mode)
            except OSError:  # not ours to change: the connection then fails and is replaced (_fault)
                pass

    def writable(self) -> bool:
        """Whether this process may write the SQLite file and its directory (always True for other databases)."""
        return self.sqlite_path is None or not self.problems()

    def _checkout(self, _dbapi_conn, rec, _proxy) -> None:
        self.verify()
        if not rec.info.get("opened_writable", True) and self.writable():
            # opened read-only while the file was not writable: the pool opens a new one in its place
            raise DisconnectionError("a connection opened while the database was read-only")

    def _checkout_writer(self, dbapi_conn, rec, proxy) -> None:
        """A write transaction's connection: refused, as /health is, while the database cannot take writes."""
        self._checkout(dbapi_conn, rec, proxy)
        trouble = self.problems()
        if trouble:
            raise DatabaseUnavailable("; ".join(trouble))

    def _pg_session_mode(self, dbapi_conn, rec) -> None:
        """Whether a new PostgreSQL session is read-only (a standby, default_transaction_read_only): it stays so."""
        try:
            with dbapi_conn.cursor() as cur:
                cur.execute("SHOW transaction_read_only")
                rec.info["opened_writable"] = cur.fetchone()[0] != "on"
        finally:
            dbapi_conn.rollback()
        rec.info["used"] = False
        if not rec.info["opened_writable"]:
            self.read_only_seen = time.monotonic()

    @staticmethod
    def _pg_checkout(_dbapi_conn, rec, _proxy) -> None:
        # a session opened read-only serves one checkout, then a new one is opened in its place (writable once the
        # database is again)
        if not rec.info.get("opened_writable", True) and rec.info.get("used"):
            raise DisconnectionError("a PostgreSQL session opened read-only")
        rec.info["used"] = True

    def _pg_new_session_read_only(self) -> bool:
        """Whether a new PostgreSQL session is read-only now (one connection of its own, outside the pool)."""
        from sqlalchemy.pool import NullPool

        if self._probe is None:
            self._probe = create_engine(self.url, poolclass=NullPool, connect_args={"connect_timeout": 5})
        try:
            with self._probe.connect() as c:
                on = c.exec_driver_sql("SHOW transaction_read_only").scalar() == "on"
        except Exception:  # noqa: BLE001 - /health's own query says what is wrong with the database
            return False
        if on:
            self.read_only_seen = time.monotonic()
        return on

    def _fault(self, ctx):
        """handle_error: a read-only session, or a SQLite file that cannot be read or opened: the connection and
        those pooled beside it are discarded (is_disconnect) and the error is answered as DatabaseUnavailable."""
        orig = ctx.original_exception
        if getattr(orig, "sqlstate", None) == PG_READ_ONLY:
            self.read_only_seen = time.monotonic()
            why = f"the PostgreSQL database is read-only (a standby, or default_transaction_read_only): {orig}"
        elif str(getattr(orig, "sqlite_errorname", "")).startswith(SQLITE_FAULTS):
            name = orig.sqlite_errorname
            why = ("the SQLite database is read-only: " if name.startswith("SQLITE_READONLY")
                   else "the SQLite database file failed: ") + str(orig)
        else:
            return None
        ctx.is_disconnect = True
        return DatabaseUnavailable(why.splitlines()[0])

    def problems(self) -> list[str]:
        """What keeps the database from taking writes, as far as the file system tells (SQLite); [] if nothing."""
        if self.sqlite_path is None:
            if time.monotonic() - self.read_only_seen < READ_ONLY_RECENT_S and self._pg_new_session_read_only():
                return ["the PostgreSQL database is read-only (a standby, or default_transaction_read_only on): "
                        "writes are refused"]
            return []
        try:
            self.verify()
        except DatabaseUnavailable as exc:
            return [exc.reason]
        if self.read_only:
            return [f"the SQLite database {self.sqlite_path} is opened read-only (mode=ro): writes are refused"]
        out = []
        if not os.access(self.sqlite_path, os.W_OK):
            out.append(f"the SQLite database file {self.sqlite_path} is read-only (not writable by this service)")
        if not os.access(os.path.dirname(self.sqlite_path), os.W_OK | os.X_OK):
            out.append(f"the directory of the SQLite database {self.sqlite_path} is read-only (not writable by this "
                       "service)")
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
        if self._probe is not None:
            self._probe.dispose()
