"""POST /robots/{id}/plan over real HTTP against `calib serve`, and `calib plan` writing a CSV."""
from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from calib_core import parse_model, write_measurements
from calib_core.robots import spray7
from calib_world import World, hide

from .conftest import ROOT, assert_problem
from .test_api import mset, robot, run_job  # noqa: F401 (module fixtures: a robot and its measurement set)


def _within_limits(model_doc, joints):
    lo, hi = np.array([j["limits"] for j in model_doc["joints"]]).T
    q = np.array(joints)
    return bool(np.all(q >= lo - 1e-9) and np.all(q <= hi + 1e-9))


def test_a_geometric_plan_in_model_units(server, robot, model_doc):
    r = server.client.post(f"/robots/{robot['id']}/plan", json={"n_poses": 20, "purpose": "geometric", "seed": 4})
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["joint_names"] == [f"J{i}" for i in range(1, 8)] and out["unit"] == {"length": "mm", "angle": "deg"}
    assert np.shape(out["joints"]) == (20, 7) and _within_limits(model_doc, out["joints"])
    assert out["targets"] is None and out["payload_kg"] is None
    obs = out["observability"]
    assert obs["criterion"].startswith("D-optimal") and obs["n_poses"] == 20 and obs["seed"] == 4
    g = obs["geometry"]
    assert g["planned"]["log_det"] > g["random"]["log_det"]
    assert {"condition_number", "observability_index", "rank"} <= set(g["planned"])
    again = server.client.post(f"/robots/{robot['id']}/plan", json={"n_poses": 20, "seed": 4}).json()
    assert again["joints"] == out["joints"]  # the seed makes it reproducible


def test_a_plan_after_a_measured_set_adds_to_it(server, robot, mset):
    r = server.client.post(f"/robots/{robot['id']}/plan", json={"n_poses": 10, "measurement_set_id": mset["id"]})
    assert r.status_code == 200, r.text
    g = r.json()["observability"]["geometry"]
    assert g["planned"]["log_det"] > g["random"]["log_det"] > g["measured"]["log_det"]


@pytest.mark.parametrize("body, field, value", [
    ({"n_poses": 0}, "body.n_poses", 0),
    ({"n_poses": "50"}, "body.n_poses", "50"),
    ({"n_poses": 5000}, "body.n_poses", 5000),
    ({"purpose": "accuracy"}, "body.purpose", "accuracy"),
    ({"tracker": [1000, 0]}, "body.tracker", [1000, 0]),
    ({"tracker": [1e9, 0, 0]}, "body.tracker", [1e9, 0, 0]),
    ({"max_incidence_deg": 0.01}, "body.max_incidence_deg", 0.01),
    ({"purpose": "diagnosis"}, "body.measurement_set_id", None),
    ({"purpose": "diagnosis", "measurement_set_id": "no-such-set"}, "body.measurement_set_id", "no-such-set"),
    ({"poses": 50}, "body.poses", 50),
])
def test_bad_requests_name_the_field_and_value(server, robot, body, field, value):
    err = assert_problem(server.client.post(f"/robots/{robot['id']}/plan", json=body), 422)
    assert any(e["field"] == field and e["value"] == value for e in err["errors"]), err


def test_an_unknown_robot_is_404(server):
    err = assert_problem(server.client.post("/robots/nope/plan", json={"n_poses": 10}), 404)
    assert "robot" in err["detail"] and "nope" in err["detail"], err


def test_a_diagnosis_plan_needs_look_alikes_to_split(server, robot, mset):
    url = f"/robots/{robot['id']}/plan"
    body = {"n_poses": 10, "purpose": "diagnosis", "measurement_set_id": mset["id"]}
    err = assert_problem(server.client.post(url, json=body), 422)
    assert "auto" in err["detail"]  # no auto calibration yet: says which job to run
    assert run_job(server, mset["id"], "auto")["status"] == "succeeded"
    err = assert_problem(server.client.post(url, json=body), 422)  # a rigid twin: nothing indistinguishable
    assert "look-alike" in err["detail"] and err["errors"][0]["value"] == mset["id"]


@pytest.mark.slow
def test_a_diagnosis_plan_splits_the_look_alikes_of_a_measured_set(server, robot):
    """The independent world hides a stiffening spring on J4; the auto diagnosis of 150 random poses names the
    compliance of J4 but cannot tell it from the bending of the link ending at J5 (benchmarks/bench_plan.py,
    draw 0): the plan's poses separate them far more than random ones would."""
    model = parse_model(spray7())
    world = World(model, 5000)
    rng = np.random.default_rng((0, 7))
    q = world.sample_joints(150, rng)
    hide(world, "stiffening_spring", 3.0, rng, q=q, payload_kg=[0.0, 10.0, 20.0])
    text = write_measurements(world.measure(q, payload_kg=[0.0, 10.0, 20.0]), model)
    ms = server.client.post(f"/robots/{robot['id']}/measurements", files={"file": ("spring.csv", text)}).json()
    assert run_job(server, ms["id"], "auto")["status"] == "succeeded"
    r = server.client.post(f"/robots/{robot['id']}/plan", json={"n_poses": 30, "purpose": "diagnosis",
                                                               "measurement_set_id": ms["id"]}, timeout=120)
    assert r.status_code == 200, r.text
    out = r.json()
    rival = out["observability"]["rivals"][0]
    assert rival["look_alike"] == "link_deflection[J5]" and rival["found"].startswith("joint_compliance[J4]")
    assert rival["planned"]["separation_chi2"] > 3 * rival["random"]["separation_chi2"]
    assert rival["expected_to_split"]  # more than the diagnosis needs to tell them apart
    assert set(out["payload_kg"]) <= {0.0, 10.0, 20.0} and len(out["payload_kg"]) == 30


def test_calib_plan_writes_a_csv_a_robot_program_can_run(tmp_path, model_doc):
    (tmp_path / "robot.json").write_text(json.dumps(model_doc))
    r = subprocess.run([sys.executable, "-m", "service.cli", "plan", "--robot", str(tmp_path / "robot.json"), "--n",
                        "25", "--purpose", "geometric", "--candidates", "4000", "--out", str(tmp_path / "plan.csv")],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "condition number" in r.stderr
    rows = list(csv.reader(ln for ln in (tmp_path / "plan.csv").read_text().splitlines() if not ln.startswith("#")))
    assert rows[0] == ["point"] + [f"J{i}" for i in range(1, 8)]
    assert len(rows) == 26 and _within_limits(model_doc, [[float(v) for v in row[1:]] for row in rows[1:]])
    bad = subprocess.run([sys.executable, "-m", "service.cli", "plan", "--robot", str(tmp_path / "robot.json"),
                          "--purpose", "diagnosis"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--data" in bad.stderr
