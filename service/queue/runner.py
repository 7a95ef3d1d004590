"""The CPU work of a job, in a job process of its own: re-parse the stored CSV, call calib_core, draw the plots.

Each job process (`slot_main`) is started by a worker, warms itself up (imports, one tiny calibration, one
figure), says `ready`, then runs one job at a time sent over its pipe and answers with progress messages and
the result. One process per running job: when a job crashes its process, spins or is cancelled, only that
process dies (or is killed) and is replaced; the other jobs of the worker never notice.

Errors raised by the computation (too few poses, a singular problem, bad data) are deterministic: the job
fails at once with the message, no retry.  The process dying (killed, out of memory) is an infrastructure
failure the worker retries up to CALIB_MAX_ATTEMPTS.

Tests only (never in production):
- CALIB_TEST_JOB_DELAY_S (read by the worker, passed in as `delay_s`) adds that many seconds of sleep before
  the computation, reporting progress, so the tests can kill a worker mid-job;
- CALIB_TEST_POISON=1 makes a CSV comment line `# calib-test-poison: crash` kill the job's process (SIGKILL
  of itself), `# calib-test-poison: spin` spin at 100 % CPU without progress, like a numerical routine
  that never returns, and `# calib-test-poison: slow=2.5` add that many seconds of delay to this job alone.
"""
from __future__ import annotations

import math
import os
import re
import signal
import threading
import time
from typing import Any, Callable

SEARCH_SHARE = 0.6
"""The diagnosis searches for causes during this share of what is left of a job's time limit; the rest finishes
the answer (what the residual follows, the plots, storing) with room to spare."""
POISON_CRASH = b"# calib-test-poison: crash"
POISON_SPIN = b"# calib-test-poison: spin"
POISON_SLOW = re.compile(rb"# calib-test-poison: slow=([0-9.]+)")


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


def render_plots(result: dict) -> dict[str, bytes]:
    """Every plot the stored answer lists, as PNG bytes (drawn once, here; the API serves them from the database).
    A plot that cannot be drawn becomes a PNG that says why, so the report never breaks on it."""
    from ..report import plots

    answer = dict(result)
    answer.setdefault("model", ["geometric"])
    out = {}
    for name in plots.names(answer):
        try:
            out[name] = plots.png(answer, name)
        except Exception as exc:  # noqa: BLE001 - a figure must not fail a calibration
            out[name] = plots.error_png(name, f"{type(exc).__name__}: {exc}")
    return out


def run_job(job_id: str, mode: str, model_json: dict, raw: bytes, delay_s: float = 0.0,
            progress: Callable[[float, str], None] | None = None, poison: bool = False,
            with_plots: bool = True, instrument: str | None = None, limits: str = "reject",
            budget_s: float | None = None, workers: int = 1) -> dict:
    """`instrument` and `limits` are the measurement set's, as uploaded: the CSV is re-parsed as it was checked.
    `budget_s`: what is left of the job's time limit; the diagnosis stops searching after SEARCH_SHARE of it and
    answers with what it has confirmed, so a large set ends with an answer that says so, not killed. `workers`:
    processes the diagnosis's independent parts run in (CALIB_DIAGNOSIS_WORKERS)."""
    deadline = None if budget_s is None else time.monotonic() + SEARCH_SHARE * budget_s
    import calib_core
    from calib_core.identify import identify
    from calib_core.io import parse_measurements
    from calib_core.model import parse_model

    def report(fraction: float, message: str) -> None:
        if progress is not None:
            try:
                progress(float(fraction), str(message))
            except Exception:  # progress is best-effort
                pass

    if poison:  # tests only, see the module docstring
        if POISON_CRASH in raw:
            os.kill(os.getpid(), signal.SIGKILL)
        if POISON_SPIN in raw:
            x = 0
            while True:
                x += 1
        if (m := POISON_SLOW.search(raw)) is not None:
            delay_s = max(delay_s, float(m.group(1)))
    try:
        report(0.02, "parsing the measurements")
        model = parse_model(model_json)
        meas = parse_measurements(raw, model, instrument=instrument, limits=limits)
        if delay_s > 0:  # tests only, see the module docstring
            t_end = time.monotonic() + delay_s
            while (left := t_end - time.monotonic()) > 0:
                report(0.05, f"test delay: {left:.1f} s left")
                time.sleep(min(0.2, left))
        report(0.1, f"calibrating ({mode}) on {meas.n_poses} poses")
        t0 = time.perf_counter()
        calibrate = getattr(calib_core, "calibrate", None)
        if calibrate is not None:
            result = dict(calibrate(model, meas, mode, lambda f, m: report(0.1 + 0.85 * f, m), deadline=deadline,
                                    workers=workers))
            state = result.pop("robot_state", None)
            if state is None:
                raise RuntimeError("calib_core.calibrate returned no robot_state")
        else:  # until calib_core.calibrate exists: the geometric identification for both modes
            cal = identify(model, meas)
            result, state = cal.to_dict(), cal.robot.to_state()
        compute_s = time.perf_counter() - t0
        result = _finite(result)
        plots = {}
        if with_plots:
            report(0.96, "drawing the plots")
            plots = render_plots(result)
        report(0.99, "storing the result")
        return {"ok": True, "result": result, "state": _finite(state), "plots": plots, "compute_s": compute_s}
    except MemoryError:
        raise  # infrastructure: the worker retries it in a fresh process
    except Exception as exc:  # numerical / data failure: deterministic, fail at once
        return {"ok": False, "error": f"{exc}" if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"}


def warm_up() -> None:
    """What the first job would otherwise pay: imports, numpy/scipy first calls, matplotlib's font cache."""
    from calib_core import Twin, write_measurements
    from calib_core.identify import identify
    from calib_core.io import parse_measurements
    from calib_core.model import parse_model
    from calib_core.robots import spray7

    from ..report import plots

    model = parse_model(spray7())
    meas = parse_measurements(write_measurements(Twin(model, 0).measure(n=24), model).encode(), model)
    identify(model, meas)  # the kinematics and the solver once (a full calibration would cost 0.5 s more)
    plots.error_png("warm-up", "warm-up")


def _watch_parent(parent_pid: int) -> None:
    """Exit if the server process that started us dies (no orphans that keep spinning): it is gone, or our parent
    (it, or its fork server, which ends with it) changed."""
    born_of = os.getppid()

    def watch():
        while True:
            time.sleep(0.5)
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:
                pass  # alive, or its pid reused by another user's process: the parent check below decides
            if os.getppid() != born_of:
                os._exit(1)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


def run_below(nice: int) -> None:
    """This process `nice` steps below the API's priority (0: the same); where the platform cannot, the same."""
    if nice > 0:
        try:
            os.nice(nice)
        except OSError:
            pass


def slot_main(conn, parent_pid: int, warm: bool, poison: bool, nice: int = 0) -> None:
    """A job process: warm up, then run the jobs the worker sends, one at a time, until the pipe closes. It runs
    `nice` steps below the API (CALIB_JOB_NICE): on a busy machine the requests people wait for go first.

    Messages to the worker: ("ready", pid), ("progress", job_id, fraction, message), ("done", job_id, out).
    Messages from it: ("job", job_id, mode, model_json, raw, delay_s, options) with options the measurement
    set's {"instrument", "limits"}."""
    # the worker decides when a job process ends: a Ctrl-C or a SIGTERM to the process group (a graceful
    # restart) must not look like a crashed job; the worker kills us after releasing the job
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    run_below(nice)
    _watch_parent(parent_pid)
    if warm:
        try:
            warm_up()
        except Exception:  # noqa: BLE001 - a failed warm-up only costs the first job its speed
            pass
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] != "job":
            continue
        _, job_id, mode, model_json, raw, delay_s, options = msg

        def progress(f: float, m: str, _id=job_id) -> None:
            conn.send(("progress", _id, f, m))

        try:
            out = run_job(job_id, mode, model_json, raw, delay_s, progress, poison, **options)
        except MemoryError:
            out = {"ok": False, "infrastructure": True, "error": "MemoryError: the job's process ran out of memory"}
        try:
            conn.send(("done", job_id, out))
        except (OSError, ValueError):
            return
        if out.get("infrastructure"):
            return  # a fresh process for the next job
