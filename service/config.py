"""Settings from the environment. Every knob is an env var so one image runs on a laptop or a cluster."""
from __future__ import annotations

import os
from dataclasses import dataclass, field


def _float(name: str, default: float) -> float:
    return float(os.environ.get(name, default))


def _int(name: str, default: int) -> int:
    return int(os.environ.get(name, default))


def default_diagnosis_workers() -> int:
    """CALIB_DIAGNOSIS_WORKERS' default: an auto job's diagnosis runs its independent parts (play searches, rival
    fits, screening) in up to 2 processes, 1 on a one-core machine (calib_core/parallel.py)."""
    return max(1, min(2, os.cpu_count() or 1))


def default_processes() -> int:
    """A lane's processes sized to the machine: half its cores (the API process, the job processes and the other
    lanes need the rest), at least 1, at most 4 (service/lanes.py)."""
    return max(1, min(4, (os.cpu_count() or 2) // 2))


PARSE_ROOM_UPLOADS = 8
"""CALIB_PARSE_ROOM_BYTES' default: this many uploads of the largest size allowed (service/measurements/service.py)."""
PLAN_ROOM_PER_PROCESS = 4
"""CALIB_PLAN_ROOM's default: this many plans waiting per plan process (service/plans/pool.py)."""


@dataclass(frozen=True)
class Settings:
    database_url: str = "sqlite:///./calib.db"
    api_token: str | None = None  # when set, every call but /health needs "Authorization: Bearer <token>"
    api_token_set: bool = False  # CALIB_API_TOKEN is in the environment, even empty (then `calib serve` refuses)
    max_upload_bytes: int = 20 * 1024 * 1024  # any request body above this gets 413
    lease_seconds: float = 30.0  # a running job whose lease is not renewed for this long is re-queued
    heartbeat_seconds: float = 10.0
    poll_seconds: float = 0.5  # idle worker poll interval
    max_attempts: int = 3  # infrastructure retries (worker died, pool broke); numerical failures fail at once
    retry_backoff_seconds: float = 1.0
    worker_concurrency: int = 2  # processes in a worker's pool = jobs run at once
    embedded_workers: bool = True  # `calib serve` runs a dispatcher in-process
    test_job_delay_s: float = 0.0  # CALIB_TEST_JOB_DELAY_S: tests only, makes a job last longer (see queue/runner.py)
    job_timeout_s: float = 600.0  # CALIB_JOB_TIMEOUT_S: a job running longer (summed over attempts) fails, its process killed
    progress_seconds: float = 0.5  # CALIB_PROGRESS_SECONDS: a running job's progress row is written this often
    diagnosis_workers: int = 1  # CALIB_DIAGNOSIS_WORKERS: processes of one auto job's diagnosis (default: 2, 1 on
    # one core; at most the cores; its forked helpers share the job's niceness and die with its process)
    job_nice: int = 10  # CALIB_JOB_NICE: the job processes' niceness (0-19): identification is batch work, the API and
    # its lanes answer people (a red team's load with jobs running: /health p99 230 ms at 0)
    warm_pool: bool = True  # CALIB_WARM_POOL: start the job processes (imports, one tiny calibration) before serving
    warmup_timeout_s: float = 30.0  # CALIB_WARMUP_TIMEOUT_S: `calib serve` waits at most this long for a warm pool
    test_poison: bool = False  # CALIB_TEST_POISON: tests only, CSV comment markers make a job crash or spin (runner.py)
    route_threads: int = 4  # CALIB_ROUTE_THREADS: the API's sync routes run at most this many at once (see app.py;
    # 8 before: the red team's load answered as many requests with 4, /health p99 168-216 -> 156-163 ms)
    switch_interval_ms: float = 1.0  # CALIB_SWITCH_INTERVAL_MS: the API process's GIL switch interval (see app.py)
    parse_processes: int = 1  # CALIB_PARSE_PROCESSES: large uploads' CSVs are checked in this many processes, small
    # ones in one of their own (0: in the API); default: half the cores, 1-4 (lanes.default_processes)
    parse_timeout_s: float = 120.0  # CALIB_PARSE_TIMEOUT_S: a CSV check running longer is stopped (503)
    parse_room_bytes: int = PARSE_ROOM_UPLOADS * 20 * 1024 * 1024  # CALIB_PARSE_ROOM_BYTES: large uploads (over 1 MiB)
    # waiting for a parse process hold at most this many bytes; more: 503 (default: 8 x CALIB_MAX_UPLOAD_BYTES)
    plan_processes: int = 1  # CALIB_PLAN_PROCESSES: plans run in this many processes (0: in the API)
    plan_room: int = PLAN_ROOM_PER_PROCESS  # CALIB_PLAN_ROOM: plans waiting for a plan process at most; more: 503
    # (default: 4 per plan process)
    plan_timeout_s: float = 60.0  # CALIB_PLAN_TIMEOUT_S: a plan running longer is stopped (503), its process replaced
    compute_processes: int = 1  # CALIB_COMPUTE_PROCESSES: predict and compensate run in this many processes (0: in
    # the API); default: half the cores, 1-4
    compute_timeout_s: float = 60.0  # CALIB_COMPUTE_TIMEOUT_S: a predict or compensate running longer is stopped (503)
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_env(cls) -> "Settings":
        lease = _float("CALIB_LEASE_SECONDS", 30.0)
        max_upload = _int("CALIB_MAX_UPLOAD_BYTES", 20 * 1024 * 1024)
        plan_processes = max(0, _int("CALIB_PLAN_PROCESSES", 1))
        return cls(
            database_url=os.environ.get("CALIB_DATABASE_URL", "sqlite:///./calib.db"),
            api_token=os.environ.get("CALIB_API_TOKEN") or None,
            api_token_set="CALIB_API_TOKEN" in os.environ,
            max_upload_bytes=max_upload,
            lease_seconds=lease,
            heartbeat_seconds=_float("CALIB_HEARTBEAT_SECONDS", max(0.2, lease / 3)),
            poll_seconds=_float("CALIB_POLL_SECONDS", 0.5),
            job_nice=min(19, max(0, _int("CALIB_JOB_NICE", 10))),
            diagnosis_workers=min(max(1, _int("CALIB_DIAGNOSIS_WORKERS", default_diagnosis_workers())),
                                  os.cpu_count() or 1),  # more processes than cores only add forks
            max_attempts=_int("CALIB_MAX_ATTEMPTS", 3),
            retry_backoff_seconds=_float("CALIB_RETRY_BACKOFF_SECONDS", 1.0),
            worker_concurrency=_int("CALIB_WORKER_CONCURRENCY", 2),
            embedded_workers=os.environ.get("CALIB_EMBEDDED_WORKERS", "1").lower() not in ("0", "false", "no"),
            test_job_delay_s=_float("CALIB_TEST_JOB_DELAY_S", 0.0),
            job_timeout_s=max(0.1, _float("CALIB_JOB_TIMEOUT_S", 600.0)),
            progress_seconds=min(1.0, max(0.05, _float("CALIB_PROGRESS_SECONDS", 0.5))),
            warm_pool=os.environ.get("CALIB_WARM_POOL", "1").lower() not in ("0", "false", "no"),
            warmup_timeout_s=_float("CALIB_WARMUP_TIMEOUT_S", 30.0),
            test_poison=os.environ.get("CALIB_TEST_POISON", "").lower() in ("1", "true", "yes"),
            route_threads=max(1, _int("CALIB_ROUTE_THREADS", 4)),
            switch_interval_ms=min(100.0, max(0.1, _float("CALIB_SWITCH_INTERVAL_MS", 1.0))),
            parse_processes=max(0, _int("CALIB_PARSE_PROCESSES", default_processes())),
            parse_timeout_s=max(0.1, _float("CALIB_PARSE_TIMEOUT_S", 120.0)),
            parse_room_bytes=max(1, _int("CALIB_PARSE_ROOM_BYTES", PARSE_ROOM_UPLOADS * max(1, max_upload))),
            plan_processes=plan_processes,
            plan_room=max(0, _int("CALIB_PLAN_ROOM", PLAN_ROOM_PER_PROCESS * plan_processes)),
            plan_timeout_s=max(0.1, _float("CALIB_PLAN_TIMEOUT_S", 60.0)),
            compute_processes=max(0, _int("CALIB_COMPUTE_PROCESSES", default_processes())),
            compute_timeout_s=max(0.1, _float("CALIB_COMPUTE_TIMEOUT_S", 60.0)),
        )

    @property
    def is_sqlite(self) -> bool:
        return self.database_url.startswith("sqlite")


class ConfigurationError(SystemExit):
    """A setting the service refuses to start with; the message is printed and the process exits with 1."""


def check_token_setting(settings: Settings) -> None:
    """Refuse CALIB_API_TOKEN set to nothing (or white space): it would silently switch authentication off."""
    token = settings.api_token
    if (token is None and settings.api_token_set) or (token is not None and not token.strip()):
        raise ConfigurationError("calib: CALIB_API_TOKEN is set but empty: refusing to start without the "
                                 "authentication it asks for. Set it to a token, or unset it (unset, the API "
                                 "asks for no token).")
    if token is not None and token != token.strip():
        raise ConfigurationError("calib: CALIB_API_TOKEN starts or ends with white space, which an HTTP header "
                                 "cannot carry (no client could authenticate): remove it.")
