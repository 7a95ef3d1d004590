"""URDF over real HTTP (contract section 5): import a URDF, measure the robot it describes (geometric twin, or a
perturbed copy of a tree with mimic joints), calibrate, export the calibrated model as JSON and URDF, and read the
URDF back: it carries the identified geometry."""
from __future__ import annotations

import numpy as np
import pytest

from calib_core import Twin, parse_model, write_measurements
from calib_core import kinematics as K
from calib_core.io import Measurements
from calib_core.urdf import parse_urdf

from ..core.test_urdf import HILTI, TREE, TREE_TARGETS, UR_LIKE, urdf_pose
from .conftest import wait_for

XML = {"Content-Type": "application/xml"}


def run_job(c, measurement_set_id: str, model: str = "geometric") -> str:
    """Run a calibration job and wait for it; the calibration's id."""
    job = c.post("/jobs", json={"measurement_set_id": measurement_set_id, "model": model})
    assert job.status_code == 202, job.text

    def done():
        j = c.get(job.headers["location"]).json()
        return j if j["status"] in ("succeeded", "failed") else None

    j = wait_for(done, 300, "the job to finish")
    assert j["status"] == "succeeded", j
    return j["calibration_id"]


def test_urdf_import_calibrate_export(server):
    c = server.client
    bad = c.post("/robots?targets=tool0", content=UR_LIKE.replace('xyz="-0.425 0 0"', 'xyz="-0.425 x 0"'),
                 headers=XML)
    assert bad.status_code == 422 and bad.headers["content-type"].startswith("application/problem+json")
    assert bad.json()["errors"][0]["field"] == "joint[@name='elbow_joint']/origin/@xyz", bad.json()
    two = c.post("/robots?targets=tool0,finger_left", content=UR_LIKE, headers=XML)  # a tree: the xyz form
    assert two.status_code == 201, two.text
    assert [t["name"] for t in c.get(f"/robots/{two.json()['id']}").json()["model"]["targets"]] == [
        "tool0", "finger_left"]
    mimic = c.post("/robots?targets=nowhere", content=UR_LIKE, headers=XML)
    assert mimic.status_code == 422 and "no link 'nowhere'" in mimic.text

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
    cal_id = run_job(c, ms.json()["id"])

    cal_doc = c.get(f"/calibrations/{cal_id}/model").json()
    assert cal_doc["urdf"] == doc["urdf"] and cal_doc["calibration"]["id"] == cal_id
    cal_model = parse_model(cal_doc)
    assert cal_doc["joints"] != doc["joints"]  # the identified geometry, not the nominal

    u = c.get(f"/calibrations/{cal_id}/urdf?form=rows")  # from the rows; the original patched: test_urdf_patch_api
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
    assert c.get(f"/calibrations/{cal_id}/urdf?form=rows").text == u.text
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
    assert main(["export-urdf", str(out), "-o", str(urdf), "--form", "rows"]) == 0
    assert parse_urdf(urdf.read_text())["joints"][0]["name"] == "track_joint"
    answer = {"calibrated_model": doc, "model": ["geometric", "backlash"],
              "diagnosis": {"findings": [{"kind": "backlash", "joints": ["elbow_joint"]}]}}
    (tmp_path / "cal.json").write_text(json.dumps(answer))
    assert main(["export-urdf", str(tmp_path / "cal.json")]) == 0
    assert "backlash on elbow_joint" in capsys.readouterr().out


def _rms_after_rigid_fit(pred: np.ndarray, measured: np.ndarray) -> float:
    """RMS (model units) of predicted against measured points once one rigid transform maps one onto the other
    (a URDF holds no base pose: the tracker's frame is registered, as any user of the URDF would)."""
    R, t = K.rigid_fit(pred, measured)
    return float(np.sqrt(((pred @ R.T + t - measured) ** 2).sum(1).mean()))


CELLS = {  # name: (URDF text, base link, target links); the real Hilti URDF when ../shared is there
    "hilti": (HILTI.read_text() if HILTI.exists() else None, "base_link", "prism"),
    "tree": (TREE, "world", TREE_TARGETS),
}


@pytest.mark.parametrize("cell", list(CELLS))
def test_urdf_tree_with_mimic_calibrates_and_exports(server, cell):
    """A URDF with mimic joints (and, for the small tree, three targets on two arms and a head) posted as XML;
    measurements of a perturbed copy of its model (calib_core.kinematics.forward + 0.02 mm noise, CSV by
    calib_core.io.write_measurements); a geometric calibration; GET /calibrations/{id}/model and /urdf. The URDF
    re-imports with the same base and targets, and its own link products (no calib_core involved) predict the
    measured points far better than the nominal URDF does, and fresh poses of the perturbed robot as well."""
    text, base, targets = CELLS[cell]
    if text is None:
        pytest.skip("../shared/datasets (Hilti trailblazer URDF) is absent")
    c = server.client
    r = c.post(f"/robots?base={base}&targets={targets}", content=text.encode(), headers=XML)
    assert r.status_code == 201, r.text
    robot = r.json()
    doc = c.get(f"/robots/{robot['id']}").json()["model"]
    assert doc == parse_urdf(text, base, targets) and doc["urdf"]["form"] == "xyz"
    model = parse_model(doc)
    assert robot["joint_names"] == list(model.joint_names)
    n, T = model.n_joints, model.n_targets
    assert any("coupled" in row for row in doc["joints"]) and any(row["type"] == "fixed" for row in doc["joints"])

    # the robot as built: every row's constants off by 0.5 mm / 1 mrad, the targets by 2 mm, a base pose
    rng = np.random.default_rng(11)
    x_true = K.nominal_vector(model)
    x_true[: K.G * n] += rng.normal(0.0, 1.0, K.G * n) * np.tile([0.5, 1e-3, 0.5, 1e-3, 1e-3, 1e-3, 0.5], n)
    x_true[K.G * n: K.G * n + 6] = [1500.0, -800.0, 200.0, 0.01, -0.02, 0.7]
    x_true[K.G * n + 6:] += rng.normal(0.0, 2.0, 3 * T)

    def poses(k: int):
        lim = model.limits[model.actuated].copy()
        lim[~np.isfinite(lim)] = np.sign(lim[~np.isfinite(lim)]) * np.pi  # a continuous joint: one turn
        q_act = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * (0.05 + 0.9 * rng.random((k, len(lim))))
        labels = K.Labels(np.arange(k) % T, np.zeros(k, int))
        return q_act, model.expand_joints(q_act), labels

    N = 60 * T + 60
    q_act, q, labels = poses(N)
    points = K.forward(model, x_true, q, labels=labels) + rng.normal(0.0, 0.02, (N, 3))
    meas = Measurements(joints=q, points=points, target=labels.target if T > 1 else None)
    csv_text = write_measurements(meas, model)
    ms = c.post(f"/robots/{robot['id']}/measurements", files={"file": (f"{cell}.csv", csv_text, "text/csv")})
    assert ms.status_code == 201, ms.text
    cal_id = run_job(c, ms.json()["id"])

    cal_doc = c.get(f"/calibrations/{cal_id}/model").json()
    assert cal_doc["urdf"] == doc["urdf"] and cal_doc["calibration"]["id"] == cal_id
    assert [row["name"] for row in cal_doc["joints"]] == [row["name"] for row in doc["joints"]]
    assert cal_doc["joints"] != doc["joints"] and all("xyz" in row for row in cal_doc["joints"])
    for a, b in zip(doc["joints"], cal_doc["joints"]):
        assert a.get("coupled") == b.get("coupled") and a["type"] == b["type"]
    assert c.post("/robots", json=cal_doc).status_code == 201  # it posts back as a model

    u = c.get(f"/calibrations/{cal_id}/urdf?form=rows")  # from the rows; the original patched: test_urdf_patch_api
    assert u.status_code == 200 and u.headers["content-type"].startswith("application/xml")
    assert "<mimic" in u.text and 'type="fixed"' in u.text
    back = parse_urdf(u.text, base, targets)  # the same base and target link names find the identified points
    # every joint keeps its child link; a target link whose calibrated point left its origin (when it does
    # not hang on a fixed joint) gets a link of its own and its old one is renamed <target>_parent
    for joint, child in doc["urdf"]["links"].items():
        expect = (child, f"{child}_parent") if child in targets.split(",") else (child,)
        assert back["urdf"]["links"][joint] in expect, (joint, back["urdf"]["links"][joint])
    assert c.post(f"/robots?base={base}&targets={targets}", content=u.content, headers=XML).status_code == 201
    assert c.get(f"/calibrations/{cal_id}/urdf?form=rows").text == u.text

    names = model.joint_names

    def urdf_points(urdf_text: str, qrows: np.ndarray, lab: K.Labels) -> np.ndarray:
        """mm, the URDF's own link products (test_urdf.urdf_pose; mimic joints follow their sources)."""
        out = []
        for qi, t in zip(qrows, lab.target):
            qd = {nm: v / (1000.0 if model.prismatic[k] else 1.0) for k, (nm, v) in enumerate(zip(names, qi))
                  if k in model.actuated}
            out.append(urdf_pose(urdf_text, model.target_names[t], qd, base)[:3, 3] * 1000.0)
        return np.array(out)

    # the measured points: the calibrated URDF explains them to about the noise, the nominal one does not
    cal_pts, nom_pts = urdf_points(u.text, q, labels), urdf_points(text, q, labels)
    mb = parse_model(back)  # the production kinematics of the re-imported model agree with the URDF's products
    assert mb.actuated_names == model.actuated_names
    assert np.abs(K.forward(mb, K.nominal_vector(mb), mb.expand_joints(q_act), labels=labels) - cal_pts).max() < 1e-6
    rms_cal, rms_nom = _rms_after_rigid_fit(cal_pts, points), _rms_after_rigid_fit(nom_pts, points)
    assert rms_cal < 0.1 and rms_nom > 10 * rms_cal, (rms_cal, rms_nom)
    # and fresh poses of the robot as built
    _, q2, lab2 = poses(40)
    truth = K.forward(model, x_true, q2, labels=lab2)
    fresh_cal, fresh_nom = urdf_points(u.text, q2, lab2), urdf_points(text, q2, lab2)
    assert _rms_after_rigid_fit(fresh_cal, truth) < 0.1 < _rms_after_rigid_fit(fresh_nom, truth)
