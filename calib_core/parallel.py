"""Independent parts of one computation in forked processes: a diagnosis's play searches per joint, its rival
fits, its two mass-data paths (pmap); and, begun ahead while it goes on (Ahead), its robust first fit, a sparser
search and the smooth correction of what is left. Each part is a function of what the parent holds when it forks (nothing is sent but
the answer, pickled back through a pipe), so the answers are those of running the parts in order, which is what
one worker does (and what a platform without fork does), to rounding: a part done in another process allocates its
arrays at other addresses, and numpy's SIMD sums follow memory alignment (a diagnosis's x can move by 1e-12 mm).

Plain os.fork, not multiprocessing: a service job runs in a daemonic process, which multiprocessing forbids to
have children. A child dies with its parent (Linux)."""
from __future__ import annotations

import ctypes
import functools
import io
import os
import pickle
import select
import signal
import struct
import traceback
from typing import Callable, Iterator, Sequence, TypeVar

import numpy as np
from threadpoolctl import threadpool_limits

T = TypeVar("T")
R = TypeVar("R")

MAX_ITEMS = 16384
"""More items than the queue pipe's buffer holds (64 KiB, 4 bytes each) are done in order here: writing their indices
would wait for a reader that is not there yet. The search's largest pool is some hundreds."""


def pmap(fn: Callable[[T], R], items: Sequence[T], workers: int = 1, shared: Sequence[object] = ()) -> list[R]:
    """[fn(item) for item in items] in `workers` processes (this one and workers - 1 forked children), each taking
    the next item left when it is free (the parts differ in cost: one joint's play search, another's). An exception
    in a part is raised here, as in the loop; the parts of a child that died without answering are done here. The
    `shared` objects come back as themselves, not as copies (a fit's model: the search checks a calibration's model
    by identity)."""
    items = list(items)
    k = min(max(int(workers), 1), len(items))
    if k <= 1 or not hasattr(os, "fork") or len(items) > MAX_ITEMS:
        return [fn(item) for item in items]
    return _forked(fn, items, k, shared)


def one_blas_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """`fn` run with one BLAS thread (restored after). Its matrices (a few thousand rows by a few hundred columns)
    gain nothing from more: the Agile Justin's diagnosis took 25.3 s on two BLAS threads and 47.8 s of CPU, 24.2 s on
    one, and two processes each with a thread per core ran the Motoman's 3x slower. One thread also gives the answer
    of the service's processes (OPENBLAS_NUM_THREADS=1) to the bit: the sums' order follows the thread count."""
    @functools.wraps(fn)
    def limited(*args, **kwargs):
        with threadpool_limits(1, user_api="blas"):
            return fn(*args, **kwargs)
    return limited


@one_blas_thread  # the processes are the parallelism
def _forked(fn: Callable[[T], R], items: list[T], k: int, shared: Sequence[object]) -> list[R]:
    """pmap's work in k processes (this one and k - 1 forked children, which inherit its BLAS thread count)."""
    queue_r, queue_w = os.pipe()  # the items' indices, 4 bytes each: a read of 4 bytes takes one, atomically
    os.write(queue_w, struct.pack(f"<{len(items)}i", *range(len(items))))
    os.close(queue_w)
    children, parent = [], os.getpid()
    for _ in range(1, k):
        children.append(_fork(lambda: [(i, True, fn(items[i])) for i in _taken(queue_r)], parent, shared))
    results: dict[int, R] = {}
    error: BaseException | None = None
    try:
        for i in _taken(queue_r):
            results[i] = fn(items[i])
    except BaseException as exc:  # noqa: BLE001 - raised once the children are collected
        error = exc
    os.close(queue_r)
    for pid, read in children:
        with os.fdopen(read, "rb") as f:
            data = f.read()
        os.waitpid(pid, 0)
        if error is not None:
            continue
        if not data:  # killed (out of memory, a signal): its parts are done again below
            continue
        for i, ok, value in _Unpickler(data, shared).load():
            if not ok:
                error = value
                break
            results[i] = value
    if error is not None:
        raise error
    for i in range(len(items)):  # what a helper that died had taken: a dead helper costs time, not the answer
        if i not in results:
            results[i] = fn(items[i])
    return [results[i] for i in range(len(items))]


class Ahead:
    """fn() computed in a forked child while this process goes on (a search whose outcome is rarely taken, begun
    beside the work that assumes it is not); result() waits for it. Without fork, or when the child died without
    answering, fn() is computed here, as it would be in order. The `shared` objects come back as themselves (pmap)."""

    def __init__(self, fn: Callable[[], R], shared: Sequence[object] = ()):
        self.fn, self.shared, self.pid, self.read, self.parent = fn, shared, None, None, os.getpid()
        if hasattr(os, "fork"):
            self.pid, self.read = _fork(lambda: [(0, True, fn())], os.getpid(), shared)

    def ready(self) -> bool:
        """Whether the answer is there to read (the child is writing it, or has died): result() then waits little."""
        return self.pid is None or bool(select.select([self.read], [], [], 0)[0])

    def result(self) -> R:
        """fn()'s answer (its exception raised here)."""
        if self.pid is None:
            return self.fn()
        with os.fdopen(self.read, "rb") as f:
            data = f.read()
        os.waitpid(self.pid, 0)
        self.pid = None
        if not data:  # killed (out of memory, a signal): done here, in order
            return self.fn()
        ((_, ok, value),) = _Unpickler(data, self.shared).load()
        if not ok:
            raise value
        return value

    def cancel(self) -> None:
        """Stops the child when its answer is no longer wanted (an exception on the way); only in the process that
        began it (a process forked since holds a copy of this object, not the child)."""
        if self.pid is not None and os.getpid() == self.parent:
            try:
                os.kill(self.pid, signal.SIGKILL)
                os.waitpid(self.pid, 0)
            except OSError:
                pass
            os.close(self.read)
            self.pid = None


def _fork(answers: Callable[[], list], parent: int, shared: Sequence[object]) -> tuple[int, int]:
    """A child that pickles answers() ([(index, True, value)], or [(-1, False, the exception)] when it raises) into a
    pipe and is gone without the parent's clean-ups; (its pid, the pipe's end to read) here."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read)
        _die_with(parent)
        code = 0
        try:
            try:
                out = answers()
            except BaseException as exc:  # noqa: BLE001 - carried to the parent, raised there
                out = [(-1, False, _portable(exc))]
            with os.fdopen(write, "wb") as f:
                _Pickler(f, shared).dump(out)
        except BaseException:  # noqa: BLE001 - the parent sees a child that gave no answer
            code = 1
        finally:
            os._exit(code)
    os.close(write)
    return pid, read


def _taken(queue: int) -> Iterator[int]:
    """The indices this process takes from the queue pipe, one at a time, until it is empty."""
    while len(b := os.read(queue, 4)) == 4:
        yield struct.unpack("<i", b)[0]


def _die_with(parent: int) -> None:
    """Linux: this process is killed when its parent ends (a job process killed at its time limit takes its helpers
    along); elsewhere it finishes its share and finds the pipe closed."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent ended before the call
        os._exit(1)


SPARSE_BYTES = 1 << 16
"""Arrays of at least this many bytes whose elements are mostly zero bits go back as their nonzero elements: the
bases a screening worker made come back to the parent's context, and an effect acting through a few joints of a
tree is zero on the rest (Agile Justin's workers pickled 134 MB of them, most of it zeros)."""


class _Pickler(pickle.Pickler):
    """Pickles the shared objects as their ids (a forked child's objects from before the fork have the parent's), and
    large mostly-zero arrays by their nonzero elements (the same bits back: -0.0 is not zero here)."""

    def __init__(self, f, shared: Sequence[object]):
        super().__init__(f, protocol=pickle.HIGHEST_PROTOCOL)
        self.ids = {id(o) for o in shared}

    def persistent_id(self, obj):
        return id(obj) if id(obj) in self.ids else None

    def reducer_override(self, obj):
        if type(obj) is not np.ndarray or obj.nbytes < SPARSE_BYTES or obj.dtype != np.float64:
            return NotImplemented
        order = "F" if obj.flags.f_contiguous and not obj.flags.c_contiguous else "C"  # as numpy pickles it
        flat = obj.ravel(order)
        nz = np.flatnonzero(flat)
        if len(nz) > flat.size // 4:
            return NotImplemented
        negative = np.packbits(np.signbit(flat))  # a zero's sign too (products leave many -0.0): the same bits
        return _from_nonzero, (obj.shape, order, nz.astype(np.int32 if flat.size < 2**31 else np.int64), flat[nz],
                               negative)


def _from_nonzero(shape: tuple, order: str, nz: np.ndarray, values: np.ndarray, negative: np.ndarray) -> np.ndarray:
    """The float64 array of `shape` (memory `order`) that is `values` at the flat indices nz and a zero elsewhere, -0.0
    where the packed sign bits say so."""
    size = int(np.prod(shape))
    flat = np.zeros(size)
    flat[np.unpackbits(negative, count=size).astype(bool)] = -0.0
    flat[nz] = values
    return flat.reshape(shape, order=order)


class _Unpickler(pickle.Unpickler):
    def __init__(self, data: bytes, shared: Sequence[object]):
        super().__init__(io.BytesIO(data))
        self.by_id = {id(o): o for o in shared}

    def persistent_load(self, pid):
        return self.by_id[pid]


def _portable(exc: BaseException) -> BaseException:
    """exc if it pickles, else a RuntimeError carrying its traceback."""
    try:
        pickle.dumps(exc)
        return exc
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError("".join(traceback.format_exception(exc)))
