"""Lanes: synchronous computation bounded and off the API process (issue 33). A lane is `size` processes of its own,
each running one call at a time, and a waiting room of `room` calls, or of `room_bytes` bytes (below); a call beyond
that is answered at once with 503 and Retry-After. A call running longer than the lane's time bound is stopped: its
process is killed (a thread cannot be) and replaced, and the call answered 503 naming the bound. A process that dies
costs its call a 503 and is replaced.

Used for plans (plans/), predict and compensate (calibrations/), and the CSV checks of uploads (measurements/: a lane
for small uploads and one for large ones, so a small upload never waits behind a large one). Waiting calls are taken
in order of `priority` (then arrival): the upload lanes take the smallest CSV first.

A waiting room in bytes (`room_bytes` > 0, the large-upload lane): each call comes with its size (`nbytes`, the CSV's
length) and is admitted while the calls waiting (not yet running) hold at most `room_bytes` bytes with it; the number
of calls is not counted. Counting calls refused a cheap 1.8 MB CSV behind six 19 MB ones (issue 33, the red team's
load: 14 x 503 "1 running, 8 waiting"), though smallest-first would have checked it next; counting bytes admits it
while a flood of large uploads still meets the bound. A call is admitted whatever its size when nothing waits, so a
budget below the largest allowed body never refuses an upload on an idle lane. What the budget bounds is memory: a
waiting call's arguments are held in the API process until a process takes them (an upload's bytes were read whole
into memory by its route before it asks for the lane; the multipart parser's spooled copy stays on disk), so the
waiting uploads hold at most max(`room_bytes`, one body) of the API process's memory, plus the `size` running ones.

Callers wait without holding a route thread (`await lane.arun(...)`) or block (`lane.run(...)`). Each lane has slot
threads (one per process) that hand calls to their process through a pipe: not a ProcessPoolExecutor, which can
neither kill one call's process nor bound its waiting room.
"""
from __future__ import annotations

import asyncio
import importlib
import itertools
import logging
import os
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass

from . import processes
from .problems import ProblemError

log = logging.getLogger("service")

RETRY_AFTER_S = 5
START_TIMEOUT_S = 120.0
"""How long a new process may take to import its modules (not counted in a call's own time bound)."""


@dataclass(frozen=True)
class Words:
    """How a lane's answers name what it does."""
    noun: str  # "plan": "every plan process is busy", "the plan took longer than ..."
    timeout_env: str  # the setting of its time bound, named in the 503
    room_env: str = ""  # the setting of its waiting room, named in the busy 503 when given
    nothing: str = "nothing was computed"
    advice: str = "a retry when the server is less busy may succeed"


def _main(conn, parent: int, preload: str, nice: int = 0) -> None:
    """A lane's process: imports `preload` once, says ready, then runs (fn, args) after (fn, args) from its pipe,
    answering ("ok", value), ("problem", ProblemError fields) or ("error", text); `nice` steps below the API."""
    import signal

    from .queue.runner import _watch_parent, run_below

    run_below(nice)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server decides when its lane processes end
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # (the fork server they come from ignores it)
    _watch_parent(parent)  # a server killed outright (SIGKILL) leaves no process behind
    importlib.import_module(preload)  # calib_core's imports, paid before a call's clock starts
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
            log.exception("a call in a lane process failed")
            out = ("error", f"{type(exc).__name__}: {exc}"[:2000])
        conn.send(out)


class _Process:
    """One lane process and its pipe."""

    def __init__(self, preload: str, name: str, nice: int = 0):
        ctx = processes.context()  # one core per call: OPENBLAS_NUM_THREADS=1
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_main, args=(child, os.getpid(), preload, nice), daemon=True, name=name)
        processes.start(self.proc)
        child.close()
        self.ready = False
        self.lock = threading.Lock()  # the lane's warm-up and its slot thread may both wait for "ready"

    def wait_ready(self, timeout_s: float) -> bool:
        with self.lock:
            if not self.ready:
                try:
                    if self.conn.poll(timeout_s):
                        self.ready = self.conn.recv() == "ready"
                except (EOFError, OSError):
                    return False
            return self.ready

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(5)
        self.conn.close()


_STOP = object()


class Lane:
    """`size` processes importing `preload`, at most `room` calls (or `room_bytes` bytes) waiting; see the module's
    docstring."""

    def __init__(self, name: str, preload: str, words: Words, nice: int = 0):
        self.name, self.preload, self.words, self.nice = name, preload, words, nice  # nice: steps below the API
        self.lock = threading.Lock()
        self.size = self.room = self.room_bytes = 0
        self.timeout_s = 60.0
        self.pending = 0  # calls waiting or running
        self.waiting_bytes = 0  # the `nbytes` of the calls waiting (admitted, not yet taken by a process)
        self.tasks: queue.PriorityQueue | None = None
        self.slots: list[_Slot] = []
        self.seq = itertools.count()

    # ------------------------------------------------------------------ life

    def configure(self, size: int, room: int, timeout_s: float, room_bytes: int = 0) -> None:
        """Start `size` processes (they import in the background) with a waiting room of `room` calls, or of
        `room_bytes` bytes when that is above 0 (then `room` is not used); once, or again when a setting changed."""
        with self.lock:
            if (self.size, self.room, self.timeout_s, self.room_bytes) == (size, room, timeout_s, room_bytes) \
                    and self.slots:
                return
            self._stop()
            self.size, self.room, self.timeout_s, self.room_bytes = size, room, timeout_s, room_bytes
            self.tasks = queue.PriorityQueue()
            self.slots = [_Slot(self, i) for i in range(size)]

    def warm(self, size: int, room: int, timeout_s: float, room_bytes: int = 0) -> None:
        """Start the processes and wait (bounded) until each has imported its modules."""
        self.configure(size, room, timeout_s, room_bytes)
        for slot in list(self.slots):
            if not slot.wait_ready(START_TIMEOUT_S):
                log.warning("a %s process did not start; its calls will try again", self.words.noun)

    def pids(self) -> list[int]:
        """The lane's processes (tests kill one)."""
        return [s.proc.proc.pid for s in self.slots]

    def shutdown(self) -> None:
        with self.lock:
            self._stop()
            self.size = self.room = self.room_bytes = 0

    def _stop(self) -> None:
        for slot in self.slots:
            slot.stop()
        self.slots = []
        while self.tasks is not None:  # calls still waiting: answered, never left hanging
            try:
                _, _, task = self.tasks.get_nowait()
            except queue.Empty:
                break
            if task is not _STOP:
                task[2].set_result(("unavailable", f"the server stopped its {self.words.noun} processes; "
                                                   f"{self.words.nothing}; try again"))
                self.pending -= 1  # (the lock is held)
                self.waiting_bytes -= task[3]

    def _stop_item(self) -> tuple:
        return (float("-inf"), next(self.seq), _STOP)

    # ------------------------------------------------------------------ calls

    def submit(self, fn, args: tuple, priority: float = 0.0, nbytes: int = 0) -> Future:
        """fn(*args) in one of the lane's processes, as a Future of (kind, value); a 503 at once when every process
        is busy and the waiting room is full (in bytes: `nbytes` more would not fit, see the module's docstring)."""
        with self.lock:
            if not self.slots:
                raise self._busy()
            if self.room_bytes > 0:
                if self.waiting_bytes > 0 and self.waiting_bytes + nbytes > self.room_bytes:
                    raise self._busy()
            elif self.pending >= self.size + self.room:
                raise self._busy()
            self.pending += 1
            self.waiting_bytes += nbytes
            fut: Future = Future()
            self.tasks.put((priority, next(self.seq), (fn, args, fut, nbytes)))
        return fut

    def run(self, fn, args: tuple, priority: float = 0.0, nbytes: int = 0):
        """fn(*args) in the lane, waiting in this thread: its value, or the ProblemError it raised; 503s as above."""
        return self._answer(*self.submit(fn, args, priority, nbytes).result())

    async def arun(self, fn, args: tuple, priority: float = 0.0, nbytes: int = 0):
        """fn(*args) in the lane, waited for on the event loop (no thread held)."""
        return self._answer(*await asyncio.wrap_future(self.submit(fn, args, priority, nbytes)))

    def _taken(self, nbytes: int) -> None:
        """A process took a call: its bytes leave the waiting room."""
        with self.lock:
            self.waiting_bytes -= nbytes

    def _done(self) -> None:
        with self.lock:
            self.pending -= 1

    def _busy(self) -> ProblemError:
        setting = f", {self.words.room_env}" if self.words.room_env else ""
        if self.room_bytes > 0:
            room = (f"{self.waiting_bytes / 1e6:.1f} MB waiting, the waiting room holds {self.room_bytes / 1e6:.1f} "
                    f"MB{setting}")
        else:
            room = f"{self.room} waiting{setting}"
        return ProblemError(503, f"every {self.words.noun} process is busy ({self.size} running, {room}); "
                            f"{self.words.nothing}; try again shortly", kind="unavailable",
                            headers={"Retry-After": str(RETRY_AFTER_S)})

    def _unavailable(self, why: str) -> ProblemError:
        return ProblemError(503, why, kind="unavailable", headers={"Retry-After": str(RETRY_AFTER_S)})

    def _answer(self, kind: str, value):
        if kind == "ok":
            return value
        if kind == "problem":
            status, detail, pkind, title, errors, headers, extra = value
            raise ProblemError(status, detail, kind=pkind, title=title, errors=errors, headers=headers, **extra)
        if kind == "unavailable":
            raise self._unavailable(value)
        raise RuntimeError(f"the {self.words.noun} failed in its process: {value}")


class _Slot:
    """A thread that feeds one process the lane's calls, one at a time, and replaces the process when it dies or
    runs beyond the time bound."""

    def __init__(self, lane: Lane, index: int):
        self.lane, self.tasks = lane, lane.tasks
        self.proc = _Process(lane.preload, f"calib-{lane.name}", lane.nice)
        self.stopped = False
        self.thread = threading.Thread(target=self._loop, name=f"calib-{lane.name}-{index}", daemon=True)
        self.thread.start()

    def wait_ready(self, timeout_s: float) -> bool:
        return self.proc.wait_ready(timeout_s)

    def stop(self) -> None:
        self.stopped = True
        self.tasks.put(self.lane._stop_item())
        self.proc.kill()

    def _loop(self) -> None:
        while True:
            item = self.tasks.get()
            task = item[2]
            if task is not _STOP:
                self.lane._taken(task[3])
            if task is _STOP or self.stopped:
                if task is not _STOP:  # the lane is stopping: answered, never left hanging
                    task[2].set_result(("unavailable", f"the server stopped its {self.lane.words.noun} processes; "
                                                       f"{self.lane.words.nothing}; try again"))
                    self.lane._done()
                return
            fn, args, fut, _ = task
            try:
                if fut.set_running_or_notify_cancel():
                    fut.set_result(self._call(fn, args))
            except BaseException as exc:  # noqa: BLE001 - never leave a caller waiting
                if not fut.done():
                    fut.set_result(("error", f"{type(exc).__name__}: {exc}"))
            finally:
                self.lane._done()

    def _replace(self) -> None:
        self.proc.kill()
        if not self.stopped:
            self.proc = _Process(self.lane.preload, f"calib-{self.lane.name}", self.lane.nice)

    def _call(self, fn, args: tuple) -> tuple[str, object]:
        w, timeout_s = self.lane.words, self.lane.timeout_s
        p = self.proc
        try:
            if not p.proc.is_alive():  # died idle (with its fork server): the call was not sent, a fresh one takes it
                log.warning("an idle %s process had died; it is replaced", w.noun)
                self._replace()
                p = self.proc
            if not p.wait_ready(START_TIMEOUT_S) or not p.proc.is_alive():
                self._replace()
                return "unavailable", f"the {w.noun} process could not start; {w.nothing}; try again"
            t0 = time.monotonic()
            p.conn.send((fn, args))
            if p.conn.poll(timeout_s):
                return p.conn.recv()
        except (EOFError, OSError):
            log.warning("a %s process died; it is replaced", w.noun)
            self._replace()
            return "unavailable", f"the {w.noun}'s process died; {w.nothing}; try again"
        log.warning("a %s ran %.1f s, beyond %s; its process is killed and replaced", w.noun,
                    time.monotonic() - t0, w.timeout_env)
        self._replace()
        return "unavailable", (f"the {w.noun} took longer than the server's bound of {timeout_s:g} s "
                               f"({w.timeout_env}) and was stopped; {w.nothing}; {w.advice}")
