"""Issue 33 over real HTTP against `calib serve` (SQLite): a lone surrogate in any JSON string is a 422 naming the
field with nothing stored (it used to be a 500 after storing the robot, then every `GET /robots` answered 500), and
an operator's `DELETE /robots/{id}` and `DELETE /measurements/{id}` (contract section 3): 204 with everything made
from it, 404 when absent, 409 while a queued or running job uses it."""
from __future__ import annotations

import copy
import json
import sqlite3
import time

import pytest

from .conftest import Server, assert_problem, sqlite_count, wait_for

TABLES = ("robots", "measurement_sets", "jobs", "calibrations", "calibration_plots")


def counts(server) -> dict[str, int]:
    return {t: sqlite_count(server.db_path, t) for t in TABLES}


def post_raw(server, path: str, doc) -> "object":
    """`doc` as JSON text the way a client escapes a lone surrogate (Python's json.dumps writes `\\ud800`)."""
    return server.client.post(path, content=json.dumps(doc).encode("ascii"), headers={"content-type": "application/json"})


def _with(model_doc: dict, edit) -> dict:
    doc = copy.deepcopy(model_doc)
    edit(doc)
    return doc


SURROGATE_MODELS = {
    "name": (lambda d: d.update(name="spray\ud800"), "body.name"),
    "joint_name": (lambda d: d["joints"][2].update(name="J\udc003"), "body.joints[2].name"),
    "meta_value": (lambda d: d.update(meta={"cell": "north", "note": "\udbff"}), "body.meta.note"),
    "meta_key": (lambda d: d.update(meta={"k\ud800": 1}), "body.meta"),
    "unknown_key": (lambda d: d.update({"colour\udfff": "red"}), "body"),
    "target_name": (lambda d: d.update(targets=[{"name": "\ud834", "parent": "J7", "xyz": [250, 0, 80]}]),
                    "body.targets[0].name"),
}


@pytest.mark.parametrize("case", sorted(SURROGATE_MODELS))
def test_a_lone_surrogate_in_a_model_is_422_naming_the_field_nothing_stored(server, model_doc, case):
    edit, field = SURROGATE_MODELS[case]
    before = counts(server)
    body = assert_problem(post_raw(server, "/robots", _with(model_doc, edit)), 422)
    assert [e["field"] for e in body["errors"]] == [field], body
    assert "\\u" in body["errors"][0]["value"] and "surrogate" in body["errors"][0]["message"], body
    assert "nothing was stored" in body["detail"], body
    assert counts(server) == before
    r = server.client.get("/robots")
    assert r.status_code == 200, r.text


@pytest.mark.parametrize("path, raw, field", [
    ("/jobs", b'{"measurement_set_id": "\\ud800", "model": "geometric"}', "body.measurement_set_id"),
    ("/jobs", b'{"measurement_set_id": "x", "model": "auto\\udc00"}', "body.model"),
    ("/calibrations/nope/predict", b'{"joints": [[1, "\\ud800"]]}', "body.joints[0][1]"),
    ("/calibrations/nope/compensate", b'{"targets": [[0, 0, 0]], "seed_joints": [["\\udfff"]]}',
     "body.seed_joints[0][0]"),
    ("/robots/nope/plan", b'{"n_poses": 10, "purpose": "geometric\\ud800"}', "body.purpose"),
])
def test_a_lone_surrogate_in_any_json_body_is_422(server, path, raw, field):
    before = counts(server)
    body = assert_problem(server.client.post(path, content=raw, headers={"content-type": "application/json"}), 422)
    assert [e["field"] for e in body["errors"]] == [field], body
    assert counts(server) == before


def test_a_surrogate_pair_is_a_character_and_is_kept(server, model_doc):
    doc = _with(model_doc, lambda d: d.update(name="spray \U0001F527", meta={"note": "\U0001F600"}))
    raw = json.dumps(doc).encode("ascii")
    assert b"\\ud83d\\udd27" in raw  # the pair as a client escapes it
    r = server.client.post("/robots", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 201, r.text
    got = server.client.get(f"/robots/{r.json()['id']}").json()
    assert got["name"] == "spray \U0001F527" and got["model"]["meta"] == {"note": "\U0001F600"}


def test_a_robot_stored_with_a_lone_surrogate_before_is_listed_and_deletable(server, model_doc):
    """A database written before the fix: the robot answers (the surrogate written as its escape) instead of
    making every `GET /robots` a 500, and the operator can delete it."""
    doc = _with(model_doc, lambda d: d["joints"][0].update(name="J\ud8001"))
    rid = "00000000-0000-4000-8000-0000000000bd"
    with sqlite3.connect(server.db_path) as c:
        c.execute("INSERT INTO robots (id, name, model_json, joint_names, created_at) VALUES (?, ?, ?, ?, ?)",
                  (rid, "legacy", json.dumps(doc), json.dumps([j["name"] for j in doc["joints"]]), time.time()))
    r = server.client.get("/robots", params={"limit": 1000})
    assert r.status_code == 200, r.text
    (got,) = [x for x in r.json() if x["id"] == rid]
    assert got["joint_names"][0] == "J\\ud8001" and got["model"]["joints"][0]["name"] == "J\\ud8001", got
    assert server.client.get(f"/robots/{rid}").status_code == 200
    assert server.client.delete(f"/robots/{rid}").status_code == 204
    assert_problem(server.client.get(f"/robots/{rid}"), 404)
    assert server.client.get("/robots").status_code == 200


# ------------------------------------------------------------------------------------------------------- DELETE

def _robot(server, model_doc) -> str:
    r = server.client.post("/robots", json=model_doc)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _set(server, rid: str, csv_text: str) -> str:
    r = server.client.post(f"/robots/{rid}/measurements", files={"file": ("d.csv", csv_text, "text/csv")})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _job(server, ms: str) -> str:
    r = server.client.post("/jobs", json={"measurement_set_id": ms, "model": "geometric"})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def _finished(server, job: str) -> dict:
    def done():
        j = server.client.get(f"/jobs/{job}").json()
        return j if j["status"] in ("succeeded", "failed") else None

    j = wait_for(done, 90, "the job")
    assert j["status"] == "succeeded", j
    return j


def test_delete_a_measurement_set_takes_its_calibrations_and_leaves_the_robot(server, model_doc, csv_text):
    rid = _robot(server, model_doc)
    keep, gone = _set(server, rid, csv_text), _set(server, rid, csv_text)
    kept_cal = _finished(server, _job(server, keep))["calibration_id"]
    job = _job(server, gone)
    cal = _finished(server, job)["calibration_id"]
    with sqlite3.connect(server.db_path) as c:  # an auto job's stored plot (geometric jobs draw none)
        c.execute("INSERT INTO calibration_plots (calibration_id, name, png, created_at) VALUES (?, ?, ?, ?)",
                  (cal, "errors", b"\x89PNG", time.time()))
    before = counts(server)
    r = server.client.delete(f"/measurements/{gone}")
    assert r.status_code == 204 and r.content == b"", r.text
    after = counts(server)
    gone_n = {t: before[t] - after[t] for t in TABLES}
    assert gone_n == {"robots": 0, "measurement_sets": 1, "jobs": 1, "calibrations": 1, "calibration_plots": 1}
    for path in (f"/measurements/{gone}", f"/jobs/{job}", f"/calibrations/{cal}", f"/calibrations/{cal}/report"):
        assert_problem(server.client.get(path), 404)
    assert_problem(server.client.delete(f"/measurements/{gone}"), 404)  # a second DELETE
    assert server.client.get(f"/robots/{rid}").status_code == 200
    assert server.client.get(f"/calibrations/{kept_cal}").status_code == 200
    assert [m["id"] for m in server.client.get(f"/robots/{rid}/measurements").json()] == [keep]


def test_delete_a_robot_takes_everything_made_from_it(server, model_doc, csv_text):
    other = _robot(server, model_doc)
    other_set = _set(server, other, csv_text)
    rid = _robot(server, model_doc)
    sets = [_set(server, rid, csv_text) for _ in range(2)]
    cal = _finished(server, _job(server, sets[0]))["calibration_id"]
    before = counts(server)
    r = server.client.delete(f"/robots/{rid}")
    assert r.status_code == 204, r.text
    after = counts(server)
    assert before["robots"] - after["robots"] == 1 and before["measurement_sets"] - after["measurement_sets"] == 2
    assert before["jobs"] - after["jobs"] == 1 and before["calibrations"] - after["calibrations"] == 1
    for path in (f"/robots/{rid}", f"/robots/{rid}/measurements", f"/measurements/{sets[1]}", f"/calibrations/{cal}"):
        assert_problem(server.client.get(path), 404)
    assert_problem(server.client.delete(f"/robots/{rid}"), 404)
    assert_problem(server.client.post(f"/robots/{rid}/measurements", files={"file": ("d.csv", csv_text)}), 404)
    assert server.client.get(f"/measurements/{other_set}").status_code == 200  # another robot's data stays


@pytest.mark.parametrize("path", ["/robots/nope", "/measurements/nope", "/robots/a%00b", "/measurements/" + "x" * 500])
def test_delete_of_nothing_is_404(server, path):
    assert assert_problem(server.client.delete(path), 404)["status"] == 404


def test_a_queued_or_running_jobs_set_is_not_deleted_from_under_it(tmp_path, model_doc, csv_text):
    """409 naming the job while it is queued and while it runs (its worker stretched to 60 s); once cancelled, the
    DELETE goes through."""
    s = Server(f"sqlite:///{tmp_path / 'd.db'}", tmp_path / "server.log", CALIB_TEST_JOB_DELAY_S="60",
               CALIB_WORKER_CONCURRENCY="1")
    s.db_path = tmp_path / "d.db"
    try:
        rid = _robot(s, model_doc)
        ms = _set(s, rid, csv_text)
        running = _job(s, ms)
        queued = _job(s, ms)  # one slot: waits behind the first
        wait_for(lambda: s.client.get(f"/jobs/{running}").json()["status"] == "running", 60, "the job to run")
        before = counts(s)
        for path in (f"/measurements/{ms}", f"/robots/{rid}"):
            body = assert_problem(s.client.delete(path), 409)
            assert {(j["id"], j["status"]) for j in body["jobs"]} == {(running, "running"), (queued, "queued")}
            assert running in body["detail"] and "cancel" in body["detail"] and "nothing was deleted" in body["detail"]
        assert counts(s) == before
        for job in (running, queued):
            assert s.client.post(f"/jobs/{job}/cancel").status_code == 200
        r = s.client.delete(f"/robots/{rid}")
        assert r.status_code == 204, r.text
        assert counts(s) == {"robots": 0, "measurement_sets": 0, "jobs": 0, "calibrations": 0, "calibration_plots": 0}
        assert s.client.get("/health").json()["status"] == "ok"
        time.sleep(1.0)  # the worker stops the cancelled job's process and finds its row gone: nothing breaks
        assert s.client.get("/health").status_code == 200 and s.p.poll() is None
    finally:
        s.stop()


def test_on_each_backend_surrogates_are_422_and_delete_takes_everything(db_url, tmp_path, model_doc, csv_text):
    """SQLite and PostgreSQL (CALIB_TEST_POSTGRES_URL): a lone surrogate in a model is a 422 with nothing stored, a
    model stored with one before (PostgreSQL's json column keeps the escape) is listed and deletable, and DELETE takes
    a robot with its set, job and calibration."""
    from sqlalchemy import create_engine, text

    eng = create_engine(db_url)

    def n() -> dict[str, int]:
        with eng.connect() as c:
            return {t: c.execute(text(f"SELECT count(*) FROM {t}")).scalar_one() for t in TABLES}

    s = Server(db_url, tmp_path / "server.log")
    try:
        assert_problem(post_raw(s, "/robots", _with(model_doc, lambda d: d.update(name="x\ud800"))), 422)
        assert n()["robots"] == 0 and s.client.get("/robots").status_code == 200
        legacy = _with(model_doc, lambda d: d.update(meta={"note": "\udc00"}))
        with eng.begin() as c:
            c.execute(text("INSERT INTO robots (id, name, model_json, joint_names, created_at) "
                           "VALUES ('00000000-0000-4000-8000-00000000legc', 'legacy', :m, :j, 0)"),
                      {"m": json.dumps(legacy), "j": json.dumps([j["name"] for j in legacy["joints"]])})
        r = s.client.get("/robots")
        assert r.status_code == 200 and r.json()[0]["model"]["meta"] == {"note": "\\udc00"}, r.text
        assert s.client.delete("/robots/00000000-0000-4000-8000-00000000legc").status_code == 204
        rid = _robot(s, model_doc)
        ms = _set(s, rid, csv_text)
        _finished(s, _job(s, ms))
        assert n() == {"robots": 1, "measurement_sets": 1, "jobs": 1, "calibrations": 1, "calibration_plots": 0}
        assert s.client.delete(f"/robots/{rid}").status_code == 204
        assert n() == {"robots": 0, "measurement_sets": 0, "jobs": 0, "calibrations": 0, "calibration_plots": 0}
        assert_problem(s.client.delete(f"/measurements/{ms}"), 404)
    finally:
        s.stop()
        eng.dispose()
