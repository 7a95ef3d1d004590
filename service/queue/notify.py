"""Waking workers when there is something to do, instead of letting them find it at their next poll.

A write that queues or cancels a job calls `wake_after_commit(session)`:
- in the same process (the dispatcher `calib serve` embeds), every registered `Waker` is set once the
  transaction has committed (a SQLAlchemy `after_commit` hook, so a woken worker always finds the row);
- on PostgreSQL the transaction also sends `NOTIFY calib_jobs` (delivered by the server at commit, never for a
  rolled-back transaction), which `PgListener` turns into a wake-up of a worker in any process or host.
On SQLite, a stand-alone `calib worker` has no cross-process signal and finds new jobs at its poll
(`CALIB_POLL_SECONDS`); the poll stays as the fallback everywhere.
"""
from __future__ import annotations

import logging
import os
import threading

from sqlalchemy import event, text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session

log = logging.getLogger("service.worker")
CHANNEL = "calib_jobs"
_KEY = "calib_wake_workers"


class Waker:
    """A self-pipe: `set()` from any thread (or a signal handler); `fileno()` is selectable, so a worker waits on
    it together with its job processes' pipes (`multiprocessing.connection.wait`)."""

    def __init__(self):
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self._w, False)

    def fileno(self) -> int:
        return self._r

    def set(self) -> None:
        try:
            os.write(self._w, b"x")
        except (BlockingIOError, OSError):  # already set (pipe full) or closed
            pass

    def drain(self) -> bool:
        """Clear; True if it had been set."""
        got = False
        try:
            while os.read(self._r, 4096):
                got = True
        except (BlockingIOError, OSError):
            pass
        return got

    def close(self) -> None:
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass


_lock = threading.Lock()
_local: set[Waker] = set()


def register(w: Waker) -> None:
    with _lock:
        _local.add(w)


def unregister(w: Waker) -> None:
    with _lock:
        _local.discard(w)


def wake_local() -> None:
    with _lock:
        wakers = list(_local)
    for w in wakers:
        w.set()


def wake_after_commit(s: Session, what: str = "job") -> None:
    """Wake the workers once this session's transaction commits (nothing happens if it rolls back)."""
    s.info[_KEY] = True
    bind = s.get_bind()
    if bind.dialect.name == "postgresql":
        s.execute(text("SELECT pg_notify(:channel, :what)"), {"channel": CHANNEL, "what": what[:100]})


@event.listens_for(Session, "after_commit")
def _after_commit(s: Session) -> None:
    if s.info.pop(_KEY, None):
        wake_local()


@event.listens_for(Session, "after_rollback")
def _after_rollback(s: Session) -> None:
    s.info.pop(_KEY, None)


class PgListener:
    """`LISTEN calib_jobs` on a dedicated PostgreSQL connection; every notification sets the worker's Waker.
    Reconnects after an error (and wakes the worker then, in case a notification was missed)."""

    def __init__(self, url: str, waker: Waker):
        self.conninfo = make_url(url).set(drivername="postgresql").render_as_string(hide_password=False)
        self.waker = waker
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self._run, name="calib-pg-listen", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(3)

    def _run(self) -> None:
        import psycopg

        while not self.stop_event.is_set():
            try:
                with psycopg.connect(self.conninfo, autocommit=True, connect_timeout=10) as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    self.waker.set()  # anything queued while we were not listening
                    while not self.stop_event.is_set():
                        for _ in conn.notifies(timeout=1.0):
                            self.waker.set()
            except Exception as exc:  # server restarted, network: the poll covers the gap
                log.warning("LISTEN %s: %s; reconnecting", CHANNEL, exc)
                self.stop_event.wait(2.0)
