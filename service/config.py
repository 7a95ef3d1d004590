"""Settings from the environment. Every knob is an env var so one image runs on a laptop or a cluster."""
from __future__ import annotations

import os
from dataclasses import dataclass, field


def _float(name: str, default: float) -> float:
    return float(os.environ.get(name, default))


def _int(name: str, default: int) -> int:
    return int(os.environ.get(name, default))


@dataclass(frozen=True)
class Settings:
    database_url: str = "sqlite:///./calib.db"
    api_token: str | None = None  # when set, writing calls need "Authorization: Bearer <token>"
    max_upload_bytes: int = 20 * 1024 * 1024  # any request body above this gets 413
    lease_seconds: float = 30.0  # a running job whose lease is not renewed for this long is re-queued
    heartbeat_seconds: float = 10.0
    poll_seconds: float = 0.5  # idle worker poll interval
    max_attempts: int = 3  # infrastructure retries (worker died, pool broke); numerical failures fail at once
    retry_backoff_seconds: float = 1.0
    worker_concurrency: int = 2  # processes in a worker's pool = jobs run at once
    embedded_workers: bool = True  # `calib serve` runs a dispatcher in-process
    test_job_delay_s: float = 0.0  # CALIB_TEST_JOB_DELAY_S: tests only, makes a job last longer (see queue/runner.py)
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_env(cls) -> "Settings":
        lease = _float("CALIB_LEASE_SECONDS", 30.0)
        return cls(
            database_url=os.environ.get("CALIB_DATABASE_URL", "sqlite:///./calib.db"),
            api_token=os.environ.get("CALIB_API_TOKEN") or None,
            max_upload_bytes=_int("CALIB_MAX_UPLOAD_BYTES", 20 * 1024 * 1024),
            lease_seconds=lease,
            heartbeat_seconds=_float("CALIB_HEARTBEAT_SECONDS", max(0.2, lease / 3)),
            poll_seconds=_float("CALIB_POLL_SECONDS", 0.5),
            max_attempts=_int("CALIB_MAX_ATTEMPTS", 3),
            retry_backoff_seconds=_float("CALIB_RETRY_BACKOFF_SECONDS", 1.0),
            worker_concurrency=_int("CALIB_WORKER_CONCURRENCY", 2),
            embedded_workers=os.environ.get("CALIB_EMBEDDED_WORKERS", "1").lower() not in ("0", "false", "no"),
            test_job_delay_s=_float("CALIB_TEST_JOB_DELAY_S", 0.0),
        )

    @property
    def is_sqlite(self) -> bool:
        return self.database_url.startswith("sqlite")
