"""The measurement order over real HTTP (the `sequence` column, service/README): a CSV without timestamps whose
`sequence` places a joint's re-homing; the auto job fits the step, and predict places each pose by the sequence
it is given (none: the robot's current state, after the step), and so does compensate."""
from __future__ import annotations

import dataclasses

import numpy as np

from calib_core.model import parse_model
from calib_core.robots import arm6
from calib_world import World
from calib_world.mechanics import ReHoming
from calib_world.scenarios import size_cause

from .test_real_cells_api import _calibrated


def test_a_step_in_the_sequence_is_fitted_and_predicted_by_sequence(server, seed):
    doc = arm6()
    model = parse_model(doc)
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    q = world.sample_joints(120, rng)
    j = int(rng.integers(1, model.n_joints - 1))
    cols = world.columns(q, None, False)
    step, _ = size_cause(world, ReHoming.within(j, 1e-3, 0.6, cols.timestamp), 15.0 * world.noise_rms_mm(q), q,
                         cols, world.absorbable_basis(q))
    world.hide(step)
    meas = world.campaign(q=q).meas
    meas = dataclasses.replace(meas, timestamp=None, sequence=np.arange(meas.n_poses) * 10.0)
    cal = _calibrated(server, doc, model, meas, "sequence.csv", "auto", 180)["calibration_id"]
    answer = server.client.get(f"/calibrations/{cal}").json()
    steps = [f for f in answer["diagnosis"]["findings"] if str(f.get("form", "")).startswith("step[")]
    where = (seed, model.joint_names[j], [f.get("form") for f in answer["diagnosis"]["findings"]])
    assert [f["joints"] for f in steps] == [[model.joint_names[j]]], where
    assert any(p["name"].startswith(f"{model.joint_names[j]}.step[") for p in answer["parameters"]), where
    early = np.arange(10)  # measured before the re-homing
    act = model.actuated
    body = {"joints": (meas.joints[early][:, act] / model.joint_scale()[act]).tolist()}  # model units
    placed = server.client.post(f"/calibrations/{cal}/predict", json={**body, "sequence": (early * 10.0).tolist()})
    now = server.client.post(f"/calibrations/{cal}/predict", json=body)
    assert placed.status_code == now.status_code == 200, (placed.text, now.text)
    off = {k: np.linalg.norm(np.asarray(r.json()["positions"]) - meas.points[early], axis=1)
           for k, r in (("placed", placed), ("now", now))}
    noise = world.noise_rms_mm(q)
    assert np.sqrt(np.mean(off["placed"] ** 2)) < 4 * noise < np.sqrt(np.mean(off["now"] ** 2)), (off, noise, where)
    # compensate places its rows the same way: targets measured before the re-homing, compensated at their sequence,
    # are reached by the model at that sequence; the same joints in the robot's current state are off by the step
    comp = server.client.post(f"/calibrations/{cal}/compensate", json={
        "targets": meas.points[early].tolist(), "seed_joints": body["joints"], "sequence": (early * 10.0).tolist()})
    assert comp.status_code == 200, comp.text
    assert all(comp.json()["reachable"]), comp.json()
    commands = {"joints": comp.json()["joints"]}
    at = {k: np.linalg.norm(np.asarray(server.client.post(f"/calibrations/{cal}/predict", json={**commands, **extra})
                                       .json()["positions"]) - meas.points[early], axis=1)
          for k, extra in (("placed", {"sequence": (early * 10.0).tolist()}), ("now", {}))}
    assert at["placed"].max() < 1e-3 < 4 * noise < np.sqrt(np.mean(at["now"] ** 2)), (at, noise, where)
    bad = server.client.post(f"/calibrations/{cal}/compensate", json={
        "targets": meas.points[early].tolist(), "seed_joints": body["joints"], "sequence": [1.0, 2.0],
        "temperature": 500.0})
    assert bad.status_code == 422, bad.text
    fields = {e["field"] for e in bad.json()["errors"]}
    assert {"body.sequence", "body.temperature"} <= fields, bad.json()
