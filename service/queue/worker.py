"""The worker loop: claim jobs, run them in a process pool, heartbeat their leases, reap dead workers' jobs.

`calib worker` runs it in the foreground; `calib serve` runs the same loop in a background thread
(the embedded dispatcher).  Any number of workers can share one database.
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue as _queue
import socket
import threading
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from ..config import Settings
from ..db import Database
from . import store
from .runner import init_pool_process, run_job

log = logging.getLogger("service.worker")


def make_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


class Worker:
    def __init__(self, db: Database, settings: Settings, worker_id: str | None = None):
        self.db, self.settings = db, settings
        self.id = worker_id or make_worker_id()
        self.concurrency = max(1, settings.worker_concurrency)
        self.stop_event = threading.Event()
        self._ctx = mp.get_context("spawn")
        self._progress_q = None
        self._pool: ProcessPoolExecutor | None = None
        self.inflight: dict[Future, store.Claimed] = {}
        self.progress: dict[str, tuple[float, str]] = {}

    # -- pool ---------------------------------------------------------------------------------------------
    def _new_pool(self) -> None:
        self._progress_q = self._ctx.Queue()
        self._pool = ProcessPoolExecutor(self.concurrency, mp_context=self._ctx, initializer=init_pool_process,
                                         initargs=(self._progress_q,))

    def _drain_progress(self) -> None:
        try:
            while True:
                job_id, f, m = self._progress_q.get_nowait()
                self.progress[job_id] = (f, m)
        except (_queue.Empty, OSError, EOFError, ValueError):
            pass

    # -- one pass ----------------------------------------------------------------------------------------
    def _finish(self, fut: Future, c: store.Claimed) -> None:
        self.progress.pop(c.job_id, None)
        try:
            out = fut.result()
        except BrokenProcessPool as exc:
            log.warning("job %s: the pool process died (%s); re-queueing", c.job_id, exc)
            store.fail(self.db, c.job_id, self.id, f"worker process died: {exc}", retry=True,
                       backoff_seconds=self.settings.retry_backoff_seconds)
            return
        except Exception as exc:  # MemoryError or pickling trouble: infrastructure
            log.warning("job %s: infrastructure failure %r; re-queueing", c.job_id, exc)
            store.fail(self.db, c.job_id, self.id, f"{type(exc).__name__}: {exc}", retry=True,
                       backoff_seconds=self.settings.retry_backoff_seconds)
            return
        if out["ok"]:
            cid = store.complete(self.db, c, self.id, out["result"], out["state"])
            if cid is None:
                log.warning("job %s: lease lost before the result was written; result discarded", c.job_id)
            else:
                log.info("job %s succeeded -> calibration %s", c.job_id, cid)
        else:
            store.fail(self.db, c.job_id, self.id, out["error"], retry=False)
            log.info("job %s failed: %s", c.job_id, out["error"])

    def _heartbeat(self) -> None:
        for fut, c in list(self.inflight.items()):
            f, m = self.progress.get(c.job_id, (None, None))
            if not store.heartbeat(self.db, c.job_id, self.id, self.settings.lease_seconds, f, m):
                log.warning("job %s: lease lost (another worker took over)", c.job_id)
                self.inflight.pop(fut, None)  # its result, if any, is ignored

    def _claim(self) -> None:
        while len(self.inflight) < self.concurrency and not self.stop_event.is_set():
            c = store.claim(self.db, self.id, self.settings.lease_seconds)
            if c is None:
                return
            log.info("job %s claimed (attempt %d)", c.job_id, c.attempt)
            fut = self._pool.submit(run_job, c.job_id, c.mode, c.model_json, c.raw, self.settings.test_job_delay_s)
            self.inflight[fut] = c

    def run(self) -> None:
        self._new_pool()
        s = self.settings
        next_hb = next_reap = 0.0
        log.info("worker %s started (concurrency %d, lease %.1f s)", self.id, self.concurrency, s.lease_seconds)
        try:
            while not self.stop_event.is_set():
                try:
                    self._drain_progress()
                    for fut in [f for f in self.inflight if f.done()]:
                        self._finish(fut, self.inflight.pop(fut))
                    if self._pool_broken():
                        self._new_pool()
                    t = time.monotonic()
                    if t >= next_hb:
                        self._heartbeat()
                        next_hb = t + s.heartbeat_seconds
                    if t >= next_reap:
                        requeued, failed = store.reap(self.db)
                        if requeued or failed:
                            log.warning("reaper: %d job(s) re-queued, %d failed (lease expired)", requeued, failed)
                        next_reap = t + max(0.2, s.lease_seconds / 2)
                    self._claim()
                except Exception:  # the database went away, etc.: keep going, leases protect the jobs
                    log.exception("worker loop error; retrying")
                    self.stop_event.wait(s.poll_seconds)
                    continue
                if self.inflight:
                    wait(list(self.inflight), timeout=min(s.poll_seconds, s.heartbeat_seconds),
                         return_when=FIRST_COMPLETED)
                else:
                    self.stop_event.wait(s.poll_seconds)
        finally:
            self._shutdown()

    def _pool_broken(self) -> bool:
        return bool(getattr(self._pool, "_broken", False))

    def _shutdown(self) -> None:
        for fut, c in list(self.inflight.items()):
            try:
                store.release(self.db, c.job_id, self.id)
            except Exception:
                log.exception("could not release job %s; its lease will expire", c.job_id)
        self.inflight.clear()
        if self._pool is not None:
            for p in list(getattr(self._pool, "_processes", {}).values()):
                p.terminate()
            self._pool.shutdown(wait=False, cancel_futures=True)
        log.info("worker %s stopped", self.id)

    def stop(self) -> None:
        self.stop_event.set()


class Dispatcher:
    """The worker loop in a background thread, for `calib serve`."""

    def __init__(self, db: Database, settings: Settings):
        self.worker = Worker(db, settings)
        self.thread = threading.Thread(target=self.worker.run, name="calib-dispatcher", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self.worker.stop()
        self.thread.join(timeout)
