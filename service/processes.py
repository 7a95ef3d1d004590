"""Where the server's processes come from: a fork server that imported what they run once (calib_core, numpy,
scipy, the lanes' modules), so a job or lane process costs a fork instead of a fresh interpreter's imports (spawn:
about a second of CPU each, seven processes per server). Where a platform has no fork server, spawn as before."""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import tempfile
import threading
import time

log = logging.getLogger("service.processes")

PRELOAD = ["service.fork_server", "service.queue.runner", "service.measurements.service", "service.plans.service",
           "service.calibrations.compute", "service.report.plots", "scipy.optimize", "scipy.stats",
           "scipy.spatial.transform"]
"""The fork server's signals (fork_server.py), then the modules the job processes and the lanes (lanes.py) import
before their first call (a job process draws its answer's plots: matplotlib, 0.8 s of CPU, imported once per server
instead of once per job process), and the parts of scipy that calib_core imports where it uses them (a diagnosis, a
twin), which the API process, parsing and answering, never does."""

_lock = threading.Lock()
_context = None


def context():
    """The multiprocessing context for every process the server starts (one fork server per server process)."""
    global _context
    with _lock:
        if _context is None:
            os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # read by numpy's import in the fork server
            if "forkserver" in mp.get_all_start_methods():
                _context = mp.get_context("forkserver")
                _context.set_forkserver_preload(PRELOAD)
            else:
                _context = mp.get_context("spawn")
        return _context


def start_early() -> None:
    """Start the fork server now (its imports: calib_core, numpy, scipy, about 2 s of CPU) so that it imports beside
    the server process's own imports and migrations instead of after them, when the first process is asked for."""
    if context().get_start_method() == "forkserver":
        from multiprocessing import forkserver

        try:
            forkserver.ensure_running()
        except OSError as exc:  # its socket lives in a directory under TMPDIR: a Unix socket path holds 107 bytes
            if "AF_UNIX path too long" not in str(exc):
                raise
            tmp = tempfile.gettempdir()
            raise SystemExit(f"calib serve: the temporary directory {tmp} ({len(tmp)} characters) is too long for "
                             f"the fork server's socket (a Unix socket's path holds at most 107 bytes, and the "
                             f"socket adds about 32 to it): set TMPDIR to a shorter directory, such as /tmp") from None


RESTART_WAIT_S = 0.2
"""Wait before a second start when the first met a fork server that had just died: multiprocessing starts a new one
only once the dead one can be reaped (a job process noticed its death first, and its replacement's start read EOF)."""


def start(proc: mp.process.BaseProcess) -> None:
    """proc.start(), once more after RESTART_WAIT_S when the fork server died under it (an operator's kill, the OOM
    killer): the second start brings up a new fork server, so a process that died with the old one is replaced
    instead of failing."""
    try:
        proc.start()
    except (EOFError, ConnectionError) as exc:
        log.warning("the fork server was gone (%s); starting a new one", type(exc).__name__)
        time.sleep(RESTART_WAIT_S)
        proc.start()
