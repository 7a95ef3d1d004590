"""Where the server's processes come from: a fork server that imported what they run once (calib_core, numpy,
scipy, the lanes' modules), so a job or lane process costs a fork instead of a fresh interpreter's imports (spawn:
about a second of CPU each, seven processes per server). Where a platform has no fork server, spawn as before."""
from __future__ import annotations

import multiprocessing as mp
import os
import threading

PRELOAD = ["service.fork_server", "service.queue.runner", "service.measurements.service", "service.plans.service",
           "service.calibrations.compute", "service.report.plots"]
"""The fork server's signals (fork_server.py), then the modules the job processes and the lanes (lanes.py) import
before their first call (a job process draws its answer's plots: matplotlib, 0.8 s of CPU, imported once per server
instead of once per job process)."""

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

        forkserver.ensure_running()
