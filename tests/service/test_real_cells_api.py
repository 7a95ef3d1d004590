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
    return model, twin, R, t, _calibrated(server, doc, model, meas, "cell.csv", "geometric", 120)["calibration_id"]


def _calibrated(server, doc, model, meas, filename, mode, timeout_s) -> dict:
    """Upload the robot and its measurements over HTTP, run a `mode` job, wait for it: the succeeded job."""
    r = server.client.post("/robots", json=doc)
    assert r.status_code == 201, r.text
    r = server.client.post(f"/robots/{r.json()['id']}/measurements",
                           files={"file": (filename, write_measurements(meas, model), "text/csv")})
    assert r.status_code == 201, r.text
    r = server.client.post("/jobs", json={"measurement_set_id": r.json()["id"], "model": mode})
    assert r.status_code == 202, r.text
    loc = r.headers["location"]
    job = wait_for(lambda: (lambda j: j if j["status"] in ("succeeded", "failed") else None)(
        server.client.get(loc).json()), timeout_s, "the job")
    assert job["status"] == "succeeded", job
    return job


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


# --- measured torques (tau_<joint>) as the load of predict and compensate ---------------------------------------

@pytest.fixture(scope="module")
def torque_cell(server):
    """The 6R arm uploaded WITHOUT masses, measured by the independent world (a hidden spring on A2, 8x the noise)
    with the joint torques its mechanics hold (tau_A1..tau_A6 = -gravity load), calibrated with model "auto": the
    diagnosis can only name the spring through the measured torques."""
    from calib_core.robots import arm6
    from calib_world import JointSpring, World
    from calib_world.scenarios import size_cause

    world = World(parse_model(arm6()), 7)  # the physical robot has its masses; the uploaded model has none
    rng = np.random.default_rng(7)
    q = world.sample_joints(150, rng)
    cols = world.columns(q, None)
    load = world.robot.joint_loads(q, cols.payload_kg())
    cause, _ = size_cause(world, JointSpring(1, 1e-4 / np.abs(load[:, 1]).max()), 8.0 * world.noise_rms_mm(q), q, cols)
    world.hide(cause)
    meas = world.measure(q)
    meas.tau = -load
    doc = arm6()
    for j in doc["joints"]:
        del j["mass"], j["com"]
    model = parse_model(doc)
    job = _calibrated(server, doc, model, meas, "arm6_tau.csv", "auto", 300)
    doc = server.client.get(f"/calibrations/{job['calibration_id']}").json()
    kinds = [f["kind"] for f in doc["diagnosis"]["findings"]]
    assert "joint_compliance" in kinds, kinds
    return model, world, job["calibration_id"]


def _world_poses(world, rng, n):
    """n fresh poses of the world, their true points and the torques its joints hold there (-load, N*m)."""
    q = world.sample_joints(n, rng)
    cols = world.columns(q, None)
    return q, world.true_points(q, cols), -world.robot.joint_loads(q, cols.payload_kg())


def test_predict_takes_measured_torques(server, torque_cell, seed):
    """With each row's tau the prediction follows the spring (within 0.1 mm of the world's truth); without tau
    the model (no masses) has no load: the answer is further off and its notes say which cause acted as zero."""
    model, world, cal = torque_cell
    rng = np.random.default_rng(seed)
    q, truth, tau = _world_poses(world, rng, 20)
    joints = np.degrees(q).tolist()
    taus = {f"tau_{name}": tau[:, j].tolist() for j, name in enumerate(model.joint_names)}
    r = server.client.post(f"/calibrations/{cal}/predict", json={"joints": joints, "tau": taus})
    assert r.status_code == 200, r.text
    with_tau = np.linalg.norm(np.array(r.json()["positions"]) - truth, axis=1)
    assert with_tau.max() < 0.1 and r.json()["notes"] == [], (seed, with_tau.max(), r.json()["notes"])

    r = server.client.post(f"/calibrations/{cal}/predict", json={"joints": joints})
    assert r.status_code == 200, r.text
    without = np.linalg.norm(np.array(r.json()["positions"]) - truth, axis=1)
    assert without.mean() > 2 * with_tau.mean(), (seed, without.mean(), with_tau.mean())
    notes = r.json()["notes"]
    assert len(notes) == 1 and "joint_compliance" in notes[0] and "tau_A2" in notes[0] and "every row" in notes[0]

    # tau on A2 only, missing (null) on row 3: that row alone is named, the others follow their torque
    a2 = tau[:, 1].tolist()
    a2[3] = None
    r = server.client.post(f"/calibrations/{cal}/predict", json={"joints": joints, "tau": {"tau_A2": a2}})
    assert r.status_code == 200, r.text
    partial = np.linalg.norm(np.array(r.json()["positions"]) - truth, axis=1)
    assert "row 3 gave no tau_A2" in r.json()["notes"][0], r.json()["notes"]
    assert np.allclose(np.delete(partial, 3), np.delete(with_tau, 3), atol=1e-9) and partial[3] == pytest.approx(
        without[3], abs=1e-9)


def test_compensate_takes_measured_torques(server, torque_cell, seed):
    """Targets where the world's robot really went; with the torques at those poses the commands put the physical
    robot on them within 0.1 mm; without them the answer says the spring acted as zero load."""
    model, world, cal = torque_cell
    rng = np.random.default_rng(seed)
    q, truth, tau = _world_poses(world, rng, 10)
    seeds = np.degrees(q) + rng.normal(0, 0.2, q.shape)
    taus = {f"tau_{name}": tau[:, j].tolist() for j, name in enumerate(model.joint_names)}
    r = server.client.post(f"/calibrations/{cal}/compensate",
                           json={"targets": truth.tolist(), "seed_joints": seeds.tolist(), "tau": taus})
    assert r.status_code == 200, r.text
    out = r.json()
    assert all(out["reachable"]) and out["notes"] == [], out
    qa = np.radians(out["joints"])
    landed = np.linalg.norm(world.true_points(qa, world.columns(qa, None)) - truth, axis=1)
    assert landed.max() < 0.1, (seed, landed)
    r = server.client.post(f"/calibrations/{cal}/compensate",
                           json={"targets": truth.tolist(), "seed_joints": seeds.tolist()})
    assert r.status_code == 200 and "tau_A2" in r.json()["notes"][0], r.text
    qa = np.radians(r.json()["joints"])
    missed = np.linalg.norm(world.true_points(qa, world.columns(qa, None)) - truth, axis=1)
    assert missed.mean() > 2 * landed.mean(), (seed, missed.mean(), landed.mean())


def test_bad_torques_are_422_naming_row_column_and_value(server, torque_cell):
    model, world, cal = torque_cell
    joints = [[0.0, -30.0, 20.0, 0.0, 40.0, 0.0]] * 2
    body = assert_problem(server.client.post(f"/calibrations/{cal}/predict", json={
        "joints": joints, "tau": {"tau_A9": 1.0, "tau_A2": [10.0, 2e6], "tau_A3": [1.0]}}), 422)
    got = {e["field"]: e for e in body["errors"]}
    assert "tau_A1" in got["body.tau.tau_A9"]["message"] and got["body.tau.tau_A9"]["value"] == "tau_A9"
    assert got["body.tau.tau_A2[1]"]["value"] == 2e6 and "implausible" in got["body.tau.tau_A2[1]"]["message"]
    assert got["body.tau.tau_A3"]["value"] == 1 and "one value per row (2)" in got["body.tau.tau_A3"]["message"]
    body = assert_problem(server.client.post(f"/calibrations/{cal}/compensate", json={
        "program_joints": joints, "tau": {"tau_A2": "12"}}), 422)  # a string is not a number
    assert any("tau" in str(e.get("field", "")) for e in body["errors"]), body


def test_a_calibration_saved_before_causes_acted_on_drives_is_refused_not_served(server):
    """Since 005b235 a cause on T2 (which T4 follows) also turns T4, with the drive's load. A stored calibration
    saved before, with such a cause, would predict otherwise than it was fitted: predict, compensate and plan answer
    409 naming the rows and what to do. The same state with the marker predicts; an old state without causes on a
    drive predicts as before."""
    import json
    import sqlite3

    from calib_core.effects import JointCompliance, effect_state
    from calib_core.calibrated import ON_DRIVES

    doc = torso_two_arms()
    model = parse_model(doc)
    twin = Twin(model, seed=32)
    cal = _calibrated(server, doc, model, twin.measure(n=60), "stale.csv", "geometric", 120)["calibration_id"]

    def stored(edit):
        with sqlite3.connect(server.db_path) as c:
            state = json.loads(c.execute("SELECT robot_state FROM calibrations WHERE id = ?", (cal,)).fetchone()[0])
            edit(state)
            c.execute("UPDATE calibrations SET robot_state = ? WHERE id = ?", (json.dumps(state), cal))

    q = np.degrees(sample_uniform(model, 3, np.random.default_rng(6))[:, model.actuated]).tolist()
    predict = lambda: server.client.post(f"/calibrations/{cal}/predict", json={"joints": q, "target": "left"})  # noqa: E731

    stored(lambda s: s.pop(ON_DRIVES))  # an old state, no causes: served as before
    assert predict().status_code == 200
    t2 = model.joint_names.index("T2")
    stored(lambda s: s["effects"].append(effect_state(JointCompliance((t2,)), np.array([1e-5]))))
    body = assert_problem(predict(), 409)
    assert "T2" in body["detail"] and "run the calibration job again" in body["detail"], body
    body = assert_problem(server.client.post(f"/calibrations/{cal}/compensate",
                                             json={"program_joints": q, "target": "left"}), 409)
    assert "T2" in body["detail"]
    info = server.client.get(f"/calibrations/{cal}").json()
    body = assert_problem(server.client.post(f"/robots/{info['robot_id']}/plan", json={
        "n_poses": 10, "purpose": "geometric", "measurement_set_id": info["measurement_set_id"]}), 409)
    assert "T2" in body["detail"]
    stored(lambda s: s.update({ON_DRIVES: True}))
    assert predict().status_code == 200
