"""Contract section 5 over real HTTP: a torso with two arms, a coupled joint, two targets and two setups —
uploaded, calibrated, predicted per target and setup, and compensated without breaking the coupling."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_core import kinematics as K
from calib_core.io import Measurements, write_measurements
from calib_core.model import parse_model
from calib_core.twin import Twin, sample_uniform

from ..core.test_tree import torso_two_arms
from .conftest import assert_problem, wait_for


@pytest.fixture(scope="module")
def cell(server):
    doc = torso_two_arms()
    model = parse_model(doc)
    twin = Twin(model, seed=31)
    a, b = twin.measure(n=120), twin.measure(n=120)
    R, t = Rotation.from_euler("z", 40, degrees=True).as_matrix(), np.array([1500.0, -300.0, 20.0])
    meas = Measurements(joints=np.r_[a.joints, b.joints], points=np.r_[a.points, b.points @ R.T + t],
                        target=np.r_[a.target, b.target], setup=np.r_[np.zeros(120, int), np.ones(120, int)],
                        setup_names=("north", "south"))
    r = server.client.post("/robots", json=doc)
    assert r.status_code == 201, r.text
    robot = r.json()
    r = server.client.post(f"/robots/{robot['id']}/measurements",
                           files={"file": ("cell.csv", write_measurements(meas, model), "text/csv")})
    assert r.status_code == 201, r.text
    r = server.client.post("/jobs", json={"measurement_set_id": r.json()["id"], "model": "geometric"})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    job = wait_for(lambda: (lambda j: j if j["status"] in ("succeeded", "failed") else None)(
        server.client.get(loc).json()), 120, "the job")
    assert job["status"] == "succeeded", job
    return model, twin, R, t, job["calibration_id"]


def test_tree_calibration_answer_has_one_torso_and_two_setups(server, cell):
    model, *_, cal = cell
    doc = server.client.get(f"/calibrations/{cal}").json()
    names = [p["name"] for p in doc["parameters"]]
    assert len(names) == len(set(names))
    assert any(n.startswith("base[south].") for n in names) and any(n.startswith("tool[right].") for n in names)
    assert doc["metrics"]["holdout_rms_mm"] < 0.2


def test_predict_per_target_and_setup(server, cell):
    model, twin, R, t, cal = cell
    rng = np.random.default_rng(4)
    q = sample_uniform(model, 6, rng)
    act = np.degrees(q[:, model.actuated])
    labels = K.Labels(np.array([0, 1, 0, 1, 0, 1]), np.zeros(6, int))
    truth = twin.true_points(q, labels)
    r = server.client.post(f"/calibrations/{cal}/predict",
                           json={"joints": act.tolist(), "target": ["left", "right"] * 3})
    assert r.status_code == 200, r.text
    assert np.abs(np.array(r.json()["positions"]) - truth).max() < 0.3
    r = server.client.post(f"/calibrations/{cal}/predict",
                           json={"joints": act.tolist(), "target": ["left", "right"] * 3, "setup": "south"})
    assert np.abs(np.array(r.json()["positions"]) - (truth @ R.T + t)).max() < 0.3
    body = assert_problem(server.client.post(f"/calibrations/{cal}/predict",
                                             json={"joints": act.tolist(), "target": "middle"}), 422)
    assert body["errors"][0]["field"] == "body.target" and "left" in body["errors"][0]["message"]
    body = assert_problem(server.client.post(f"/calibrations/{cal}/predict",
                                             json={"joints": np.degrees(q).tolist()}), 422)  # rows, not actuated
    assert "T1, T2, T3, L1" in body["errors"][0]["message"]


def test_compensate_keeps_the_coupling(server, cell):
    model, twin, R, t, cal = cell
    rng = np.random.default_rng(5)
    q = sample_uniform(model, 5, rng)
    labels = K.Labels(np.array([1, 1, 0, 1, 0]), np.zeros(5, int))
    truth = twin.true_points(q, labels)
    seeds = np.degrees(q[:, model.actuated]) + rng.normal(0, 0.5, (5, 11))
    r = server.client.post(f"/calibrations/{cal}/compensate",
                           json={"targets": truth.tolist(), "seed_joints": seeds.tolist(),
                                 "target": ["right", "right", "left", "right", "left"]})
    assert r.status_code == 200, r.text
    out = r.json()
    assert all(out["reachable"]) and np.array(out["joints"]).shape == (5, 11)
    rows = model.expand_joints(np.radians(out["joints"]))
    assert np.abs(twin.true_points(rows, labels) - truth).max() < 0.3  # where the real robot lands
    body = assert_problem(server.client.post(f"/calibrations/{cal}/compensate",
                                             json={"program_joints": seeds.tolist(), "locked_joints": ["T4"]}), 422)
    assert "coupling" in body["errors"][0]["message"]
