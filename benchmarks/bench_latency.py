"""Latency of a job over HTTP, as a cell PC sees it: `calib serve` on SQLite (embedded mode, the default), started
here on a temporary file, real HTTP.

    .venv/bin/python benchmarks/bench_latency.py [--jobs 30] [--starts 2] [--poll-ms 5]

Measures
- submit-to-succeeded of a 150-pose `geometric` job with a warm server: POST /jobs, then GET /jobs/{id} every
  --poll-ms until it succeeded; p50 / p95 over --jobs jobs run one after the other;
- the first job after `calib serve` started (answered /health), over --starts fresh starts;
- the same jobs split on the server's own clock (`created_at`, `started_at`, `finished_at`, `run_seconds`):
  queue wait (submit to claim), time in the job process, and the rest (result written, seen by the poll);
- the computation alone: `calib_core.calibrate` in this process, no service (the floor of any latency);
- how often a running job's progress changes, as seen by polling GET /jobs/{id} every 50 ms during an `auto`
  job (diagnosis) on the same poses.
Prints a markdown table (for docs/RESULTS.md). Not a test: nothing is asserted.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from benchmarks import free_port, server_env  # noqa: E402
from calib_core import Twin, parse_model, write_measurements  # noqa: E402
from calib_core.robots import spray7  # noqa: E402


def start_server(db_path: Path, log: Path) -> tuple[subprocess.Popen, str, float]:
    """`calib serve` on db_path; returns (process, url, seconds until /health answered)."""
    port = free_port()
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "service.cli", "--log-level", "WARNING", "serve", "--port", str(port)],
                         cwd=ROOT, env=server_env(db_path), stdout=open(log, "ab"), stderr=subprocess.STDOUT,
                         start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    while time.perf_counter() - t0 < 180:
        if p.poll() is not None:
            raise SystemExit(f"the server exited; see {log}")
        try:
            if httpx.get(url + "/health", timeout=1).status_code == 200:
                return p, url, time.perf_counter() - t0
        except httpx.HTTPError:
            pass
        time.sleep(0.05)
    p.kill()
    raise SystemExit("the server did not start")


def stop_server(p: subprocess.Popen) -> None:
    p.terminate()
    try:
        p.wait(20)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait(5)


def epoch(iso: str | None) -> float:
    return datetime.fromisoformat(iso).timestamp() if iso else float("nan")


def run_job(c: httpx.Client, ms_id: str, mode: str, poll_s: float) -> tuple[float, dict]:
    """Submit, poll until finished; (seconds from submit to seeing `succeeded`, the final job)."""
    t0 = time.perf_counter()
    r = c.post("/jobs", json={"measurement_set_id": ms_id, "model": mode})
    r.raise_for_status()
    jid = r.json()["id"]
    while True:
        j = c.get(f"/jobs/{jid}").json()
        if j["status"] not in ("queued", "running"):
            break
        time.sleep(poll_s)
    took = time.perf_counter() - t0
    if j["status"] != "succeeded":
        raise SystemExit(f"job {jid} ended {j['status']}: {j.get('error')}")
    return took, j


def upload(c: httpx.Client, csv: str) -> str:
    rid = c.post("/robots", json=spray7()).json()["id"]
    r = c.post(f"/robots/{rid}/measurements", files={"file": ("bench.csv", csv)})
    r.raise_for_status()
    return r.json()["id"]


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def ms(v: float) -> str:
    return f"{1000 * v:.0f} ms"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=30, help="warm jobs, one after the other (default 30)")
    ap.add_argument("--starts", type=int, default=2, help="fresh `calib serve` starts for the first job (default 2)")
    ap.add_argument("--poll-ms", type=float, default=5.0, help="GET /jobs/{id} interval while waiting (default 5)")
    ap.add_argument("--no-auto", action="store_true", help="skip the progress measurement (an auto job)")
    args = ap.parse_args()
    poll_s = args.poll_ms / 1000

    import calib_core
    from calib_core.io import parse_measurements

    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    model = parse_model(spray7())
    csv = write_measurements(Twin(model, 1).measure(n=150), model)
    meas = parse_measurements(csv.encode(), model)
    compute, compute_cpu = [], []
    for _ in range(5):
        t0, c0 = time.perf_counter(), time.process_time()
        calib_core.calibrate(model, meas, "geometric")
        compute.append(time.perf_counter() - t0)
        compute_cpu.append(time.process_time() - c0)

    tmp = Path(tempfile.mkdtemp(prefix="calib-bench-latency-"))
    log = tmp / "server.log"
    firsts, startup = [], []
    warm, server_side = [], []
    changes: list[float] = []
    auto_s = float("nan")
    for k in range(args.starts):
        p, url, t_start = start_server(tmp / "calib.db", log)
        startup.append(t_start)
        try:
            with httpx.Client(base_url=url, timeout=120) as c:
                ms_id = upload(c, csv)
                firsts.append(run_job(c, ms_id, "geometric", poll_s)[0])
                if k < args.starts - 1:
                    continue
                for _ in range(args.jobs):
                    took, j = run_job(c, ms_id, "geometric", poll_s)
                    warm.append(took)
                    created, started, done = epoch(j["created_at"]), epoch(j["started_at"]), epoch(j["finished_at"])
                    server_side.append((started - created, j.get("run_seconds") or float("nan"), done - created))
                if not args.no_auto:
                    t0 = time.perf_counter()
                    jid = c.post("/jobs", json={"measurement_set_id": ms_id, "model": "auto"}).json()["id"]
                    last = None
                    while True:
                        j = c.get(f"/jobs/{jid}").json()
                        if j["status"] == "running":
                            seen = (j["progress"], j["message"])
                            if seen != last:
                                changes.append(time.perf_counter())
                                last = seen
                        elif j["status"] != "queued":
                            break
                        time.sleep(0.05)
                    auto_s = time.perf_counter() - t0
        finally:
            stop_server(p)

    wait = [s[0] for s in server_side]
    run = [s[1] for s in server_side]
    gaps = [b - a for a, b in zip(changes, changes[1:])]
    cpu = os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\n`benchmarks/bench_latency.py --jobs {args.jobs} --starts {args.starts} --poll-ms {args.poll_ms:g}`: "
          f"`calib serve` on SQLite (embedded worker, CALIB_WORKER_CONCURRENCY=2), 150-pose spray7 `geometric` "
          f"jobs one at a time over HTTP, polled every {args.poll_ms:g} ms; {cpu} cores, load average "
          f"{load0:.1f} at the start, {load:.1f} at the end.\n")
    print("| measure | p50 | p95 | n |")
    print("|---|---|---|---|")
    print(f"| submit -> succeeded, warm server | {ms(pct(warm, 50))} | {ms(pct(warm, 95))} | {len(warm)} |")
    print(f"| submit -> succeeded, first job after `calib serve` | {ms(pct(firsts, 50))} | {ms(max(firsts))} (max) | "
          f"{len(firsts)} |")
    print(f"| first job / warm p50 | {pct(firsts, 50) / pct(warm, 50):.2f}x | {max(firsts) / pct(warm, 50):.2f}x (max) "
          f"| |")
    print(f"| server clock: submit -> claimed (queue wait) | {ms(pct(wait, 50))} | {ms(pct(wait, 95))} | {len(wait)} |")
    print(f"| server clock: time in the job process | {ms(pct(run, 50))} | {ms(pct(run, 95))} | {len(run)} |")
    print(f"| `calib_core.calibrate` alone, in-process (the floor) | {ms(statistics.median(compute))} | "
          f"{ms(max(compute))} (max) | {len(compute)} |")
    print(f"| `calib_core.calibrate` alone, CPU time (what the wall time is on an idle core) | "
          f"{ms(statistics.median(compute_cpu))} | {ms(max(compute_cpu))} (max) | {len(compute_cpu)} |")
    print(f"| overhead: warm latency - computation (p50s) | {ms(pct(warm, 50) - statistics.median(compute))} | | |")
    print(f"| `calib serve` start until /health answers (pool warm) | {statistics.median(startup):.1f} s | "
          f"{max(startup):.1f} s (max) | {len(startup)} |")
    if gaps:
        print(f"| progress change seen while an `auto` job runs ({auto_s:.1f} s) | every {ms(statistics.median(gaps))} "
              f"| longest gap {ms(max(gaps))} | {len(changes)} changes |")
    print(f"\nserver log: {log}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
