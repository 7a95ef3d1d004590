"""Benchmarks: one command each (`python -m benchmarks.NAME`), peers measured in the same run; and the helpers
they share."""
from __future__ import annotations

import os
import socket
import time
from pathlib import Path


def best_time(fn, repeats: int) -> tuple[float, object]:
    """Best wall time (s) of `repeats` calls of fn, and its last result."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a `calib serve` started by a benchmark)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def server_env(db_path: Path, max_upload: int | None = None) -> dict:
    """The environment of a `calib serve` on the SQLite file db_path: no CALIB_* of the caller's, BLAS
    single-threaded, and CALIB_MAX_UPLOAD_BYTES when given."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CALIB_")}
    env.update({"CALIB_DATABASE_URL": f"sqlite:///{db_path}", "OPENBLAS_NUM_THREADS": "1"})
    if max_upload:
        env["CALIB_MAX_UPLOAD_BYTES"] = str(max_upload)
    return env
