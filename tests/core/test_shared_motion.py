"""Targets measured at one pose that move together (issue 9): a torso carrying two arms, each pose measured at
both hands, with a motion drawn here upstream of where the arms part (a torso joint landing differently at each
visit, or the base rocking about a pivot under it) or, for the null, the arms' own joints landing differently
(independent between the hands). The motion is written in this file, not with the diagnosis's functions; the robot's
geometry is the product's forward kinematics."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_core import kinematics as K
from calib_core.diagnosis import diagnose, holdout_gain
from calib_core.diagnosis.residual import _shared_motion
from calib_core.identify import fold_ids, identify, pose_folds
from calib_core.io import Measurements
from calib_core.model import parse_model
from calib_core.shared_motion import pose_groups, pose_noise, shared_joints
from calib_core.twin import sample_uniform
from tests.core.test_tree import torso_two_arms

SIGMA_MM = 0.05
N_POSES = 120


@pytest.fixture(scope="module")
def tree():
    return parse_model(torso_two_arms())


def _campaign(tree, rng, motion: str, size_x_noise: float):
    """Both hands at every pose; `motion`: 'torso' (one torso joint off by a per-pose random angle), 'base' (the
    robot rocking about a pivot 400 mm under its base by a per-pose random tilt), 'arms' (every arm joint off by a
    per-pose random angle, each hand its own) or 'none'. The motion's 3-D RMS at a hand is size_x_noise times the
    noise's. Returns the measurements, the true share of a hand's mean square error the motion makes, the torso
    joint drawn and the true geometry."""
    q = sample_uniform(tree, N_POSES, rng)
    x = K.nominal_vector(tree)
    geo = K.layout(tree).geometry
    x[geo] += np.where(K.angular_mask(tree)[geo], 2e-3, 0.5) * rng.normal(size=x[geo].shape)
    rows = np.repeat(np.arange(N_POSES), 2)
    target = np.tile([0, 1], N_POSES)
    labels = K.Labels(target, np.zeros(2 * N_POSES, int))
    clean = K.forward(tree, x, q[rows], None, labels)
    names = tree.joint_names
    torso = names.index(rng.choice(["T1", "T2", "T3"]))
    arm = [names.index(n) for n in ("L1", "L2", "L3", "L4", "R1", "R2", "R3", "R4")]
    pivot = np.array([0.0, 0.0, -400.0])

    def displaced(unit: float, g: np.random.Generator) -> np.ndarray:
        if motion == "torso":
            dq, d = q.copy(), unit * g.normal(size=N_POSES)
            dq[:, torso] += d
            if names[torso] in ("T2", "T3"):  # the passive T4 keeps the shoulders level on the actual angles
                dq[:, names.index("T4")] -= d
            return K.forward(tree, x, dq[rows], None, labels) - clean
        if motion == "base":
            R = Rotation.from_rotvec(unit * g.normal(size=(N_POSES, 3)) * [1, 1, 0.2]).as_matrix()[rows]
            return np.einsum("nij,nj->ni", R, clean - pivot) + pivot - clean
        if motion == "arms":
            dq = q[rows].copy()
            dq[:, arm] += unit * g.normal(size=(2 * N_POSES, len(arm)))  # each hand's measurement its own
            return K.forward(tree, x, dq, None, labels) - clean
        return np.zeros_like(clean)

    d = np.zeros_like(clean)
    if motion != "none":
        state = int(rng.integers(2**31))
        unit = np.sqrt(np.mean(np.sum(displaced(1e-4, np.random.default_rng(state)) ** 2, axis=1)))
        d = displaced(1e-4 * size_x_noise * np.sqrt(3) * SIGMA_MM / unit, np.random.default_rng(state))
    moved = np.mean(np.sum(d**2, axis=1))
    share = moved / (moved + 3 * SIGMA_MM**2)
    pts = clean + d + rng.normal(0, SIGMA_MM, clean.shape)
    meas = Measurements(joints=q[rows], points=pts, sigma=np.full(2 * N_POSES, SIGMA_MM), target=target,
                        point_ids=[f"{i}-{'lr'[t]}" for i, t in zip(rows, target)])
    return meas, share, names[torso], x


def _found(tree, meas):
    """Every shared motion tried, largest share first."""
    cal = identify(tree, meas, folds=0)
    return _shared_motion(cal, meas, cal.sigma_mm, cal.x)


def test_poses_group_the_targets_measured_together(tree):
    rng = np.random.default_rng(0)
    meas, *_ = _campaign(tree, rng, "none", 0.0)
    groups = pose_groups(meas, tree)
    assert len(groups) == N_POSES and all(sorted(meas.target[g]) == [0, 1] for g in groups)
    assert [tree.joint_names[j] for j in shared_joints(tree)] == ["T1", "T2", "T3", "T4"]
    one = meas.subset(np.flatnonzero(meas.target == 0))
    assert pose_groups(one, tree) == [] and _shared_motion(identify(tree, one, folds=0), one, one.noise_sigma_mm(),
                                                    None) is None


def test_the_targets_of_a_pose_are_one_unit_in_folds_and_paired_tests(tree, seed):
    """Held-out folds keep the targets of a pose together, and a paired test counts them once: two targets that share
    their pose's error are not two independent poses (a pose visited again, or a set of one target, is unchanged)."""
    rng = np.random.default_rng(seed)
    meas, *_ = _campaign(tree, rng, "none", 0.0)
    assign = pose_folds(meas, 5)
    assert (assign[0::2] == assign[1::2]).all()
    one = meas.subset(np.flatnonzero(meas.target == 0))
    assert (pose_folds(one, 5) == fold_ids(one.n_poses, 5)).all() and (one.pose_index() == np.arange(N_POSES)).all()
    again = Measurements(joints=np.r_[one.joints, one.joints[:5]], points=np.r_[one.points, one.points[:5]],
                         target=np.zeros(N_POSES + 5, int))
    assert len(np.unique(again.pose_index())) == N_POSES + 5  # a revisit is another placement of the robot
    drop = rng.normal(0.3, 1.0, N_POSES)  # per pose, shared by both of its targets

    def stub(d2, index):
        return SimpleNamespace(holdout_residual_mm=np.sqrt(d2), inliers=lambda: np.ones(len(d2), bool),
                               pose_index=index)
    base = 10.0 + np.abs(drop).max()
    single = holdout_gain(stub(np.full(N_POSES, base), None), stub(base - drop, None))
    paired = holdout_gain(stub(np.full(2 * N_POSES, base), meas.pose_index()),
                          stub(np.repeat(base - drop, 2), meas.pose_index()))
    assert paired[0] == pytest.approx(single[0], rel=1e-9), (seed, single, paired)


@pytest.mark.parametrize("motion", ["torso", "base"])
def test_a_motion_upstream_of_the_arms_is_found_shared(tree, seed, motion):
    rng = np.random.default_rng(seed)
    size = rng.uniform(1.5, 3.0)
    meas, truth, joint, _ = _campaign(tree, rng, motion, size)
    found = _found(tree, meas)
    significant = [s for s in found if s.p_value < 0.01]
    assert significant, (seed, motion, joint, size, found)
    # one motion explains a large part of what the shared motion moves, and not much more: the share is estimated from
    # the two hands' cross-products at 120 poses (a torso joint, 700 draws: share - truth mean -0.28, std 0.14; 2 over
    # +0.15: seed 202 at +0.16, and a test run's seed 1287319432 at +0.24, its share capped at 1)
    assert truth / 3 < significant[0].share < truth + 0.3, (seed, motion, joint, size, truth, found)


def test_each_hand_on_its_own_is_not_shared(tree, seed):
    """The null: pure noise, or every arm joint landing differently at each hand's measurement (as large as the
    shared motion above): at most 2 of 20 draws below p = 0.01 (the test's size is 1 %)."""
    rng = np.random.default_rng(seed)
    ps = []
    for k in range(20):
        meas, *_ = _campaign(tree, rng, "arms" if k % 2 else "none", rng.uniform(1.0, 3.0))
        ps.append(min(s.p_value for s in _found(tree, meas)))
    assert sum(p < 0.01 for p in ps) <= 2, (seed, sorted(ps)[:4])


@pytest.mark.parametrize("motion", ["torso", "arms"])
def test_diagnosis_says_the_hands_move_together_only_when_they_do(tree, seed, motion):
    """The whole diagnosis: a torso joint landing differently at each pose is named as what the residual left
    follows, with the advice it calls for; each hand's own joints doing so is not."""
    rng = np.random.default_rng(seed)
    meas, *_ = _campaign(tree, rng, motion, rng.uniform(2.0, 3.0))
    d = diagnose(tree, meas)
    follows = [f for u in d.findings if u["kind"] == "unexplained" for f in u["follows"]]
    shared = [f for f in follows if f.get("family") == "shared_by_targets"]
    if motion == "torso":
        assert shared and shared[0]["p_value"] < 0.01, (seed, d.findings)
        text = next(u["evidence"] for u in d.findings if u["kind"] == "unexplained")
        assert "move together" in text and "reference target" in text, text
    else:
        assert not shared, (seed, shared)


def test_the_shared_motion_weighed_as_noise_of_each_pose_predicts_fresh_poses_better(tree, seed):
    """A torso joint landing differently at each pose (2-4x the noise): the fit that weighs the shared motions found
    as noise of each pose (generalised least squares, identify's pose_noise) predicts fresh poses closer to the true geometry than ordinary
    least squares, which lets the per-pose motion pull the parameters."""
    rng = np.random.default_rng(seed)
    meas, _, joint, x = _campaign(tree, rng, "torso", rng.uniform(2.0, 4.0))
    ols = identify(tree, meas, folds=0)
    s = [f for f in _shared_motion(ols, meas, ols.sigma_mm, ols.x) if f.p_value < 0.01]
    gls = identify(tree, meas, folds=0, pose_noise=pose_noise(ols.robot.chain(meas.joints, meas)[0], meas, s))
    q = sample_uniform(tree, 200, rng)
    target = np.tile([0, 1], 200)
    fresh = Measurements(joints=np.repeat(q, 2, axis=0), points=np.zeros((400, 3)), target=target)
    truth = K.forward(tree, x, fresh.joints, None, K.Labels(target, np.zeros(400, int)))
    err = {name: float(np.sqrt(np.mean(np.sum((c.predict(fresh.joints, fresh) - truth) ** 2, axis=1))))
           for name, c in (("ols", ols), ("gls", gls))}
    assert len(gls.solution.x) == len(ols.solution.x) and gls.solution.residual.shape == meas.points.shape
    assert err["gls"] < err["ols"], (seed, joint, s, err)


def test_whitening_a_pose_is_generalised_least_squares(seed):
    """PoseNoise.whitening against the dense covariance built here: for drawn poses of 1-4 rows, motions, sizes and
    sigmas, (W a / sigma)' (W b / sigma) = a' V^-1 b with V = diag(sigma^2) + sum_k tau_k^2 z_k z_k' over each pose's
    rows (the rows of two poses independent): the fit on whitened rows is GLS."""
    from calib_core.shared_motion import PoseNoise

    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 5, size=int(rng.integers(3, 9)))
    unit = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))  # rows of a pose need not be adjacent
    N, k = len(unit), int(rng.integers(1, 5))
    noise = PoseNoise(unit, rng.normal(size=(N, 3, k)), rng.uniform(0.1, 2.0, k))
    sigma = rng.uniform(0.02, 0.2, N)
    V = np.diag(np.repeat(sigma**2, 3))
    for p in range(len(sizes)):
        for j in range(k):
            z = np.where((unit == p)[:, None], noise.Z[:, :, j], 0.0).ravel()
            V += noise.tau[j] ** 2 * np.outer(z, z)
    a, b = rng.normal(size=(N, 3)), rng.normal(size=(N, 3, 2))
    white = noise.whitening(sigma)
    got = (white(a) / sigma[:, None]).ravel() @ (white(b) / sigma[:, None, None]).reshape(3 * N, 2)
    want = a.ravel() @ np.linalg.solve(V, b.reshape(3 * N, 2))
    assert np.allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max()), (seed, got, want)
