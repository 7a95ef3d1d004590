"""Fixtures for the service tests: real servers and workers in subprocesses, real databases.

Every API test talks HTTP to `python -m service.cli serve` on a free loopback port against a temporary SQLite
file (or the PostgreSQL server named by CALIB_TEST_POSTGRES_URL; those tests skip when it is unset).
"""
from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from service.demo_client import stop_process_group

from calib_core import Twin, parse_model, write_measurements
from calib_core.robots import spray7

ROOT = Path(__file__).resolve().parents[2]
PG_URL = os.environ.get("CALIB_TEST_POSTGRES_URL")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def base_env(db_url: str, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CALIB_")}
    env.update({"CALIB_DATABASE_URL": db_url, "CALIB_LEASE_SECONDS": "2", "CALIB_HEARTBEAT_SECONDS": "0.5",
                "CALIB_POLL_SECONDS": "0.1", "CALIB_RETRY_BACKOFF_SECONDS": "0.2", "PYTHONUNBUFFERED": "1"})
    env.update({k: str(v) for k, v in extra.items()})
    return env


class Proc:
    """A subprocess in its own process group (so SIGKILL takes its pool processes too, like a dead machine)."""

    def __init__(self, args: list[str], env: dict, log: Path):
        self.log = log
        self._fh = open(log, "ab")
        self.p = subprocess.Popen([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env,
                                  stdout=self._fh, stderr=subprocess.STDOUT, start_new_session=True)

    @property
    def pid(self) -> int:
        return self.p.pid

    def kill(self) -> None:
        """SIGKILL, no clean-up: what a power cut or the OOM killer does."""
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.p.wait(10)
        self._fh.close()

    def stop(self) -> None:
        stop_process_group(self.p, 15)
        self._fh.close()

    def output(self) -> str:
        return self.log.read_text(errors="replace")


class Server(Proc):
    def __init__(self, db_url: str, log: Path, **env):
        self.db_url = db_url
        for attempt in range(5):
            self.port = free_port()
            self.url = f"http://127.0.0.1:{self.port}"
            logged = log.stat().st_size if log.exists() else 0
            super().__init__(["serve", "--port", str(self.port)], base_env(db_url, **env), log)
            if self._started(logged, last=attempt == 4):
                break
        self.client = httpx.Client(base_url=self.url, timeout=30)

    def _started(self, logged: int, last: bool) -> bool:
        """Wait until the server answers. False if the free port was taken meanwhile (by a server another test
        process started, as on an xdist run): the caller tries another one."""
        deadline = time.monotonic() + 60
        while True:
            if self.p.poll() is not None:
                self._fh.close()
                out = self.log.read_bytes()[logged:].decode(errors="replace")
                if "address already in use" in out.lower() and not last:
                    return False
                raise RuntimeError("server exited:\n" + self.output())
            try:
                if self.ready():
                    return True
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("server did not start:\n" + self.output())
            time.sleep(0.1)

    def ready(self) -> bool:
        """Whether the server is up (an httpx.HTTPError counts as not yet)."""
        return httpx.get(self.url + "/health", timeout=2).status_code == 200

    def stop(self) -> None:
        if hasattr(self, "client"):
            self.client.close()
        super().stop()

    def kill(self) -> None:
        if hasattr(self, "client"):
            self.client.close()
        super().kill()


PROBLEM = "application/problem+json"


def assert_problem(r, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM), r.headers
    body = r.json()
    assert body["status"] == status and body["title"] and "type" in body
    return body


def sqlite_count(db_path: Path, table: str) -> int:
    with sqlite3.connect(db_path) as c:
        return c.execute(f"SELECT count(*) FROM {table}").fetchone()[0]


def wait_for(pred, timeout: float, what: str, interval: float = 0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="session")
def model_doc() -> dict:
    return spray7()


@pytest.fixture(scope="session")
def csv_text(model_doc) -> str:
    m = parse_model(model_doc)
    return write_measurements(Twin(m, 1).measure(n=150), m)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """One `calib serve` on a fresh SQLite file for every module that takes it, per test process (a server's start
    costs ~5 s of CPU: imports, the fork server's, warm job processes; once per module it was a tenth of the suite):
    a test may count rows before and after, never assume an empty database."""
    d = tmp_path_factory.mktemp("srv")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log")
    s.db_path = d / "calib.db"
    yield s
    s.stop()


def reset_postgres(url: str) -> None:
    from sqlalchemy import create_engine, text

    from service.cli import db_upgrade

    eng = create_engine(url)
    with eng.begin() as c:
        c.execute(text("DROP SCHEMA IF EXISTS public CASCADE"))
        c.execute(text("CREATE SCHEMA public"))
    eng.dispose()
    db_upgrade(url)


@pytest.fixture(params=["sqlite", "postgres"])
def db_url(request, tmp_path):
    """A fresh, migrated database of each kind."""
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'queue.db'}"
        from service.cli import db_upgrade
        db_upgrade(url)
        return url
    if not PG_URL:
        pytest.skip("CALIB_TEST_POSTGRES_URL is not set (.ci/run starts a PostgreSQL server)")
    reset_postgres(PG_URL)
    return PG_URL


@pytest.fixture(scope="session")
def motoman_demo(tmp_path_factory):
    """`calib demo` on the Motoman MA1400 (real laser-tracker data), run once for every test that reads its story:
    (stdout, stderr, folder with calib.db and motoman/model.json, measurements.csv)."""
    from calib_core import datasets

    from .test_demo import calib

    if not datasets.available():
        pytest.skip("the shared real datasets are not present")
    tmp = tmp_path_factory.mktemp("motoman")
    env = base_env(f"sqlite:///{tmp / 'calib.db'}")
    r = calib("convert-dataset", "motoman_leica", str(tmp / "motoman"), cwd=tmp, env=env)
    assert r.returncode == 0, r.stderr
    r = calib("demo", "--robot", str(tmp / "motoman" / "model.json"), "--data",
              str(tmp / "motoman" / "measurements.csv"), cwd=tmp, env=env)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    return r.stdout, r.stderr, tmp
