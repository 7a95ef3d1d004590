"""The plan processes (CALIB_PLAN_PROCESSES): a plan is computed there, not on the API's route threads.

Issue 33: plans ran in the API process, so 16 concurrent 1000-pose plans held every route thread and a GET waited
48 s. Here at most `size` plans run at once, each in its own process, and at most `size` more wait for one; any
further plan is a 503 with Retry-After at once. A plan running longer than CALIB_PLAN_TIMEOUT_S is stopped: its
process is killed (a thread cannot be) and replaced, and the request gets a 503 naming the bound.

One process per plan slot with a pipe, not a ProcessPoolExecutor: the executor cannot kill one task's process.
"""
from __future__ import annotations

import importlib
import logging
import multiprocessing as mp
import os
import queue
import threading
import time

from ..problems import ProblemError

log = logging.getLogger("service")

RETRY_AFTER_S = 5
START_TIMEOUT_S = 120.0
"""How long a new plan process may take to import calib_core (not counted in the plan's own time bound)."""


def _busy(size: int) -> ProblemError:
    return ProblemError(503, f"every plan process is busy ({size} running, {size} waiting); nothing was computed; "
                        "try again shortly", kind="unavailable", headers={"Retry-After": str(RETRY_AFTER_S)})


def _main(conn, parent: int) -> None:
    """A plan process: imports once, says ready, then runs (fn, args) after (fn, args) from its pipe, answering
    ("ok", value), ("problem", ProblemError fields) or ("error", text)."""
    import signal

    from ..queue.runner import _watch_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when its plan processes end
    _watch_parent(parent)  # a server killed outright (SIGKILL) leaves no plan process behind
    importlib.import_module(__package__ + ".service")  # calib_core's imports, paid before a plan's clock starts

    conn.send("ready")
    while True:
        try:
            fn, args = conn.recv()
        except EOFError:
            return
        try:
            out = ("ok", fn(*args))
        except ProblemError as exc:
            out = ("problem", (exc.status, exc.detail, exc.kind, exc.title, exc.errors, exc.headers, exc.extra))
        except Exception as exc:  # noqa: BLE001 - the API answers it as a 500, as it did in-process
            log.exception("a plan failed")
            out = ("error", f"{type(exc).__name__}: {exc}"[:2000])
        conn.send(out)


class _Process:
    """One plan process and its pipe."""

    def __init__(self):
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # inherited by the spawned child: one core per plan
        self.proc = ctx.Process(target=_main, args=(child, os.getpid()), daemon=True, name="calib-plan")
        self.proc.start()
        child.close()
        self.ready = False

    def wait_ready(self, timeout_s: float) -> bool:
        if not self.ready and self.conn.poll(timeout_s):
            self.ready = self.conn.recv() == "ready"
        return self.ready

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(5)
        self.conn.close()


class PlanPool:
    """`size` plan processes, each running one plan at a time, and room for `size` more plans waiting."""

    def __init__(self):
        self.lock = threading.Lock()
        self.size = 0
        self.slots: threading.BoundedSemaphore | None = None
        self.idle: queue.Queue[_Process] = queue.Queue()

    def configure(self, size: int) -> None:
        """Start `size` processes (once; they import calib_core in the background)."""
        with self.lock:
            if self.size == size:
                return
            self._drain()
            self.size = size
            self.slots = threading.BoundedSemaphore(2 * size)
            for _ in range(size):
                self.idle.put(_Process())

    def warm(self, size: int) -> None:
        """Start the processes and wait (bounded) until each has imported calib_core."""
        self.configure(size)
        procs = [self.idle.get() for _ in range(size)]
        try:
            for p in procs:
                if not p.wait_ready(START_TIMEOUT_S):
                    log.warning("a plan process did not start; plans will try again")
        finally:
            for p in procs:
                self.idle.put(p)

    def run(self, fn, args: tuple, timeout_s: float):
        """fn(*args) in a plan process; its return value, or the ProblemError it raised; a 503 when all processes
        and the waiting room are taken, or when the plan ran longer than timeout_s (its process then replaced)."""
        slots = self.slots
        if slots is None or not slots.acquire(blocking=False):
            raise _busy(self.size)
        try:
            p = self.idle.get()
            try:
                p, (kind, value) = self._call(p, fn, args, timeout_s)
            finally:
                self.idle.put(p)
        finally:
            slots.release()
        if kind == "ok":
            return value
        if kind == "problem":
            status, detail, pkind, title, errors, headers, extra = value
            raise ProblemError(status, detail, kind=pkind, title=title, errors=errors, headers=headers, **extra)
        if kind == "unavailable":
            raise ProblemError(503, value, kind="unavailable", headers={"Retry-After": str(RETRY_AFTER_S)})
        raise RuntimeError(f"the plan failed in its process: {value}")

    @staticmethod
    def _call(p: _Process, fn, args: tuple, timeout_s: float) -> tuple[_Process, tuple[str, object]]:
        """Run one plan on p: the process to put back (p, or its replacement when p was killed, had died or did not
        start) and the answer (kind, value)."""
        try:
            if not p.wait_ready(START_TIMEOUT_S) or not p.proc.is_alive():
                p.kill()
                return _Process(), ("unavailable", "the plan process could not start; nothing was computed; "
                                                   "try again")
            t0 = time.monotonic()
            p.conn.send((fn, args))
            if p.conn.poll(timeout_s):
                return p, p.conn.recv()
        except (EOFError, OSError):
            log.warning("a plan process died; it is replaced")
            p.kill()
            return _Process(), ("unavailable", "the plan's process died; nothing was computed; try again")
        log.warning("a plan ran %.1f s, beyond CALIB_PLAN_TIMEOUT_S; its process is killed and replaced",
                    time.monotonic() - t0)
        p.kill()
        return _Process(), ("unavailable", f"the plan took longer than the server's bound of {timeout_s:g} s "
                            "(CALIB_PLAN_TIMEOUT_S) and was stopped; nothing was computed; fewer poses, or a "
                            "retry when the server is less busy, plan faster")

    def _drain(self) -> None:
        while True:
            try:
                p = self.idle.get_nowait()
            except queue.Empty:
                return
            p.kill()

    def shutdown(self) -> None:
        with self.lock:
            self._drain()
            self.size, self.slots = 0, None


PLANNERS = PlanPool()
