"""The CPU work of one job, run in a pool process: re-parse the stored CSV and call calib_core.

Errors raised by the computation (too few poses, a singular problem, bad data) are deterministic: the job
fails at once with the message, no retry.  Only the pool dying (the process was killed, ran out of memory)
is an infrastructure failure, seen by the worker as BrokenProcessPool and retried.

CALIB_TEST_JOB_DELAY_S (read by the worker, passed in as `delay_s`) adds that many seconds of sleep before the
computation, reporting progress; it exists only so the tests can kill a worker mid-job. Never set it in production.
"""
from __future__ import annotations

import math
import os
import threading
import time
from typing import Any

_progress_queue = None


def init_pool_process(progress_queue) -> None:
    """Pool initializer: remember the progress queue and exit if the parent worker dies (no orphans)."""
    global _progress_queue
    _progress_queue = progress_queue
    parent = os.getppid()

    def watch():
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _finite(v: Any) -> Any:
    """JSON for the database: non-finite numbers become null."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if hasattr(v, "tolist"):
        return _finite(v.tolist())
    return v


def run_job(job_id: str, mode: str, model_json: dict, raw: bytes, delay_s: float = 0.0) -> dict:
    import calib_core
    from calib_core.identify import identify
    from calib_core.io import parse_measurements
    from calib_core.model import parse_model

    def progress(fraction: float, message: str) -> None:
        if _progress_queue is not None:
            try:
                _progress_queue.put_nowait((job_id, float(fraction), str(message)))
            except Exception:  # progress is best-effort
                pass

    try:
        progress(0.02, "parsing the measurements")
        model = parse_model(model_json)
        meas = parse_measurements(raw, model)
        if delay_s > 0:  # tests only, see the module docstring
            t_end = time.monotonic() + delay_s
            while (left := t_end - time.monotonic()) > 0:
                progress(0.05, f"test delay: {left:.1f} s left")
                time.sleep(min(0.2, left))
        progress(0.1, f"calibrating ({mode}) on {meas.n_poses} poses")
        calibrate = getattr(calib_core, "calibrate", None)
        if calibrate is not None:
            result = dict(calibrate(model, meas, mode, lambda f, m: progress(0.1 + 0.88 * f, m)))
            state = result.pop("robot_state", None)
            if state is None:
                raise RuntimeError("calib_core.calibrate returned no robot_state")
        else:  # until calib_core.calibrate exists: the geometric identification for both modes
            cal = identify(model, meas)
            result, state = cal.to_dict(), cal.robot.to_state()
        progress(0.99, "storing the result")
        return {"ok": True, "result": _finite(result), "state": _finite(state)}
    except MemoryError:
        raise  # infrastructure: let the worker retry elsewhere
    except Exception as exc:  # numerical / data failure: deterministic, fail at once
        return {"ok": False, "error": f"{exc}" if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"}
