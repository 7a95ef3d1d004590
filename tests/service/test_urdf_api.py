"""URDF over real HTTP (contract section 5): import a URDF, measure the robot it describes (geometric twin),
calibrate, export the calibrated model as JSON and URDF, and read the URDF back."""
from __future__ import annotations

import numpy as np

from calib_core import Twin, parse_model, write_measurements
from calib_core import kinematics as K
from calib_core.urdf import parse_urdf

from ..core.test_urdf import UR_LIKE
from .conftest import wait_for

XML = {"Content-Type": "application/xml"}


def test_urdf_import_calibrate_export(server):
    c = server.client
    bad = c.post("/robots?targets=tool0", content=UR_LIKE.replace('xyz="-0.425 0 0"', 'xyz="-0.425 x 0"'),
                 headers=XML)
    assert bad.status_code == 422 and bad.headers["content-type"].startswith("application/problem+json")
    assert bad.json()["errors"][0]["field"] == "joint[@name='elbow_joint']/origin/@xyz", bad.json()
    two = c.post("/robots?targets=tool0,finger_left", content=UR_LIKE, headers=XML)
    assert two.status_code == 422 and "not yet supported" in two.text
    mimic = c.post("/robots?targets=finger_right", content=UR_LIKE, headers=XML)
    assert mimic.status_code == 422 and "finger_right_joint" in mimic.text

    r = c.post("/robots?base=world&targets=tool0", content=UR_LIKE.encode(), headers=XML)
    assert r.status_code == 201, r.text
    robot = r.json()
    assert robot["joint_names"][0] == "track_joint" and len(robot["joint_names"]) == 7
    doc = c.get(f"/robots/{robot['id']}").json()["model"]
    assert doc == parse_urdf(UR_LIKE, "world", "tool0")  # stored as the JSON upload of the converted model
    assert c.post("/robots", json=doc).status_code == 201  # JSON uploads still reach the JSON route

    model = parse_model(doc)
    twin = Twin(model, 3)
    csv_text = write_measurements(twin.measure(n=120), model)
    ms = c.post(f"/robots/{robot['id']}/measurements", files={"file": ("ur.csv", csv_text, "text/csv")})
    assert ms.status_code == 201, ms.text
    job = c.post("/jobs", json={"measurement_set_id": ms.json()["id"], "model": "geometric"})
    assert job.status_code == 202, job.text

    def done():
        j = c.get(job.headers["location"]).json()
        return j if j["status"] in ("succeeded", "failed") else None

    j = wait_for(done, 120, "the job to finish")
    assert j["status"] == "succeeded", j
    cal_id = j["calibration_id"]

    cal_doc = c.get(f"/calibrations/{cal_id}/model").json()
    assert cal_doc["urdf"] == doc["urdf"] and cal_doc["calibration"]["id"] == cal_id
    cal_model = parse_model(cal_doc)
    assert cal_doc["joints"] != doc["joints"]  # the identified geometry, not the nominal

    u = c.get(f"/calibrations/{cal_id}/urdf")
    assert u.status_code == 200 and u.headers["content-type"].startswith("application/xml")
    back = parse_urdf(u.text)  # a single chain: the defaults find world -> tool0
    assert back["urdf"]["base_link"] == "world" and back["urdf"]["target_link"] == "tool0"
    q = twin.sample_joints(30)
    m_back = parse_model(back)
    p_cal = K.forward(cal_model, K.nominal_vector(cal_model), q)
    p_back = K.forward(m_back, K.nominal_vector(m_back), q)
    assert np.abs(p_cal - p_back).max() < 1e-9  # mm: the URDF carries the calibrated kinematics exactly
    # and the calibrated kinematics are the robot's: same shape as the twin's truth up to a rigid motion
    truth = twin.true_points(q)
    R, t = K.rigid_fit(p_cal, truth)
    assert np.abs(p_cal @ R.T + t - truth).max() < 1.0
    assert c.post("/robots", content=u.content, headers=XML).status_code == 201
    assert c.get(f"/calibrations/{cal_id}/urdf").text == u.text
    assert c.get("/calibrations/nope/urdf").status_code == 404


def test_cli_import_and_export_urdf(tmp_path, capsys):
    import json

    from service.cli import main

    src = tmp_path / "ur.urdf"
    src.write_text(UR_LIKE)
    out = tmp_path / "model.json"
    assert main(["import-urdf", str(src), "--target", "tool0", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc == parse_urdf(UR_LIKE, target="tool0")
    assert main(["import-urdf", str(src)]) == 1  # several leaves: named on stderr
    assert "finger_left" in capsys.readouterr().err
    assert main(["import-urdf", str(src), "--target", "tool0", "--length-unit", "mm", "--angle-unit", "deg"]) == 0
    assert json.loads(capsys.readouterr().out)["units"] == {"length": "mm", "angle": "deg"}

    urdf = tmp_path / "out.urdf"
    assert main(["export-urdf", str(out), "-o", str(urdf)]) == 0
    assert parse_urdf(urdf.read_text())["joints"][0]["name"] == "track_joint"
    answer = {"calibrated_model": doc, "model": ["geometric", "backlash"],
              "diagnosis": {"findings": [{"kind": "backlash", "joints": ["elbow_joint"]}]}}
    (tmp_path / "cal.json").write_text(json.dumps(answer))
    assert main(["export-urdf", str(tmp_path / "cal.json")]) == 0
    assert "backlash on elbow_joint" in capsys.readouterr().out
