"""Pose planning: planned poses are within the limits and visible, D-optimal sets carry more information than
random ones, and a diagnosis plan tells two look-alike causes apart better than random poses do."""
import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.effects import CyclicJointError, JointScale
from calib_core.identify import CalibratedRobot, identify
from calib_core.identifiability import structural
from calib_core.io import Measurements
from calib_core.model import parse_model
from calib_core.instruments import instrument
from calib_core.plan import (MAX_INCIDENCE_DEG, REPEATABILITY_MM, TRACKER_DISTANCE_MM, default_tracker, lookalike_pairs,
                             observability, outward, plan, visible_pool)
from calib_core.robots import arm6, spray7
from calib_core.twin import Twin, sample_uniform

from .chains import random_chain

SPRAY = parse_model(spray7())
FEW = 4000
"""Candidates in these tests (the product default is 20,000; the benchmark times that)."""


def _incidence_deg(model, joints_act, tracker):
    chain = K.Chain(model, K.nominal_vector(model), model.expand_joints(joints_act))
    sight = tracker - chain.p
    cos = (outward(model, chain) * sight).sum(1) / np.linalg.norm(sight, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.mark.parametrize("doc", [spray7, arm6], ids=["spray7", "arm6"])
def test_planned_poses_are_within_the_limits_and_face_the_tracker(doc):
    model = parse_model(doc())
    p = plan(model, 30, candidates=FEW, seed=3)
    lo, hi = model.limits[model.actuated].T
    assert p.joints.shape == (30, len(model.actuated))
    assert np.all(p.joints >= lo) and np.all(p.joints <= hi)
    assert len(np.unique(p.joints, axis=0)) == 30  # distinct poses
    tracker = np.array(p.observability["tracker_mm"])
    assert np.all(_incidence_deg(model, p.joints, tracker) <= MAX_INCIDENCE_DEG + 1e-6)
    assert np.allclose(p.model_units(model)[:, 0] * model.joint_scale()[model.actuated[0]], p.joints[:, 0])


def test_the_default_tracker_stands_level_three_metres_from_the_workspace():
    chain = K.Chain(SPRAY, K.nominal_vector(SPRAY), sample_uniform(SPRAY, 2000, np.random.default_rng(0)))
    t = default_tracker(SPRAY, chain, outward(SPRAY, chain), MAX_INCIDENCE_DEG)
    up = -SPRAY.gravity / np.linalg.norm(SPRAY.gravity)
    offset = t - chain.p.mean(0)
    assert np.linalg.norm(offset) == pytest.approx(TRACKER_DISTANCE_MM)
    assert abs(offset @ up) < 1e-6  # level with the centre
    assert abs(offset[2]) < 0.1 * TRACKER_DISTANCE_MM  # beside spray7's rail (along z), not at its end


def test_a_tracker_that_sees_nothing_is_refused():
    with pytest.raises(ValueError, match="face the tracker"):
        plan(SPRAY, 20, candidates=FEW, max_incidence_deg=0.01)


def _log_dets(model, p, n_random, seed):
    """log det of the planned set and of n_random random visible sets of its size, noise-weighted as the planner
    weights them, with the same column scale."""
    tracker = np.array(p.observability["tracker_mm"])
    pool = visible_pool(model, FEW, np.random.default_rng(seed), tracker)
    ident = structural(model).identifiable
    names = K.parameter_names(model)
    J = pool.chain.jacobian() / pool.sigma[:, None, None]
    scale = np.sqrt((J[:, :, ident] ** 2).sum(axis=(0, 1)) / len(J))
    mine = K.Chain(model, K.nominal_vector(model), model.expand_joints(p.joints))
    sigma = np.hypot(instrument(None).sigma_mm(mine.p - tracker), REPEATABILITY_MM)
    rng = np.random.default_rng(seed + 1)
    randoms = [observability(J[rng.choice(len(J), len(p.joints), replace=False)], scale, ident, names)["log_det"]
               for _ in range(n_random)]
    return observability(mine.jacobian() / sigma[:, None, None], scale, ident, names)["log_det"], randoms


def test_d_optimal_sets_carry_more_information_than_random_sets(seed):
    """Several robots (spray7 and a random chain per run), several random sets: the greedy D-optimal set has the
    larger log det of the information matrix every time (statistical: the margin is large, not guaranteed)."""
    rng = np.random.default_rng(seed)
    for model in (SPRAY, random_chain(rng)):
        p = plan(model, 40, candidates=FEW, seed=int(rng.integers(2**31)), loads=False)
        planned, randoms = _log_dets(model, p, 5, int(rng.integers(2**31)))
        where = f"{model.name} {model.joint_names}, seed {seed}: planned {planned:.1f}, random {np.round(randoms, 1)}"
        assert planned > max(randoms), where
        g = p.observability["geometry"]
        assert g["planned"]["log_det"] > g["random"]["log_det"], where
        assert g["information_gain_per_parameter"] > 1.0, where


def test_load_variety_keeps_the_geometry_and_reports_the_loaded_joints():
    p = plan(SPRAY, 40, candidates=FEW, seed=5)
    assert p.observability["loaded_joints"] == ["J3", "J4", "J6"]
    assert "compliance" in p.observability["criterion"]
    g = p.observability["geometry"]
    assert g["planned"]["log_det"] > g["random"]["log_det"]


def test_a_plan_after_a_measured_set_adds_to_what_it_identifies():
    twin = Twin(SPRAY, 2)
    meas = twin.measure(n=40)
    p = plan(SPRAY, 20, candidates=FEW, meas=meas, seed=2)
    g = p.observability["geometry"]
    assert g["planned"]["log_det"] > g["random"]["log_det"] > g["measured"]["log_det"]


# ------------------------------------------------------------------------------------------ diagnosis
J4 = 3
SCALE, HARMONIC = JointScale((J4,)), CyclicJointError((J4,), 1)
"""A joint scale error and a first harmonic of the same joint: alike over a small range of the joint (sin q ~ q)."""


def _measure(twin, truth, q, rng):
    meas = twin.measure(q)
    meas.points = truth.predict(q, meas) + rng.normal(0.0, 0.03, (len(q), 3))
    return meas


def _lack_of_fit(meas):
    """Weighted residual sum of squares of each rival fitted to the data (noise 30 um per axis)."""
    return [float(np.sum((identify(SPRAY, meas, effects=(e,), folds=0).solution.residual / 0.03) ** 2))
            for e in (SCALE, HARMONIC)]


def test_a_diagnosis_plan_splits_look_alikes_better_than_random_poses(seed):
    """J4 reads 0.05 % off (a scale error), but the measured set moved J4 only within +-20 deg, where a first
    harmonic fits as well. The plan's poses, measured, separate the two fits further than as many random poses."""
    rng = np.random.default_rng(seed)
    twin = Twin(SPRAY, int(rng.integers(2**31)))
    truth = CalibratedRobot(SPRAY, twin.x_true, twin.R0, (SCALE,), (np.array([5e-4]),))
    q = twin.sample_joints(80)
    q[:, J4] = rng.uniform(-0.35, 0.35, 80)
    meas = _measure(twin, truth, q, rng)
    before = _lack_of_fit(meas)
    assert abs(before[1] - before[0]) < 30, (before, seed)  # alike on the measured set
    pairs = lookalike_pairs(SPRAY, meas, (SCALE,), [{"kind": "joint_scale", "joints": ["J4"],
                                                     "indistinguishable_from": [{"kind": "cyclic_joint_error",
                                                                                 "joints": ["J4"]}]}])
    assert pairs == [(SCALE, HARMONIC)]
    p = plan(SPRAY, 15, "diagnosis", candidates=FEW, meas=meas, effects=(SCALE,), rivals=pairs, seed=seed)
    rival = p.observability["rivals"][0]
    assert rival["planned"]["separation_chi2"] > rival["random"]["separation_chi2"], (rival, seed)
    gained = {}
    for name, new in (("planned", SPRAY.expand_joints(p.joints)), ("random", twin.sample_joints(15))):
        more = _measure(twin, truth, new, rng)
        both = Measurements(np.vstack([meas.joints, more.joints]), np.vstack([meas.points, more.points]))
        fit = _lack_of_fit(both)
        gained[name] = fit[1] - fit[0]  # how much worse the wrong model fits
    assert gained["planned"] > gained["random"] and gained["planned"] > 30, (gained, seed)
