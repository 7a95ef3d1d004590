"""The worker loop: claim jobs, run each in a job process of its own, write progress, enforce the time limit,
stop cancelled jobs, reap dead workers' jobs.

`calib worker` runs it in the foreground; `calib serve` runs the same loop in a background thread (the
embedded dispatcher).  Any number of workers can share one database.

A worker keeps CALIB_WORKER_CONCURRENCY job processes (`Slot`s, see runner.slot_main), started and warmed
up when the worker starts, and reused job after job. A job process that dies takes only its own job with it
(re-queued as an infrastructure failure, up to CALIB_MAX_ATTEMPTS); a job over CALIB_JOB_TIMEOUT_S (its run
time summed over attempts) or cancelled has its process killed; in every case the slot gets a fresh process
and the other jobs run on untouched.

The loop sleeps in one `multiprocessing.connection.wait` on the job processes' pipes and exits and on a
`Waker` (notify.py) that a job queued or cancelled in this process, or a PostgreSQL NOTIFY, sets: a result, a
crash, a new job or a cancellation is handled at once, not at the next poll (CALIB_POLL_SECONDS is the
fallback).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import socket
import threading
import time
import uuid
from dataclasses import dataclass
from multiprocessing.connection import wait as mp_wait

from ..config import Settings
from .. import processes
from ..db import Database
from . import notify, store
from .runner import slot_main

log = logging.getLogger("service.worker")


def make_worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"


def describe_exit(code: int | None) -> str:
    if code is None:
        return "it stopped answering"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


@dataclass
class Slot:
    """One job process and the job it runs (if any)."""
    index: int
    proc: mp.process.BaseProcess
    conn: object  # multiprocessing Connection
    ready: bool = False
    retiring: bool = False  # it said it will exit after its job (out of memory): no new job for it
    job: store.Claimed | None = None
    t_job: float = 0.0  # monotonic, when the job was sent
    progress: float | None = None
    message: str | None = None
    next_write: float = 0.0  # monotonic: the next progress/lease write

    def elapsed(self, t: float) -> float:
        """The job's run time over all its attempts."""
        return (self.job.run_seconds if self.job else 0.0) + (t - self.t_job)


class Worker:
    def __init__(self, db: Database, settings: Settings, worker_id: str | None = None):
        self.db, self.settings = db, settings
        self.id = worker_id or make_worker_id()
        self.concurrency = max(1, settings.worker_concurrency)
        self.stop_event = threading.Event()
        self.ready_event = threading.Event()  # every slot has been warm once
        self.waker = notify.Waker()
        self._ctx = processes.context()
        self.slots: list[Slot] = []
        self._respawn_at: dict[int, float] = {}  # slot index -> monotonic time (back-off after failed starts)
        self._start_failures: dict[int, int] = {}
        self._listener: notify.PgListener | None = None
        self._t0 = time.monotonic()
        self._freed = True  # a slot became free or ready: try to claim without waiting for the poll
        self._claim_at = float("inf")  # monotonic: a job this worker re-queued becomes claimable

    # -- job processes ------------------------------------------------------------------------------------
    def _spawn(self, index: int) -> Slot:
        parent, child = self._ctx.Pipe(duplex=True)
        p = self._ctx.Process(target=slot_main, name=f"calib-job-{index}", daemon=True,
                              args=(child, os.getpid(), self.settings.warm_pool, self.settings.test_poison,
                                    self.settings.job_nice))
        processes.start(p)
        child.close()
        return Slot(index, p, parent)

    def _kill(self, slot: Slot) -> None:
        try:
            slot.proc.kill()
            slot.proc.join(5)
        except Exception:  # noqa: BLE001
            log.exception("could not kill job process %s", slot.proc.pid)
        try:
            slot.conn.close()
        except OSError:
            pass

    def _replace(self, slot: Slot) -> None:
        """A fresh process in this slot (the old one is dead or killed)."""
        self._kill(slot)
        if not slot.ready and not slot.retiring:  # died before it got ready: back off (a broken install must
            # not fork-bomb the machine)
            n = self._start_failures.get(slot.index, 0) + 1
            self._start_failures[slot.index] = n
            self._respawn_at[slot.index] = time.monotonic() + min(30.0, 0.5 * 2 ** n)
            self.slots[slot.index] = None  # type: ignore[call-overload]
            log.error("job process %d died while starting (%s); restarting it in %.1f s", slot.index,
                      describe_exit(slot.proc.exitcode), self._respawn_at[slot.index] - time.monotonic())
            return
        self._start_failures.pop(slot.index, None)
        self.slots[slot.index] = self._spawn(slot.index)

    def _respawn_due(self, t: float) -> None:
        for i, at in list(self._respawn_at.items()):
            if t >= at:
                del self._respawn_at[i]
                self.slots[i] = self._spawn(i)

    def _live(self) -> list[Slot]:
        return [s for s in self.slots if s is not None]

    # -- messages from the job processes ------------------------------------------------------------------
    def _read(self, slot: Slot) -> None:
        try:
            while slot.conn.poll():
                msg = slot.conn.recv()
                kind = msg[0]
                if kind == "ready":
                    slot.ready = self._freed = True
                    if not self.ready_event.is_set() and all(s is not None and s.ready for s in self.slots):
                        log.info("worker %s: %d job process(es) warm in %.1f s", self.id, len(self.slots),
                                 time.monotonic() - self._t0)
                        self.ready_event.set()
                elif kind == "progress" and slot.job is not None and msg[1] == slot.job.job_id:
                    slot.progress, slot.message = msg[2], msg[3]
                elif kind == "done" and slot.job is not None and msg[1] == slot.job.job_id:
                    c, t = slot.job, time.monotonic()
                    run_s = slot.elapsed(t)
                    slot.job, self._freed = None, True
                    self._finish(c, msg[2], run_s)
                    if msg[2].get("infrastructure"):
                        slot.ready, slot.retiring = False, True
                        return  # the process exits; _check_dead replaces it
        except (EOFError, OSError):
            pass  # it died: _check_dead handles it

    def _finish(self, c: store.Claimed, out: dict, run_s: float) -> None:
        if out.get("ok"):
            cid = store.complete(self.db, c, self.id, out["result"], out["state"], out.get("plots"), run_s)
            if cid is None:
                if not store.ack_cancel(self.db, c.job_id, self.id):
                    log.warning("job %s: lease lost before the result was written; result discarded", c.job_id)
            else:
                log.info("job %s succeeded -> calibration %s (computed in %.3f s)", c.job_id, cid,
                         out.get("compute_s", float("nan")))
        elif out.get("infrastructure"):
            log.warning("job %s: %s; re-queueing", c.job_id, out["error"])
            self._retry(c, out["error"], run_s)
        else:
            store.fail(self.db, c.job_id, self.id, out["error"], retry=False, run_seconds=run_s)
            log.info("job %s failed: %s", c.job_id, out["error"])

    def _check_dead(self) -> None:
        for slot in self._live():
            if slot.proc.is_alive():
                continue
            self._read(slot)  # a result sent just before it exited
            c = slot.job
            if c is not None:
                why = describe_exit(slot.proc.exitcode)
                err = (f"the job's process died ({why}) on attempt {c.attempt}; a job whose process dies on every "
                       f"attempt (CALIB_MAX_ATTEMPTS) fails")
                log.warning("job %s: its process %s died (%s); re-queueing", c.job_id, slot.proc.pid, why)
                self._retry(c, err, slot.elapsed(time.monotonic()))
                slot.job = None
            self._replace(slot)

    def _retry(self, c: store.Claimed, error: str, run_s: float) -> None:
        """An infrastructure failure: back to the queue after the back-off (or failed, out of attempts); this
        worker looks for it again when the back-off ends, not at its next poll."""
        backoff = self.settings.retry_backoff_seconds
        store.fail(self.db, c.job_id, self.id, error, retry=True, backoff_seconds=backoff, run_seconds=run_s)
        self._claim_at = min(self._claim_at, time.monotonic() + backoff * 2 ** (c.attempt - 1) + 0.01)

    # -- the limits and ownership of running jobs ---------------------------------------------------------
    def _timeouts(self, t: float) -> None:
        limit = self.settings.job_timeout_s
        for slot in self._live():
            if slot.job is None or slot.elapsed(t) <= limit:
                continue
            c, run_s = slot.job, slot.elapsed(t)
            self._kill(slot)  # first: frees the CPU and the slot whatever the database says
            slot.job = None
            err = (f"the job ran {run_s:.1f} s, over the time limit of {limit:g} s (CALIB_JOB_TIMEOUT_S, summed "
                   f"over attempts); its process was stopped")
            log.warning("job %s: %s", c.job_id, err)
            store.fail(self.db, c.job_id, self.id, err, retry=False, run_seconds=run_s)
            self._replace(slot)

    def _lost(self, slot: Slot) -> None:
        """This worker no longer owns the slot's job (cancelled, or its lease expired and another worker took
        it): stop its process now; it must not run on for nothing."""
        c = slot.job
        slot.job = None
        self._kill(slot)
        if store.ack_cancel(self.db, c.job_id, self.id):
            log.info("job %s cancelled; its process %s was stopped", c.job_id, slot.proc.pid)
        else:
            log.warning("job %s: lease lost (another worker took over); its process was stopped", c.job_id)
        self._replace(slot)

    def _check_owned(self) -> None:
        busy = [s for s in self._live() if s.job is not None]
        if not busy:
            return
        owned = store.still_owned(self.db, self.id, [s.job.job_id for s in busy])
        for slot in busy:
            if slot.job.job_id not in owned:
                self._lost(slot)

    def _write_progress(self, t: float) -> None:
        """Every CALIB_PROGRESS_SECONDS per running job: progress, message with the elapsed time, lease."""
        s = self.settings
        for slot in self._live():
            if slot.job is None or t < slot.next_write:
                continue
            slot.next_write = t + min(s.progress_seconds, s.heartbeat_seconds)
            run_s = slot.elapsed(t)
            message = f"{slot.message or 'running'} ({run_s:.1f} s)"
            if not store.heartbeat(self.db, slot.job.job_id, self.id, s.lease_seconds, slot.progress, message,
                                   run_s):
                self._lost(slot)

    # -- claiming ---------------------------------------------------------------------------------------
    def _claim(self) -> None:
        for slot in self._live():
            if self.stop_event.is_set():
                return
            if not slot.ready or slot.job is not None or not slot.proc.is_alive():
                continue
            c = store.claim(self.db, self.id, self.settings.lease_seconds)
            if c is None:
                return
            log.info("job %s claimed (attempt %d) by process %s", c.job_id, c.attempt, slot.proc.pid)
            slot.job, slot.t_job, slot.progress, slot.message = c, time.monotonic(), None, None
            slot.next_write = slot.t_job + self.settings.progress_seconds
            try:
                slot.conn.send(("job", c.job_id, c.mode, c.model_json, c.raw, self.settings.test_job_delay_s,
                                {"instrument": c.instrument, "limits": c.limits,
                                 "budget_s": max(0.0, self.settings.job_timeout_s - c.run_seconds),
                                 "workers": self.settings.diagnosis_workers}))
            except (OSError, ValueError):  # it died just now: give the job back untouched
                slot.job = None
                store.release(self.db, c.job_id, self.id)

    # -- the loop ---------------------------------------------------------------------------------------
    def run(self) -> None:
        s = self.settings
        notify.register(self.waker)
        if self.db.engine.dialect.name == "postgresql":
            self._listener = notify.PgListener(self.db.url, self.waker)
            self._listener.start()
        self.slots = [self._spawn(i) for i in range(self.concurrency)]
        next_poll = next_reap = 0.0
        log.info("worker %s started (concurrency %d, lease %.1f s, time limit %g s)", self.id, self.concurrency,
                 s.lease_seconds, s.job_timeout_s)
        try:
            while not self.stop_event.is_set():
                timeout = s.poll_seconds
                try:
                    woken = self.waker.drain()
                    for slot in self._live():
                        self._read(slot)
                    self._check_dead()
                    t = time.monotonic()
                    self._respawn_due(t)
                    self._timeouts(t)
                    if woken:
                        self._check_owned()  # a cancellation, perhaps: stop its process now
                    self._write_progress(t)
                    if t >= next_reap:
                        requeued, failed = store.reap(self.db)
                        if requeued or failed:
                            log.warning("reaper: %d job(s) re-queued, %d failed (lease expired)", requeued, failed)
                        next_reap = t + max(0.2, s.lease_seconds / 2)
                    idle = any(x.ready and x.job is None for x in self._live())
                    if idle and (woken or t >= next_poll or t >= self._claim_at or self._freed):
                        self._freed, self._claim_at = False, float("inf")
                        self._claim()
                        next_poll = t + s.poll_seconds
                    timeout = self._next_wake(time.monotonic(), next_poll, next_reap)
                except Exception:  # the database went away, etc.: keep going, leases protect the jobs
                    log.exception("worker loop error; retrying")
                    self.stop_event.wait(s.poll_seconds)
                    continue
                live = self._live()
                mp_wait([self.waker] + [x.conn for x in live] + [x.proc.sentinel for x in live], timeout)
        finally:
            self._shutdown()

    def _next_wake(self, t: float, next_poll: float, next_reap: float) -> float:
        """Seconds until the loop has something to do that no pipe, exit or wake-up will announce."""
        s = self.settings
        due = [next_reap, t + 5.0, *self._respawn_at.values()]
        if any(x.ready and x.job is None for x in self._live()):
            due += [next_poll, self._claim_at]
        for x in self._live():
            if x.job is not None:
                due.append(x.next_write)
                due.append(x.t_job + (s.job_timeout_s - x.job.run_seconds) + 0.01)
        return max(0.005, min(due) - t)

    def _shutdown(self) -> None:
        t = time.monotonic()
        for slot in self._live():
            if slot.job is not None:
                try:
                    store.release(self.db, slot.job.job_id, self.id, run_seconds=slot.elapsed(t))
                except Exception:
                    log.exception("could not release job %s; its lease will expire", slot.job.job_id)
                slot.job = None
        for slot in self._live():
            self._kill(slot)
        if self._listener is not None:
            self._listener.stop()
        notify.unregister(self.waker)
        log.info("worker %s stopped", self.id)

    def stop(self) -> None:
        self.stop_event.set()
        self.waker.set()


class Dispatcher:
    """The worker loop in a background thread, for `calib serve`."""

    def __init__(self, db: Database, settings: Settings):
        self.worker = Worker(db, settings)
        self.thread = threading.Thread(target=self.worker.run, name="calib-dispatcher", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def wait_ready(self, timeout: float) -> bool:
        """Block until every job process is warm (or timeout); True if they are."""
        return self.worker.ready_event.wait(timeout)

    def stop(self, timeout: float = 10.0) -> None:
        self.worker.stop()
        self.thread.join(timeout)
