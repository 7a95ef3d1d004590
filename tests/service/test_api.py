"""The REST API over real HTTP against `calib serve` on a real SQLite file."""
from __future__ import annotations

import numpy as np
import pytest


from .conftest import PROBLEM, Server, assert_problem, sqlite_count, wait_for


@pytest.fixture(scope="module")
def robot(server, model_doc) -> dict:
    r = server.client.post("/robots", json=model_doc)
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture(scope="module")
def mset(server, robot, csv_text) -> dict:
    r = server.client.post(f"/robots/{robot['id']}/measurements", files={"file": ("cell3.csv", csv_text, "text/csv")})
    assert r.status_code == 201, r.text
    return r.json()


def run_job(server, ms_id: str, mode: str = "geometric") -> dict:
    r = server.client.post("/jobs", json={"measurement_set_id": ms_id, "model": mode})
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/jobs/{r.json()['id']}"
    assert r.json()["status"] in ("queued", "running")

    def done():
        j = server.client.get(r.headers["location"]).json()
        return j if j["status"] in ("succeeded", "failed") else None

    return wait_for(done, 60, "the job to finish")


def test_health(server):
    r = server.client.get("/health")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and r.json()["database"] == "sqlite"


def test_openapi_documents_every_call_with_examples(server):
    assert server.client.get("/docs").status_code == 200
    spec = server.client.get("/openapi.json").json()
    paths = spec["paths"]
    for path, method in [("/robots", "post"), ("/robots", "get"), ("/robots/{robot_id}", "get"),
                         ("/robots/{robot_id}/measurements", "post"), ("/measurements/{measurement_set_id}", "get"),
                         ("/jobs", "post"), ("/jobs/{job_id}", "get"), ("/calibrations/{calibration_id}", "get"),
                         ("/calibrations/{calibration_id}/predict", "post"),
                         ("/calibrations/{calibration_id}/compensate", "post"), ("/health", "get")]:
        op = paths[path][method]
        text = str(op) + str(spec["components"])
        assert "example" in text, (path, method)
        if method == "post":
            assert "example" in str(op["requestBody"]), (path, method)
    assert PROBLEM in str(paths["/robots"]["post"]["responses"]["422"])


def test_robot_round_trip(server, robot, model_doc):
    assert robot["joint_names"] == [f"J{i}" for i in range(1, 8)]
    got = server.client.get(f"/robots/{robot['id']}").json()
    assert got["model"] == model_doc  # stored as given
    assert any(r["id"] == robot["id"] for r in server.client.get("/robots").json())


def test_upload_summary(server, robot, mset):
    assert mset["n_poses"] == 150 and mset["robot_id"] == robot["id"]
    assert mset["columns"][:2] == ["point", "J1"]
    assert server.client.get(f"/measurements/{mset['id']}").json() == mset
    assert mset["id"] in [m["id"] for m in server.client.get(f"/robots/{robot['id']}/measurements").json()]


def test_geometric_job_to_prediction(server, model_doc, mset, csv_text):
    job = run_job(server, mset["id"])
    assert job["status"] == "succeeded", job
    assert job["progress"] == 1.0 and job["attempts"] == 1 and job["error"] is None
    cal = server.client.get(f"/calibrations/{job['calibration_id']}").json()
    assert cal["id"] == job["calibration_id"] and cal["model"][0] == "geometric"
    assert cal["metrics"]["n_poses"] == 150 and cal["metrics"]["rms_mm"] < 0.5
    assert {"name", "value", "std", "unit"} <= set(cal["parameters"][0])
    assert "robot_state" not in cal
    # predict reproduces the measured points to within the fit's residual
    rows = [ln.split(",") for ln in csv_text.strip().splitlines()[1:6]]
    joints = [[float(v) for v in r[1:8]] for r in rows]
    measured = np.array([[float(v) for v in r[8:11]] for r in rows])
    r = server.client.post(f"/calibrations/{cal['id']}/predict", json={"joints": joints})
    assert r.status_code == 200, r.text
    assert np.abs(np.array(r.json()["positions"]) - measured).max() < 0.5
    assert r.json()["unit"] == "mm"


def test_auto_job_runs_once(server, mset):
    """'auto' needs calib_core's diagnosis; until it exists the job fails at once with calib_core's reason."""
    job = run_job(server, mset["id"], "auto")
    assert job["attempts"] == 1, job
    if job["status"] == "failed":
        assert "not available" in job["error"], job
    else:
        assert job["status"] == "succeeded", job


def test_numerical_failure_fails_at_once(server, robot, csv_text):
    """Three poses pass the upload (fewer are refused there) but give 9 equations for more parameters."""
    three_poses = "\n".join(csv_text.splitlines()[:4]) + "\n"
    r = server.client.post(f"/robots/{robot['id']}/measurements", files={"file": ("three.csv", three_poses)})
    assert r.status_code == 201, r.text
    job = run_job(server, r.json()["id"])
    assert job["status"] == "failed" and job["attempts"] == 1
    assert "poses" in job["error"]


def test_predict_rejects_wrong_shapes(server, mset):
    job = run_job(server, mset["id"])
    url = f"/calibrations/{job['calibration_id']}/predict"
    body = assert_problem(server.client.post(url, json={"joints": [[1, 2, 3]]}), 422)
    assert body["errors"][0]["field"] == "body.joints[0]"
    assert_problem(server.client.post(url, json={"joints": []}), 422)
    assert_problem(server.client.post(url, content=b'{"joints": [[NaN, 0, 0, 0, 0, 0, 0]]}',
                                      headers={"content-type": "application/json"}), 422)


def test_compensate_puts_the_model_on_the_targets(server, mset, model_doc):
    job = run_job(server, mset["id"])
    cal = job["calibration_id"]
    rng = np.random.default_rng(0)
    lo, hi = np.array([j["limits"] for j in model_doc["joints"]]).T
    program = lo + (hi - lo) * (0.2 + 0.6 * rng.random((20, 7)))
    targets = server.client.post(f"/calibrations/{cal}/predict", json={"joints": program.tolist()}).json()["positions"]
    seeds = program + rng.normal(0, 0.3, program.shape) * np.where(np.arange(7) % 5 == 0, 5.0, 1.0)  # off by mm
    targets.append([1e5, 0.0, 0.0])  # 100 m away: reported, not a failed batch
    seeds = np.vstack([seeds, program[:1]])
    r = server.client.post(f"/calibrations/{cal}/compensate",
                           json={"targets": targets, "seed_joints": seeds.tolist(), "locked_joints": ["J6"]})
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["reachable"][:-1] == [True] * 20 and out["reachable"][-1] is False and out["reason"][-1]
    assert max(out["residual_mm"][:-1]) < 1e-2
    joints = np.array(out["joints"])
    assert np.all(joints >= lo - 1e-9) and np.all(joints <= hi + 1e-9)
    assert np.allclose(joints[:-1, 5], seeds[:-1, 5])  # the telescopic joint stays where the program had it
    again = server.client.post(f"/calibrations/{cal}/predict", json={"joints": joints[:-1].tolist()}).json()
    assert np.abs(np.array(again["positions"]) - np.array(targets[:-1])).max() < 1e-2
    # a program as joints only: the answer reaches where the nominal model said
    r = server.client.post(f"/calibrations/{cal}/compensate", json={"program_joints": program[:5].tolist()})
    assert r.status_code == 200 and all(r.json()["reachable"]), r.text
    body = assert_problem(server.client.post(f"/calibrations/{cal}/compensate",
                                             json={"targets": [[0, 0, 0]], "seed_joints": [[0] * 6]}), 422)
    assert body["errors"][0]["field"] == "body.seed_joints[0]"
    assert_problem(server.client.post(f"/calibrations/{cal}/compensate", json={"targets": [[0, 0, 0]]}), 422)
    # one iteration from seeds off by mm is not enough: the reason asks for more, and more reaches the targets
    few = {"targets": targets[:-1], "seed_joints": seeds[:-1].tolist(), "locked_joints": ["J6"], "max_iter": 1}
    r = server.client.post(f"/calibrations/{cal}/compensate", json=few)
    assert r.status_code == 200, r.text
    short = [why for why in r.json()["reason"] if why]
    assert short and all("still converging: raise max_iter above 1" in why for why in short), short
    r = server.client.post(f"/calibrations/{cal}/compensate", json={**few, "max_iter": 60})
    assert r.status_code == 200 and all(r.json()["reachable"]), r.text
    body = assert_problem(server.client.post(f"/calibrations/{cal}/compensate", json={**few, "max_iter": 10**6}), 422)
    assert body["errors"][0]["field"] == "body.max_iter", body


@pytest.mark.parametrize("path", ["/robots/nope", "/measurements/nope", "/jobs/nope", "/calibrations/nope",
                                  "/no/such/route"])
def test_not_found_is_a_problem(server, path):
    body = assert_problem(server.client.get(path), 404)
    assert body["status"] == 404


def test_validation_errors_are_problems(server):
    body = assert_problem(server.client.post("/jobs", json={"model": "quantum"}), 422)
    fields = {e["field"] for e in body["errors"]}
    assert {"body.measurement_set_id", "body.model"} <= fields
    assert_problem(server.client.post("/jobs", content=b"{not json", headers={"content-type": "application/json"}), 422)
    body = assert_problem(server.client.post("/jobs", json={"measurement_set_id": "missing"}), 422)
    assert body["errors"][0]["field"] == "body.measurement_set_id"
    assert_problem(server.client.delete("/robots"), 405)


def test_auth_on_writing_calls(tmp_path, model_doc):
    s = Server(f"sqlite:///{tmp_path / 'auth.db'}", tmp_path / "server.log", CALIB_API_TOKEN="s3cret")
    try:
        r = s.client.post("/robots", json=model_doc)
        body = assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer") and "Bearer" in body["detail"]
        assert_problem(s.client.post("/robots", json=model_doc, headers={"Authorization": "Bearer wrong"}), 401)
        r = s.client.post("/robots", json=model_doc, headers={"Authorization": "Bearer s3cret"})
        assert r.status_code == 201
        assert_problem(s.client.get(f"/robots/{r.json()['id']}"), 401)  # reads need the token too (issue 10)
        assert s.client.get(f"/robots/{r.json()['id']}", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert sqlite_count(tmp_path / "auth.db", "robots") == 1
    finally:
        s.stop()


def upload(server, robot_id: str, text: str, **params):
    return server.client.post(f"/robots/{robot_id}/measurements", params=params,
                              files={"file": ("cell.csv", text, "text/csv")})


def test_instrument_is_validated_stored_and_names_the_noise_model(server, robot, csv_text):
    """The same CSV (no sigma column) with instrument=motion_capture and with none: the jobs re-parse it with the
    stored preset, so the noise floors differ and the answer names the preset that was used."""
    body = assert_problem(upload(server, robot["id"], csv_text, instrument="ruler"), 422)
    err = body["errors"][0]
    assert err["field"] == "query.instrument" and err["value"] == "ruler"
    assert all(name in err["message"] for name in ("laser_tracker", "optical", "motion_capture", "total_station"))

    mocap = upload(server, robot["id"], csv_text, instrument="motion_capture")
    plain = upload(server, robot["id"], csv_text)
    assert mocap.status_code == plain.status_code == 201, (mocap.text, plain.text)
    mocap, plain = mocap.json(), plain.json()
    assert mocap["instrument"] == "motion_capture" and plain["instrument"] is None
    assert server.client.get(f"/measurements/{mocap['id']}").json() == mocap
    jobs = [server.client.post("/jobs", json={"measurement_set_id": m["id"], "model": "auto"}) for m in (mocap, plain)]
    assert all(r.status_code == 202 for r in jobs), [r.text for r in jobs]

    def answer(loc):
        job = wait_for(lambda: (j := server.client.get(loc).json())["status"] in ("succeeded", "failed") and j,
                       120, "the auto job")
        assert job["status"] == "succeeded", job
        return server.client.get(f"/calibrations/{job['calibration_id']}").json()

    a_mocap, a_plain = (answer(r.headers["location"]) for r in jobs)
    assert "motion_capture" in a_mocap["noise_model"] and "motion_capture" in a_mocap["diagnosis"]["noise_model"]
    assert "laser_tracker" in a_plain["noise_model"] and "assumed" in a_plain["noise_model"]
    assert a_mocap["diagnosis"]["noise_floor_mm"] > 2 * a_plain["diagnosis"]["noise_floor_mm"]


@pytest.fixture(scope="module")
def narrow_robot(server, model_doc) -> dict:
    """spray7 with J2 limited to +-40 deg: the module's CSV (spray7's full +-60 deg) has rows beyond that."""
    doc = {**model_doc, "name": "spray7-narrow",
           "joints": [dict(j, limits=[-40, 40]) if j["name"] == "J2" else j for j in model_doc["joints"]]}
    r = server.client.post("/robots", json=doc)
    assert r.status_code == 201, r.text
    return r.json()


def _beyond_40(csv_text: str) -> list[int]:
    """Line numbers of the rows whose J2 is outside +-40 deg."""
    lines = csv_text.strip().splitlines()
    k = lines[0].split(",").index("J2")
    return [i + 1 for i, ln in enumerate(lines) if i and abs(float(ln.split(",")[k])) > 40]


def test_limits_reject_by_default(server, narrow_robot, csv_text):
    bad = _beyond_40(csv_text)
    assert len(bad) >= 5
    for params in ({}, {"limits": "reject"}):
        body = assert_problem(upload(server, narrow_robot["id"], csv_text, **params), 422)
        assert body["type"].endswith("/invalid-csv") and body["error_count"] == len(bad)
        assert [e["row"] for e in body["errors"]] == bad[:len(body["errors"])]
        assert all(e["column"] == "J2" and "outside the joint limits [-40, 40] deg" in e["message"]
                   for e in body["errors"])
    body = assert_problem(upload(server, narrow_robot["id"], csv_text, limits="ignore"), 422)
    assert body["errors"][0]["field"] == "query.limits" and "'warn'" in body["errors"][0]["message"]


def test_limits_warn_accepts_reports_and_calibrates(server, narrow_robot, csv_text):
    bad = _beyond_40(csv_text)
    r = upload(server, narrow_robot["id"], csv_text, limits="warn")
    assert r.status_code == 201, r.text
    ms = r.json()
    lines = csv_text.strip().splitlines()
    q2 = [float(ln.split(",")[lines[0].split(",").index("J2")]) for ln in lines[1:]]
    assert ms["limits"] == "warn" and ms["n_poses"] == 150
    assert ms["out_of_limits"] == [{"joint": "J2", "unit": "deg", "limits": [-40.0, 40.0], "rows": len(bad),
                                    "min": pytest.approx(min(q2)), "max": pytest.approx(max(q2)),
                                    "first_rows": bad[:10]}]
    assert server.client.get(f"/measurements/{ms['id']}").json() == ms
    assert next(m for m in server.client.get(f"/robots/{narrow_robot['id']}/measurements").json()
                if m["id"] == ms["id"]) == ms
    for mode in ("geometric", "auto"):  # the job re-parses the CSV as uploaded: the out-of-limit rows are used
        job = run_job(server, ms["id"], mode)
        assert job["status"] == "succeeded", job
        cal = server.client.get(f"/calibrations/{job['calibration_id']}").json()
        assert cal["metrics"]["n_poses"] == 150 and cal["metrics"]["rms_mm"] < 0.5
