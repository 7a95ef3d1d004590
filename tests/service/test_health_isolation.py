"""/health stays answerable under the red team's load (issue 10, docs/RESULTS.md 2.4), over real HTTP against
`calib serve`: an oversized predict/compensate is refused with 413 before its JSON is parsed (the 100k-row body
used to be validated on the event loop, 0.1-0.4 s each, stalling everything), and /health runs in threads of
its own, so it answers while every thread of the routes' shared pool is busy."""
from __future__ import annotations

import json
import sqlite3
import statistics
import threading
import time

import httpx
import pytest

from service.limits import MAX_PREDICT_BYTES, MAX_PREDICT_ROWS

from .conftest import PROBLEM, Server, assert_problem

POSE = [2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]
J = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    d = tmp_path_factory.mktemp("health")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log", CALIB_EMBEDDED_WORKERS="0")
    s.db_path = d / "calib.db"
    yield s
    s.stop()


def test_predict_over_the_row_limit_is_413_naming_count_and_maximum(srv):
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [["x"]] * 100_000})
    body = assert_problem(r, 413)
    assert body["items"] == 100_000 and body["max_rows"] == MAX_PREDICT_ROWS and body["field"] == "body.joints"
    assert "100000" in body["detail"] and str(MAX_PREDICT_ROWS) in body["detail"], body
    assert len(r.content) < 2048

    r = srv.client.post("/calibrations/nope/compensate",
                        json={"targets": [[0.0, 0.0, 0.0]], "seed_joints": [POSE] * (MAX_PREDICT_ROWS + 1)})
    body = assert_problem(r, 413)
    assert body["items"] == MAX_PREDICT_ROWS + 1 and body["field"] == "body.seed_joints", body
    # per-pose lists count too, and so do the members of an object (one pydantic error each)
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [POSE], "payload": [1.0] * 20_000})
    assert assert_problem(r, 413)["field"] == "body.payload"
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [POSE], **{f"k{i}": 1 for i in range(20_000)}})
    assert assert_problem(r, 413)["items"] == 20_001


def test_at_the_row_limit_the_request_goes_on_to_validation(srv):
    """Exactly MAX_PREDICT_ROWS rows: not refused at the edge; a missing calibration is then a 404, and a bad
    value a 422 naming the field, as before."""
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [POSE] * MAX_PREDICT_ROWS})
    assert_problem(r, 404)
    # commas inside strings are not items
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [POSE], "timestamp": "," * 50_000})
    assert r.status_code in (404, 422) and r.status_code != 413, r.text
    r = srv.client.post("/calibrations/nope/predict", json={"joints": [POSE] * 9_999 + [["x"] * 7]})
    body = assert_problem(r, 422)
    assert body["errors"][0]["field"].startswith("body.joints"), body


def test_oversized_predict_is_refused_without_being_parsed(srv):
    """The body is not JSON past its rows: a parser would answer 422 'not valid JSON'; the edge answers 413
    from the row count alone. A body over MAX_PREDICT_BYTES is refused from its Content-Length."""
    raw = b'{"joints": [' + b'["x"],' * (MAX_PREDICT_ROWS + 5) + b"}}} this is not JSON"
    r = srv.client.post("/calibrations/nope/predict", content=raw, headers=J)
    body = assert_problem(r, 413)
    assert body["items"] >= MAX_PREDICT_ROWS + 5, body
    r = srv.client.post("/calibrations/nope/compensate", content=b" " * (MAX_PREDICT_BYTES + 1), headers=J)
    body = assert_problem(r, 413)
    assert str(MAX_PREDICT_BYTES) in body["detail"], body
    assert srv.client.get("/health").status_code == 200


def test_health_answers_while_oversized_predicts_are_in_flight(srv):
    """Six clients send 100k-row predicts back to back while /health is polled: every poll answers well within
    a second (each such request cost the event loop 0.1-0.4 s of validation before the edge refused it)."""
    big = json.dumps({"joints": [["x"]] * 100_000}).encode()
    idle = []
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        for _ in range(5):
            t = time.perf_counter()
            assert c.get("/health").status_code == 200
            idle.append(time.perf_counter() - t)
    stop, codes, started = threading.Event(), [], threading.Barrier(7)

    def flood():
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            started.wait()
            while not stop.is_set():
                codes.append(c.post("/calibrations/nope/predict", content=big, headers=J).status_code)

    threads = [threading.Thread(target=flood, daemon=True) for _ in range(6)]
    for t in threads:
        t.start()
    lat = []
    try:
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            started.wait()
            deadline = time.monotonic() + 4.0
            while time.monotonic() < deadline or len(codes) < 12:
                t = time.perf_counter()
                assert c.get("/health").status_code == 200
                lat.append(time.perf_counter() - t)
                time.sleep(0.05)
                if time.monotonic() > deadline + 30:
                    break
    finally:
        stop.set()
        for t in threads:
            t.join(60)
    assert len(codes) >= 12 and set(codes) == {413}, codes
    base = statistics.median(idle)
    assert max(lat) < base + 1.0, (f"/health under load: max {max(lat):.3f} s, median {statistics.median(lat):.3f} s "
                                   f"({len(lat)} polls, {len(codes)} predicts); idle {base:.3f} s")


def test_health_does_not_wait_for_the_routes_thread_pool(srv, model_doc):
    """Every thread of the routes' shared pool (CALIB_ROUTE_THREADS, 4) is a write waiting for the SQLite write
    lock, which this test holds, and more writes queue for them: /health (a read, in threads of its own) still
    answers, before any of those writes can complete."""
    n = 24
    lock = sqlite3.connect(srv.db_path, timeout=30, isolation_level=None)
    lock.execute("BEGIN IMMEDIATE")  # WAL: readers go on, every writer waits (busy timeout 30 s)
    results: list[int] = []
    done = threading.Event()

    def write(k: int):
        with httpx.Client(base_url=srv.url, timeout=90) as c:
            results.append(c.post("/robots", json={**model_doc, "name": f"blocked-{k}"}).status_code)
            if len(results) == n:
                done.set()

    threads = [threading.Thread(target=write, args=(k,), daemon=True) for k in range(n)]
    try:
        for t in threads:
            t.start()
        time.sleep(2.0)  # the writes are in: their threads wait on the lock
        t0 = time.perf_counter()
        r = httpx.get(srv.url + "/health", timeout=25)
        took = time.perf_counter() - t0
        assert r.status_code == 200 and r.json()["status"] == "ok", r.text
        assert not results, f"writes completed while the lock was held: {results}"
        assert took < 5.0, f"/health took {took:.2f} s with the routes' pool busy"
    finally:
        lock.execute("ROLLBACK")
        lock.close()
    assert done.wait(60), results
    assert sorted(set(results)) == [201], results
    r = srv.client.get("/health")
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/json")
    assert not r.headers["content-type"].startswith(PROBLEM)
