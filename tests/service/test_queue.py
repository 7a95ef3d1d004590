"""The durable queue against real databases (SQLite file and, when CALIB_TEST_POSTGRES_URL is set, PostgreSQL):
N workers and M jobs run each job exactly once; a worker killed with SIGKILL mid-job has its job finished by
another after the lease expires; a server killed and restarted loses nothing.

Job duration is stretched with CALIB_TEST_JOB_DELAY_S (read only by the worker, see service/queue/runner.py).
"""
from __future__ import annotations

import time

from sqlalchemy import func, select

from service.calibrations.models import Calibration
from service.db import Database
from service.jobs.models import Job
from service.jobs.service import enqueue
from service.measurements.service import create_measurement_set
from service.queue import store
from service.robots.service import create_robot

from .conftest import Proc, Server, base_env, wait_for


def seed(url: str, model_doc: dict, csv_text: str, n_jobs: int) -> tuple[Database, list[str]]:
    db = Database(url)
    with db.session() as s:
        rid = create_robot(s, model_doc).id
    ms = create_measurement_set(db, rid, csv_text.encode(), "queue.csv")
    with db.session() as s:
        ids = [enqueue(s, ms.id, "geometric", 3).id for _ in range(n_jobs)]
    return db, ids


def jobs(db: Database, ids: list[str]) -> list[Job]:
    with db.session() as s:
        return list(s.scalars(select(Job).where(Job.id.in_(ids))))


def all_done(db, ids):
    js = jobs(db, ids)
    return js if all(j.status in ("succeeded", "failed") for j in js) else None


def calibrations_per_job(db: Database) -> dict[str, int]:
    with db.session() as s:
        return dict(s.execute(select(Calibration.job_id, func.count()).group_by(Calibration.job_id)).all())


def test_n_workers_m_jobs_each_exactly_once(db_url, model_doc, csv_text, tmp_path):
    n_workers, m_jobs = 3, 12
    db, ids = seed(db_url, model_doc, csv_text, m_jobs)
    workers = [Proc(["worker", "--concurrency", "1"], base_env(db_url, CALIB_TEST_JOB_DELAY_S=0.3),
                    tmp_path / f"worker{i}.log") for i in range(n_workers)]
    try:
        done = wait_for(lambda: all_done(db, ids), 120, "all jobs to finish", interval=0.3)
    finally:
        for w in workers:
            w.stop()
    assert [j.status for j in done] == ["succeeded"] * m_jobs, [(j.status, j.error) for j in done]
    assert all(j.attempts == 1 for j in done), [j.attempts for j in done]  # claimed once each
    per_job = calibrations_per_job(db)
    assert per_job == {i: 1 for i in ids}  # one result per job
    with db.session() as s:
        used = set(s.scalars(select(Calibration.worker)))
    assert len(used) >= 2, used  # the work was shared
    db.dispose()


def test_sigkilled_worker_job_finished_by_another(db_url, model_doc, csv_text, tmp_path):
    db, (job_id,) = seed(db_url, model_doc, csv_text, 1)
    a = Proc(["worker", "--concurrency", "1"], base_env(db_url, CALIB_TEST_JOB_DELAY_S=60), tmp_path / "a.log")
    b = None
    try:
        j = wait_for(lambda: (x := jobs(db, [job_id])[0]).status == "running" and x, 60, "worker A to claim")
        assert f":{a.pid}:" in j.lease_owner
        wait_for(lambda: jobs(db, [job_id])[0].progress > 0, 30, "progress from worker A")
        a.kill()  # SIGKILL the worker and its pool: no clean-up, the lease just stops being renewed
        t_kill = time.monotonic()
        b = Proc(["worker", "--concurrency", "1"], base_env(db_url, CALIB_TEST_JOB_DELAY_S=0.5), tmp_path / "b.log")
        (j,) = wait_for(lambda: all_done(db, [job_id]), 90, "worker B to finish the job")
        assert time.monotonic() - t_kill >= 1.5  # not before the 2 s lease expired
    finally:
        a.stop()
        if b is not None:
            b.stop()
    assert j.status == "succeeded", (j.status, j.error)
    assert j.attempts == 2
    assert f":{b.pid}:" in j.lease_owner
    assert calibrations_per_job(db) == {job_id: 1}
    db.dispose()


def test_stale_worker_cannot_write_a_result(db_url, model_doc, csv_text):
    db, (job_id,) = seed(db_url, model_doc, csv_text, 1)
    c1 = store.claim(db, "worker-a", lease_seconds=0.05)
    assert c1 is not None and store.claim(db, "worker-b", 5) is None  # nothing else to claim
    time.sleep(0.1)
    assert store.reap(db) == (1, 0)
    c2 = store.claim(db, "worker-b", 5)
    assert c2 is not None and c2.job_id == job_id and c2.attempt == 2
    assert not store.heartbeat(db, job_id, "worker-a", 5)  # A learns it lost the lease
    assert store.complete(db, c1, "worker-a", {"model": ["geometric"]}, {}) is None
    assert not store.fail(db, job_id, "worker-a", "late", retry=False)
    cid = store.complete(db, c2, "worker-b", {"model": ["geometric"]}, {})
    assert cid is not None
    assert store.complete(db, c2, "worker-b", {"model": ["geometric"]}, {}) is None  # written once
    (j,) = jobs(db, [job_id])
    assert j.status == "succeeded" and j.calibration_id == cid
    assert calibrations_per_job(db) == {job_id: 1}
    db.dispose()


def test_infrastructure_failures_retry_numerical_do_not(db_url, model_doc, csv_text):
    db, (a, b) = seed(db_url, model_doc, csv_text, 2)
    c = store.claim(db, "w", 5)
    assert store.fail(db, c.job_id, "w", "pool died", retry=True, backoff_seconds=0)
    (j,) = jobs(db, [c.job_id])
    assert j.status == "queued" and j.attempts == 1
    c = store.claim(db, "w", 5)
    c = c if c.job_id == j.id else store.claim(db, "w", 5)
    store.fail(db, c.job_id, "w", "need at least 3 poses, got 2", retry=False)
    (j,) = jobs(db, [c.job_id])
    assert j.status == "failed" and "poses" in j.error
    db.dispose()


def test_server_killed_and_restarted_loses_nothing(db_url, model_doc, csv_text, tmp_path):
    env = dict(CALIB_TEST_JOB_DELAY_S=3, CALIB_WORKER_CONCURRENCY=1)
    s = Server(db_url, tmp_path / "server1.log", **env)
    c = s.client
    rid = c.post("/robots", json=model_doc).json()["id"]
    sets = [_ok(c.post(f"/robots/{rid}/measurements", files={"file": (f"{k}.csv", csv_text)}))["id"]
            for k in range(3)]
    job_ids = [c.post("/jobs", json={"measurement_set_id": sets[k % 3], "model": "geometric"}).json()["id"]
               for k in range(4)]
    wait_for(lambda: any(c.get(f"/jobs/{j}").json()["status"] == "running" for j in job_ids), 60, "a running job")
    s.kill()  # SIGKILL mid-job: the API, the dispatcher and its pool die together
    s2 = Server(db_url, tmp_path / "server2.log", CALIB_WORKER_CONCURRENCY=2)
    try:
        c = s2.client
        assert c.get(f"/robots/{rid}").status_code == 200
        for m in sets:
            assert c.get(f"/measurements/{m}").json()["n_poses"] == 150
        done = wait_for(lambda: (js := [c.get(f"/jobs/{j}").json() for j in job_ids])
                        and all(j["status"] == "succeeded" for j in js) and js, 90, "all jobs after the restart")
        assert max(j["attempts"] for j in done) == 2  # the interrupted job ran again
        cal_ids = {j["calibration_id"] for j in done}
        assert len(cal_ids) == 4 and all(c.get(f"/calibrations/{i}").status_code == 200 for i in cal_ids)
    finally:
        s2.stop()
    db = Database(db_url)
    assert calibrations_per_job(db) == {j: 1 for j in job_ids}
    db.dispose()


def _ok(r) -> dict:
    assert r.status_code < 300, r.text
    return r.json()
