"""Real cells in calib_core (contract section 5): a torso carrying two arms, a coupled joint, fixed mount rows,
two targets and several setups, recovered exactly from noise-free data."""
import dataclasses

import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.identify import identify
from calib_core.io import Measurements, parse_measurements, write_measurements
from calib_core.model import ModelError, parse_model
from calib_core.twin import Twin, sample_uniform


def torso_two_arms(mass: bool = False) -> dict:
    """A humanoid-like torso: T1 (vertical), T2, T3 pitch, T4 passive with q = -q2 - q3 (keeps the shoulders
    level), a fixed shoulder plate per arm and a 4-joint arm each side (xyz/rpy/axis rows on the right)."""
    m = (lambda kg, c: {"mass": kg, "com": c}) if mass else (lambda kg, c: {})
    lim = [-150.0, 150.0]
    return {
        "name": "torso_two_arms", "units": {"length": "mm", "angle": "deg"},
        "joints": [
            {"name": "T1", "a": 0, "alpha": 0, "d": 300, "theta": 0, "limits": lim, **m(20, [0, 0, 100])},
            {"name": "T2", "a": 50, "alpha": -90, "d": 0, "theta": -90, "limits": [-90, 90], **m(15, [150, 0, 0])},
            {"name": "T3", "a": 400, "alpha": 0, "d": 0, "theta": 0, "limits": [-120, 120], **m(12, [150, 0, 0])},
            {"name": "T4", "a": 350, "alpha": 0, "d": 0, "theta": 0, "coupled": {"T2": -1.0, "T3": -1.0},
             **m(10, [0, 0, 0])},
            {"name": "Lplate", "type": "fixed", "parent": "T4", "xyz": [0, 0, 250], "rpy": [90, 0, 0], **m(1, [0, 0, 0])},
            {"name": "L1", "a": 0, "alpha": 0, "d": 0, "theta": 0, "limits": lim, **m(4, [0, 0, 50])},
            {"name": "L2", "a": 0, "alpha": 90, "d": 0, "theta": 0, "limits": lim, **m(3, [150, 0, 0])},
            {"name": "L3", "a": 300, "alpha": 0, "d": 0, "theta": 0, "limits": lim, **m(2, [120, 0, 0])},
            {"name": "L4", "a": 250, "alpha": -90, "d": 80, "theta": 0, "limits": lim, **m(1, [0, 0, 30])},
            {"name": "Rplate", "type": "fixed", "parent": "T4", "xyz": [0, 0, -250], "rpy": [-90, 0, 0],
             **m(1, [0, 0, 0])},
            {"name": "R1", "axis": [0, 0, 1], "limits": lim, **m(4, [0, 0, 50])},
            {"name": "R2", "axis": [0, 1, 0], "xyz": [0, 0, 60], "limits": lim, **m(3, [0, 0, 150])},
            {"name": "R3", "axis": [0, 1, 0], "xyz": [0, 0, 300], "limits": lim, **m(2, [0, 0, 120])},
            {"name": "R4", "axis": [0, 0, 1], "xyz": [30, 0, 250], "rpy": [0, 0, 15], "limits": lim,
             **m(1, [0, 0, 30])},
        ],
        "targets": [{"name": "left", "parent": "L4", "xyz": [20, 10, 120]},
                    {"name": "right", "parent": "R4", "xyz": [-15, 5, 110]}],
    }


@pytest.fixture(scope="module")
def tree():
    return parse_model(torso_two_arms())


def test_tree_structure(tree):
    assert tree.actuated_names == ("T1", "T2", "T3", "L1", "L2", "L3", "L4", "R1", "R2", "R3", "R4")
    q = tree.expand_joints(np.arange(11.0)[None] / 10)
    assert q[0, 3] == pytest.approx(-0.1 - 0.2)  # T4 = -T2 - T3
    assert q[0, 4] == q[0, 9] == 0.0  # fixed plates
    anc = tree.ancestors()
    assert anc[tree.joint_names.index("R4"), tree.joint_names.index("T4")]
    assert not anc[tree.joint_names.index("R4"), tree.joint_names.index("L1")]


def test_left_arm_does_not_move_the_right_target(tree):
    rng = np.random.default_rng(3)
    q = sample_uniform(tree, 20, rng)
    labels = K.Labels(np.ones(20, int), np.zeros(20, int))  # every pose measures "right"
    x = K.nominal_vector(tree)
    p = K.forward(tree, x, q, None, labels)
    q2 = q.copy()
    q2[:, [5, 6, 7, 8]] += 0.3  # move the left arm only
    assert np.allclose(K.forward(tree, x, q2, None, labels), p, atol=1e-12)
    J = K.Chain(tree, x, q, None, labels).jacobian()
    names = K.parameter_names(tree)
    left = [i for i, nm in enumerate(names) if nm.startswith(("L1.", "L2.", "L3.", "L4.", "tool[left]"))]
    assert np.all(J[:, :, left] == 0.0)


@pytest.mark.parametrize("seed", [11, 12])
def test_analytic_jacobian_matches_finite_differences_on_the_tree(tree, seed):
    rng = np.random.default_rng(seed)
    q = sample_uniform(tree, 8, rng)
    labels = K.Labels(rng.integers(0, 2, 8), np.zeros(8, int))
    x = K.nominal_vector(tree) + rng.normal(0, 0.01, K.layout(tree).size)
    J = K.Chain(tree, x, q, None, labels).jacobian()
    h = 1e-6
    for i in range(len(x)):
        d = np.zeros_like(x)
        d[i] = h
        fd = (K.forward(tree, x + d, q, None, labels) - K.forward(tree, x - d, q, None, labels)) / (2 * h)
        assert np.allclose(J[:, :, i], fd, atol=1e-5), K.parameter_names(tree)[i]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_twin_of_a_tree_with_a_coupled_joint_and_two_targets_is_recovered_exactly(tree, seed):
    twin = Twin(tree, seed=seed, repeatability_mm=0.0, tracker_noise=False)
    meas = twin.measure(n=160)
    assert set(meas.target) == {0, 1}
    cal = identify(tree, meas, folds=0, regularize=False)
    names = cal.names
    assert len(names) == len(set(names))  # the shared torso is identified once
    assert sum(nm.startswith("T2.") for nm in names) == K.G
    assert cal.to_dict()["metrics"]["rms_mm"] < 1e-6
    fresh = twin.measure(n=60)
    pred = cal.predict(fresh.joints, fresh)
    assert np.abs(pred - twin.true_points(fresh.joints, fresh.labels)).max() < 1e-5


def test_setups_get_their_own_base_and_share_the_robot(tree):
    rng = np.random.default_rng(8)
    twin = Twin(tree, seed=4, repeatability_mm=0.0, tracker_noise=False)
    a, b = twin.measure(n=90), twin.measure(n=90)
    # the second station: the same robot seen from elsewhere (a rigid move of the tracker)
    from scipy.spatial.transform import Rotation
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.uniform(-2000, 2000, 3)
    pts = np.r_[a.points, b.points @ R.T + t]
    meas = Measurements(joints=np.r_[a.joints, b.joints], points=pts, target=np.r_[a.target, b.target],
                        setup=np.r_[np.zeros(90, int), np.ones(90, int)], setup_names=("station A", "station B"))
    text = write_measurements(meas, tree)
    assert "setup" in text.splitlines()[0] and "T4" not in text.splitlines()[0].split(",")  # no coupled column
    back = parse_measurements(text, tree)
    assert back.setup_names == ("station A", "station B")
    cal = identify(tree, back, folds=0, regularize=False)
    assert cal.to_dict()["metrics"]["rms_mm"] < 1e-4
    doc = cal.to_dict()
    assert [s["setup"] for s in doc["setups"]] == ["station A", "station B"]
    Ra, pa = cal.base_pose(0)
    Rb_, pb = cal.base_pose(1)
    assert np.allclose(Rb_, R @ Ra, atol=1e-7) and np.allclose(pb, R @ pa + t, atol=1e-4)


def test_coupled_column_must_agree_and_fixed_rows_have_no_column(tree):
    twin = Twin(tree, seed=5, repeatability_mm=0.0, tracker_noise=False)
    meas = twin.measure(n=5)
    text = write_measurements(meas, tree)
    lines = text.splitlines()
    head = lines[0] + ",T4"
    good = [ln + f",{np.degrees(q):.9f}" for ln, q in zip(lines[1:], meas.joints[:, 3])]
    assert parse_measurements("\n".join([head, *good]), tree).n_poses == 5
    bad = good[:2] + [lines[3] + ",12.5"] + good[3:]
    with pytest.raises(Exception) as exc:
        parse_measurements("\n".join([head, *bad]), tree)
    err = exc.value.errors[0]
    assert err["row"] == 4 and err["column"] == "T4" and "coupling" in err["message"]
    with pytest.raises(Exception) as exc:
        parse_measurements("\n".join([lines[0] + ",Lplate", *(ln + ",0" for ln in lines[1:])]), tree)
    assert exc.value.errors[0]["column"] == "Lplate"
    no_target = "\n".join(",".join(f for k, f in enumerate(ln.split(",")) if k != lines[0].split(",").index("target"))
                          for ln in lines)
    with pytest.raises(Exception) as exc:
        parse_measurements(no_target, tree)
    assert exc.value.errors[0]["column"] == "target"


def test_model_errors_name_the_field():
    doc = torso_two_arms()
    doc["joints"][5]["parent"] = "R4"  # listed after
    doc["joints"][3]["coupled"] = {"T9": 1.0, "T3": 1e200}  # 1e200: the drive's load overflowed into an SVD error
    doc["targets"][1]["parent"] = "nope"
    with pytest.raises(ModelError) as exc:
        parse_model(doc)
    fields = {e["field"] for e in exc.value.errors}
    assert {"joints[5].parent", "joints[3].coupled.T9", "joints[3].coupled.T3", "targets[1].parent"} <= fields


def test_tree_model_round_trips_through_contract_json(tree):
    rng = np.random.default_rng(9)
    g = tree.geometry + rng.normal(0, 0.01, tree.geometry.shape)
    tools = tree.target_points + rng.normal(0, 1, (2, 3))
    back = parse_model(tree.to_dict(g, tools))
    q = sample_uniform(tree, 30, rng)
    labels = K.Labels(rng.integers(0, 2, 30), np.zeros(30, int))
    x = np.concatenate([g.ravel(), np.zeros(6), tools.ravel()])
    assert np.abs(K.forward(tree, x, q, None, labels)
                  - K.forward(back, K.nominal_vector(back), q, None, labels)).max() < 1e-9


@pytest.mark.parametrize("seed", [21, 22])
def test_compensation_on_the_tree_keeps_the_coupling_and_serves_each_rows_target(tree, seed):
    from calib_core.compensate import compensate

    twin = Twin(tree, seed=seed, repeatability_mm=0.0, tracker_noise=False)
    cal = identify(tree, twin.measure(n=160), folds=0, regularize=False)
    rng = np.random.default_rng(seed)
    want = sample_uniform(tree, 12, rng)  # rows; the actuated part is what a program commands
    cols = Measurements(joints=want, points=np.zeros((12, 3)), target=rng.integers(0, 2, 12))
    truth = twin.true_points(want, cols.labels)
    act = tree.actuated
    seeds = want[:, act] + rng.normal(0, 0.02, (12, len(act)))
    out = compensate(cal.robot, truth, seeds, columns=cols)
    assert out.joints.shape == (12, len(act)) and out.reachable.all()
    rows = tree.expand_joints(out.joints)
    assert np.allclose(rows[:, 3], -rows[:, 1] - rows[:, 2])  # T4 follows T2 and T3
    assert np.abs(twin.true_points(rows, cols.labels) - truth).max() < 1e-3
    # each row moved only the joints on the way to its own target: the other arm stays at its seed
    left = [tree.actuated_names.index(n) for n in ("L1", "L2", "L3", "L4")]
    right_rows = cols.target == 1
    assert np.allclose(out.joints[np.ix_(right_rows, left)], seeds[np.ix_(right_rows, left)], atol=1e-9)


@pytest.mark.parametrize("seed", [41, 42])
def test_orientation_rows_sharpen_the_geometry(seed):
    """A 3-joint arm measured at 25 poses: with the tracker's orientation (6-D rows) the shared geometric
    parameters are determined better than from the points alone, still agree with the truth, and the answer's
    model is the robot's own (the virtual targets that carried the orientation are gone)."""
    from scipy.spatial.transform import Rotation

    from calib_core.orientation import with_orientation
    from calib_core.pipeline import calibrate
    from calib_core.shared_motion import pose_groups

    doc = {"name": "arm3", "joints": [
        {"name": "J1", "a": 0, "alpha": 0, "d": 400, "theta": 0, "limits": [-170, 170]},
        {"name": "J2", "a": 100, "alpha": -90, "d": 0, "theta": 0, "limits": [-90, 90]},
        {"name": "J3", "a": 500, "alpha": 0, "d": 0, "theta": 0, "limits": [-120, 120]}],
        "tool": [300, 0, 50]}
    model = parse_model(doc)
    twin = Twin(model, seed=seed)
    meas = twin.measure(n=25)
    R = K.Chain(model, twin.x_true, meas.joints, twin.R0).R_end  # the target frame in the tracker's, exactly
    xyzw = Rotation.from_matrix(R).as_quat()
    meas.orientation = np.c_[xyzw[:, 3], xyzw[:, :3]]
    m6, meas6 = with_orientation(model, meas)
    assert m6.n_targets == 4 and meas6.n_poses == 4 * 25
    # one reading is one unit (folds, paired tests), and its virtual points are not targets that move together
    assert len(np.unique(meas6.pose_index())) == 25 and pose_groups(meas6, m6) == []
    plain = calibrate(model, dataclasses.replace(meas, orientation=None))
    full = calibrate(model, meas)
    geo = lambda out: {p["name"]: p for p in out["parameters"] if p["name"][:2] in ("J1", "J2", "J3")}  # noqa: E731
    a, b = geo(plain), geo(full)
    common = [k for k in a if k in b and a[k]["std"] and b[k]["std"]]
    assert common
    assert np.median([b[k]["std"] / a[k]["std"] for k in common]) < 0.8
    from calib_core.identify import CalibratedRobot

    fresh = twin.sample_joints(200)
    err = {k: np.linalg.norm(CalibratedRobot.from_state(model, out["robot_state"]).predict(fresh)
                             - twin.true_points(fresh), axis=1).mean() for k, out in (("plain", plain), ("6d", full))}
    assert err["6d"] < 1.1 * err["plain"] and err["6d"] < 0.1, err
    assert full["orientation"]["rows"] == 25
    assert len(full["robot_state"]["x"]) == len(K.nominal_vector(model))  # the robot's model, no virtual targets
    assert "targets" not in full["calibrated_model"]


def test_registration_frees_every_setups_base_and_every_target(tree):
    """identify(free=("base", "tool")) (the registration the model selection starts from) frees base[s].* and
    tool[t].*, and a full fit ranks them first, so no target point is traded for a row's geometry."""
    twin = Twin(tree, seed=6, repeatability_mm=0.0, tracker_noise=False)
    a, b = twin.measure(n=60), twin.measure(n=60)
    meas = Measurements(joints=np.r_[a.joints, b.joints], points=np.r_[a.points, b.points + [900.0, 0.0, 0.0]],
                        target=np.r_[a.target, b.target], setup=np.r_[np.zeros(60, int), np.ones(60, int)],
                        setup_names=("A", "B"))
    reg = identify(tree, meas, free=("base", "tool"), folds=0)
    freed = {reg.names[i] for i in reg.free}
    assert freed == {n for n in reg.names if n.startswith(("base[", "tool["))}
    full = identify(tree, meas, folds=0, regularize=False)
    assert {n for n in full.names if n.startswith(("base[", "tool["))} <= {full.names[i] for i in full.free}
