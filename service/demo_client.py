"""`calib demo`'s HTTP side: the `calib serve` it starts and stops, and the client of the API's calls."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np

from calib_core.io import Measurements
from calib_core.model import LENGTH_TO_MM, RobotModel

from .demo_campaign import _commands, _groups, _pose_fields
from .demo_console import DemoError, ProgressBar


# ----------------------------------------------------------------------------------------------- server

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Server:
    """`calib serve` in a subprocess (its own process group) on a free loopback port."""

    proc: subprocess.Popen
    url: str
    log: Path

    @classmethod
    def start(cls, database_url: str, log: Path, timeout: float = 60.0) -> "Server":
        port = free_port()
        env = {k: v for k, v in os.environ.items() if k not in ("CALIB_TEST_JOB_DELAY_S",)}
        env.update({"CALIB_DATABASE_URL": database_url, "CALIB_EMBEDDED_WORKERS": "1", "CALIB_POLL_SECONDS": "0.1",
                    "CALIB_HEARTBEAT_SECONDS": "0.5",  # the worker writes progress with its heartbeat
                    "PYTHONUNBUFFERED": "1"})
        fh = open(log, "ab")
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "--log-level", "WARNING", "serve",
                                 "--host", "127.0.0.1", "--port", str(port)], env=env, stdout=fh,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        fh.close()
        server = cls(proc, f"http://127.0.0.1:{port}", log)
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                raise DemoError(f"calib serve exited (status {proc.returncode}):\n{server.tail()}")
            try:
                if httpx.get(server.url + "/health", timeout=2).status_code == 200:
                    return server
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                server.stop()
                raise DemoError(f"calib serve did not answer within {timeout:.0f} s:\n{server.tail()}")
            time.sleep(0.1)

    def tail(self, n: int = 30) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def stop(self) -> None:
        stop_process_group(self.proc, 20)


def stop_process_group(proc: subprocess.Popen, grace_s: float) -> None:
    """SIGTERM a server started in its own process group, SIGKILL it if it outlives grace_s."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
    except ProcessLookupError:
        pass


class Api:
    """The few REST calls of the story, with problem documents turned into DemoError."""

    def __init__(self, url: str, token: str | None, job_wait_s: float = 600.0):
        """job_wait_s: how long `wait` waits for a job; the server's own job time limit plus the queue's time
        (a client limit below the server's cut an hour-long job at 600 s)."""
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.refused: list[str] = []  # every call the service answered with a 4xx or 5xx: 'POST /path -> 422'
        self.c = httpx.Client(base_url=url, timeout=120, headers=headers, event_hooks={"response": [self._seen]})
        self.job_wait_s = job_wait_s

    def _seen(self, r: httpx.Response) -> None:
        if r.status_code >= 400:
            self.refused.append(f"{r.request.method} {r.request.url.path} -> {r.status_code}")

    def close(self) -> None:
        self.c.close()

    def call(self, method: str, path: str, expect: tuple[int, ...] = (200,), **kw) -> httpx.Response:
        r = self.c.request(method, path, **kw)
        if r.status_code not in expect:
            try:
                body = r.json()
                detail = body.get("detail") or body
                errors = body.get("errors") or []
            except ValueError:
                detail, errors = r.text[:500], []
            more = "".join(f"\n    {e}" for e in errors[:10])
            raise DemoError(f"{method} {path} answered {r.status_code}: {detail}{more}")
        return r

    def submit(self, ms_id: str, mode: str) -> str:
        return self.call("POST", "/jobs", (202,), json={"measurement_set_id": ms_id, "model": mode}).headers["location"]

    def wait(self, loc: str, bar: ProgressBar | None = None) -> dict:
        timeout = self.job_wait_s
        deadline = time.monotonic() + timeout
        try:
            while True:
                j = self.call("GET", loc).json()
                if bar is not None:
                    bar.update(j["progress"], j.get("message") or j["status"])
                if j["status"] == "succeeded":
                    return j
                if j["status"] == "failed":
                    raise DemoError(f"the {j['model']} job failed: {j.get('error')}")
                if time.monotonic() > deadline:
                    raise DemoError(f"the {j['model']} job did not finish within {timeout:.0f} s")
                time.sleep(0.2)
        finally:
            if bar is not None:
                bar.close()

    def predict_mm(self, cal_id: str, model: RobotModel, meas: Measurements) -> np.ndarray:
        """Positions (N, 3) in mm predicted by the service for the poses of `meas` (internal units), each with what
        its CSV row says (_pose_fields; one request per setup)."""
        out = np.empty((meas.n_poses, 3))
        for rows in _groups(meas):
            body = {"joints": _commands(model, meas.joints[rows]).tolist(), **_pose_fields(model, meas, rows)}
            if meas.payload is not None:
                body["payload"] = meas.payload[rows].tolist()
            r = self.call("POST", f"/calibrations/{cal_id}/predict", json=body).json()
            out[rows] = np.asarray(r["positions"], float) * LENGTH_TO_MM[model.length_unit]
        return out
