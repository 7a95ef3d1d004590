"""Blind search for hidden causes in the independent world (calib_world): kind, joint, size and seed are drawn,
the diagnosis must name what the physics did, with its own vocabulary (calib_world.EXPECTED)."""
import dataclasses
import re
import time
from types import SimpleNamespace

import numpy as np
import pytest

from calib_core.diagnosis import (ALPHA, NAMED_SHARE, PLAUSIBLE_TRAVEL_MM, PLAUSIBLE_TURN_RAD, diagnose, field_share,
                                  holdout_gain, holdout_ms, named_joints, noise_floor_mm, runs_probability, screen)
from calib_core.diagnosis.findings import _judge_sizes
from calib_core.diagnosis.fitter import _Fitter
from calib_core.diagnosis.masses import _identify_masses
from calib_core.diagnosis import plays as plays_module
from calib_core.diagnosis.plays import _identified_backlash
from calib_core.diagnosis.search import _Search
from calib_core.effects import Context, CyclicJointError, JointCompliance, LateralJointCompliance, candidates
from calib_core.identify import CalibratedRobot, identify
from calib_core.model import parse_model
from calib_core.pipeline import calibrate
from calib_core.robots import arm6, spray7
from calib_core.solve import OUTLIER_U
from calib_core.uncertainty import z_scores
from calib_world import EXPECTED, KINDS, World, hide, null_world
from calib_world.mechanics import ElasticBearings, JointSpring, ReHoming
from calib_world.scenarios import size_cause

SPRAY = parse_model(spray7())
NAMED = [k for k in KINDS if EXPECTED[k] != "unexplained"]
"""World kinds the diagnosis has a name for."""
OFF_VOCABULARY = [k for k in KINDS if EXPECTED[k] == "unexplained"]
"""World kinds no named cause has the shape of (re-homing step, cable force; a base tilting under the robot's
moment is named base_compliance since issue 34's round on Agile Justin)."""
SIZES = (3.0, 8.0)
"""Drawn log-uniformly: the unabsorbable part of the hidden cause is this many times the noise RMS.  The
benchmark (benchmarks/detection.py) measures the small sizes; a test must pass on every draw."""
TRUTH_LIMIT = 0.8
"""The extended model's error against the world's noise-free truth on fresh poses, times the noise RMS. The
benchmark measures a median of 0.28-0.30x and a 90th percentile of 0.52-0.62x (docs/RESULTS.md, 3.2); a
single draw must stay below this, where the geometry alone leaves 3-8x."""
BEARINGS_TRUTH_LIMIT = 1.6
"""Elastic bearings tilt under the bending moment across every joint, which depends on where the bodies really
are: along a joint axis the geometric fit does not pin that down (an MD-H d offset of a parallel axis), so the
lateral form is evaluated some 20 mm off and fits the world only approximately (0.4-1.2x the noise in
development draws, with the mass data identified); the geometry alone leaves 3-8x."""
BENDING_SHARE = 0.25
"""A link's bending is computed from the model's mass data, which are 15 % off the world's with centres of mass 30 mm
off (the mass steps cover compliances, not this form): the bent model can miss a fifth of the cause, so the truth
limit of a bending is also this share of its size (seed 1595584777: 1.18x the noise, 0.20 of a 6x cantilever)."""
RAIL_SHARE = 0.15
"""A guide bent in a sine of 0.7-2.5 waves is followed by the straightness form's Legendre P2..P5 only approximately;
at the large sizes the part it cannot represent shows, so the truth limit of a rail is also this share of its size
(seed 549: 0.99x the noise at 7.8x, 0.13 of the size; the same at 7008116, before this session)."""
PLAY_TRUTH_LIMIT = 2.0
"""For a gear play the identified switch misplaces a few poses, and each costs the full play: the benchmark
measures 0.3-2.7x the noise at 1-4x (docs/RESULTS.md, section 3); the geometry alone leaves 3-8x here. The same
when a stiffening spring is named as a soft play with the spring among its look-alikes: the calibration poses
cannot tell them apart, and fresh poses at larger loads can (seed 1808188314: 1.83x the noise at 7.8x, the
spring on the play's load 1 % better held out)."""
Z_LIMIT = {"cable_force": 6.0, "rehoming_step": 3.0}
"""Guard on the RMS z of fresh poses' predictions against the truth when structure is left unexplained: the
de-noised held-out model error is in the prediction std (calib_core.uncertainty). The target is 2 and it is
NOT met on every draw (issue 9 open): over 24 draws of 3-8x the noise, base tilt and cable force reached
2.04-2.29 in 4, and a re-homing step 5.3-7.0 in 2 (fresh poses between the campaign's times fall on either side
of the step; since the step's place between two measured poses is in the std, 16 of 16 seeds gave 0.53-1.18). A
cable force reached 3.43 (seed 2086651407, also on the code before 8b8790f); the benchmark's per-draw range for it
is 1.1-5.6. This guard catches a collapse (the first release's std were 100x off); benchmarks/detection.py measures
the distribution (docs/RESULTS.md, 3.2)."""


def _size(seed: int, lo: float = SIZES[0], hi: float = SIZES[1]) -> float:
    return float(np.exp(np.random.default_rng((seed, 2)).uniform(np.log(lo), np.log(hi))))


PLAYS = ("hard_backlash", "soft_backlash")
MIN_SWITCHED = 0.1
"""A play shows only on poses whose load has the minority sign; on a joint whose load changes sign on a
handful of the 150 poses it cannot be told from as many outliers (benchmarks/detection.py counts those
draws). The tests draw plays where at least this share of the poses sits on each side."""


def _world(kind, size, seed, model=SPRAY):
    """A world hiding one cause of `kind`, its description and 150 measured poses."""
    for attempt in range(20):
        world = World(model, seed + attempt)
        info = hide(world, kind, size, np.random.default_rng((seed, attempt, 1)))
        if kind not in PLAYS:
            break
        j = model.joint_names.index(info["joints"][0])
        tau = world.robot.joint_loads(info["q"], None)[:, j]
        if min((tau > 0).mean(), (tau < 0).mean()) >= MIN_SWITCHED:
            break
    meas = world.measure(info["q"], payload_kg=info["payload_kg"], temperature=info["temperature"])
    return world, info, meas


def _named(findings, kind, joints) -> dict | None:
    """The finding that names `kind` on exactly these joints (its joints, or the joints it is named for: its
    significant ones, issue 31), or lists it among its look-alikes."""
    for f in findings:
        if f["kind"] == kind and (kind == "unexplained" or set(joints) in (set(f["joints"]),
                                                                        set(named_joints(f)[0]))):
            return f
        if any(a["kind"] == kind and set(a["joints"]) == set(joints) for a in f.get("indistinguishable_from", [])):
            return f
    return None


LOAD_DRIVEN = {"joint_compliance", "link_deflection", "backlash"}
ANGLE_DRIVEN = {"cyclic_joint_error", "joint_scale"}
"""Named causes that are a function of their joint's own angle."""


def _implicated(findings, kind, joints) -> dict | None:
    """A load-driven cause spread over several joints that include the hidden one (a short link's bending and
    the compliance of the joints around it look alike). The benchmark counts only exact names; a single test
    draw accepts this weaker answer so that CI does not fail on the few per cent of look-alike draws the
    benchmark reports."""
    if kind not in LOAD_DRIVEN:
        return None
    spread = next((f for f in findings if f["kind"] in LOAD_DRIVEN and set(joints) <= set(f["joints"])), None)
    return spread or _link_or_its_joint(findings, kind, joints)


def _link_or_its_joint(findings, kind, joints) -> dict | None:
    """A joint's compliance named as the bending of the link it turns (the link ending at the next joint), or that
    bending named as the joint's compliance: that link's root carries the same gravity moment, and with positions
    alone the two differ only by the tilt at the link's end (seed 910: a spring on J4 at 6.2x named as J5's link
    bending, also before this session; seed 1723020749: J5's link bending at 5.6x named as J4's spring)."""
    if len(joints) != 1 or joints[0] not in SPRAY.joint_names:
        return None
    j = SPRAY.joint_names.index(joints[0])
    if kind == "joint_compliance" and j + 1 < SPRAY.n_joints:
        other, other_kind = SPRAY.joint_names[j + 1], "link_deflection"
    elif kind == "link_deflection" and j > 0:
        other, other_kind = SPRAY.joint_names[j - 1], "joint_compliance"
    else:
        return None
    return next((f for f in findings if f["kind"] == other_kind and f["joints"] == [other]), None)


def _truth_error(world, robot, info=None, n=100) -> float:
    """Error of a calibrated robot against the world's noise-free truth on n fresh poses, over the noise RMS
    per pose: the RMS over the poses, leaving out up to 5 % of them (a play's switch point cannot be known
    to better than the geometry on poses whose load is within a hair of zero)."""
    camp = world.campaign(n=n, payload_kg=None if info is None else info["payload_kg"],
                          temperature=bool(info and info["temperature"]))
    d = np.linalg.norm(robot.predict(camp.meas.joints, camp.meas) - camp.truth.points, axis=1)
    d = np.sort(d)[: int(np.ceil(0.95 * n))]
    return float(np.sqrt(np.mean(d**2))) / world.noise_rms_mm(camp.meas.joints)


def _said(d) -> list:
    return [(f["kind"], f["joints"], round(f["gain_pct"], 1),
             [(a["kind"], a["joints"]) for a in f.get("indistinguishable_from", [])]) for f in d.findings]


@pytest.mark.slow
@pytest.mark.parametrize("kind", NAMED)
def test_hidden_cause_is_found_blind(kind, seed):
    size = _size(seed)
    world, info, meas = _world(kind, size, seed)
    d = diagnose(SPRAY, meas)
    where = (f"{kind} on {info['joints']} ({info['parameters']}) at {size:.1f}x noise, seed {seed}: expected "
             f"{info['expected']}, said {_said(d)}")
    f = _named(d.findings, info["expected"], info["joints"]) or _implicated(d.findings, info["expected"], info["joints"])
    assert f is not None, where
    assert f["gain_pct"] > 0, where
    # the world's causes have physical sizes, and so have the forms fitted to them; not always the bearings' lateral
    # form on identified masses, which can trade one joint's tilt against another's (J5 14 deg, seed 274816721)
    # (issue 31: a fit outside its bound is presented as a correction, never under a physical kind)
    if kind != "elastic_bearings":
        assert all(g.get("physical", True) or g["kind"] == "correction" for g in d.findings), where
    # with the cause in the model, fresh poses are predicted closer to the truth than the tracker measures
    ratio = _truth_error(world, d.calibration, info)
    limit = (PLAY_TRUTH_LIMIT if kind in PLAYS or f["kind"] == "backlash" else BEARINGS_TRUTH_LIMIT
             if kind == "elastic_bearings" else TRUTH_LIMIT)
    if kind in ("cantilever", "telescopic_bending"):
        limit = max(limit, BENDING_SHARE * size)
    if kind == "rail_straightness":
        limit = max(limit, RAIL_SHARE * size)
    assert ratio < limit, (ratio, where)


@pytest.mark.slow
@pytest.mark.parametrize("kind", OFF_VOCABULARY)
def test_cause_without_a_name_is_never_silent(kind, seed):
    # CI seed 1449148170 (re-homing of J5): the step was placed 7 poses late, those poses flagged as outliers, z 10.8
    size = _size(seed)
    world, info, meas = _world(kind, size, seed)
    d = diagnose(SPRAY, meas)
    where = f"{kind} on {info['joints']} at {size:.1f}x noise, seed {seed}: {d.explanation}"
    assert d.findings, where
    # what the model leaves is carried in the prediction std: fresh poses' errors against the truth are covered
    # fresh poses in the same session (times over the campaign's span: a re-homing is in the same state)
    q = world.sample_joints(100, np.random.default_rng((seed, 3)))
    t = np.linspace(meas.timestamp[0], meas.timestamp[-1], 100)
    cols = dataclasses.replace(world.columns(q, info["payload_kg"], info["temperature"]), timestamp=t,
                               temperature=world.temperature_at(t) if info["temperature"] else None)
    z = z_scores(d.calibration, q, world.true_points(q, cols), cols)
    assert np.sqrt(np.mean(z**2)) < Z_LIMIT[kind], (float(np.sqrt(np.mean(z**2))), where)


@pytest.mark.slow
def test_a_cable_pulled_by_one_joint_is_traced_to_it(seed):
    """The world's cable pulls on one joint with a tension that grows with another joint's travel beyond its slack:
    off the vocabulary, but the unexplained finding says which joint drives it (the other joints' offsets as
    harmonics of it), or a named form of the driver's angle stands in for it, and the model takes most of it off on
    fresh poses. In development draws at 2-8x the noise: the driver among what the residual follows in 18 of 18 spray7
    draws, fresh-pose error 0.06-0.38x the geometric fit's. Before a form of the driver's angle counted, seeds 500-529
    and 600-623 missed once, and CI drew the seed above."""
    size = _size(seed, 2.0, 8.0)
    world, info, meas = _world("cable_force", size, seed)
    driven, driver = info["joints"]
    d = diagnose(SPRAY, meas)
    where = f"cable on {driven} pulled by {driver} at {size:.1f}x noise, seed {seed}: {d.explanation}"
    follows = [x for f in d.findings if f["kind"] == "unexplained" for x in f.get("follows", [])]
    # or a named form that is a function of the driver's angle takes it to the floor (seed 155959065: two harmonics of
    # J3 and J4's bending, 1.18x the floor, no `unexplained` left)
    angle_of = [f for f in d.findings if f["kind"] in ANGLE_DRIVEN and f["joints"] == [driver]]
    traced = any(x["joints"] == [driver] and "other joints" in x["what"] for x in follows) or angle_of
    assert traced, (follows, where)
    assert _truth_error(world, d.calibration.robot, info) < 0.5 * _truth_error(world, d.geometric.robot, info), where


def _rehomed(seed: int, joint: int | None, size_x_noise: tuple, at: tuple):
    """A drawn robot (arm6 on odd seeds, else spray7) with a joint (drawn unless given) re-homed at a drawn share
    `at` of the session by a drawn size (x the noise RMS of its unabsorbable part), measured at 150 poses:
    (model, world, joint, size, the cause, the measurements with timestamps)."""
    rng = np.random.default_rng(seed)
    model = parse_model(arm6()) if seed % 2 else SPRAY
    world = World(model, rng=rng)
    q = world.sample_joints(150, rng)
    j = int(rng.integers(1, model.n_joints)) if joint is None else joint
    size = float(np.exp(rng.uniform(*np.log(size_x_noise))))
    cols = world.columns(q, None, False)
    step, _ = size_cause(world, ReHoming.within(j, 1e-3, float(rng.uniform(*at)), cols.timestamp),
                         size * world.noise_rms_mm(q), q, cols, world.absorbable_basis(q))
    world.hide(step)
    return model, world, j, size, step, world.campaign(q=q).meas


def _first_after(step: ReHoming, meas) -> int:
    """The first pose (in time order) measured after the re-homing."""
    return int(np.searchsorted(meas.timestamp, step.at_time))


@pytest.mark.slow
def test_a_late_block_off_in_row_order_is_structure_not_outliers(seed):
    """A joint re-homed for the last 8-18 % of a session with no timestamps (the Motoman's case): a robust fit flags
    that block, but bad readings are not consecutive. `auto` keeps them at full weight and the answer says the
    residual follows a step of that joint in row order; under the Huber loss they were down-weighted and left out of
    every held-out test, and the answer could be `[]` (arm6, 16.8x the noise, J4: "follows nothing")."""
    model, world, j, size, step, meas = _rehomed(seed, None, (10.0, 30.0), (0.82, 0.92))
    where = f"{model.joint_names[j]} re-homed at pose {_first_after(step, meas)} by {size:.1f}x noise, seed {seed}"
    meas = dataclasses.replace(meas, timestamp=None)
    d = diagnose(model, meas)
    assert d.loss is None and any("run(s) of consecutive measurements" in n for n in d.notes), (d.notes, where)
    assert not d.calibration.metrics()["outliers"], where
    follows = [x for f in d.findings if f["kind"] == "unexplained" for x in f.get("follows", [])]
    # the step is the re-homed joint's, not a rigid shift of the late poses (which hardly follows a joint offset:
    # seed 493459735 followed nothing)
    assert any(x["what"].startswith("row order") and x["joints"] == [model.joint_names[j]] for x in follows), \
        (follows, where)


@pytest.mark.slow
def test_a_step_of_the_last_joint_is_told_from_a_remounted_target(seed):
    """In row order the last joint re-homed turns the target along a chord that the target's offset on the flange
    fits exactly with two parameters more: the joint's zero is named unless they pay (before, 3 of 100 re-homings
    were named a shift of the target or the whole robot: the joint's tangent misses the chord at 20x the noise);
    a target re-mounted in a drawn direction is the target's step, not the joint's."""
    model = parse_model(arm6()) if seed % 2 else SPRAY
    last = model.joint_names[-1]
    if np.random.default_rng((seed, 7)).random() < 0.5:
        model, world, _, size, step, meas = _rehomed(seed, model.n_joints - 1, (10.0, 30.0), (0.5, 0.92))
        expected, stepped, where = [last], f"{last}'s zero", f"{last} re-homed at pose {_first_after(step, meas)}"
    else:
        rng = np.random.default_rng(seed)
        world = World(model, rng=rng)
        q = world.sample_joints(150, rng)
        size = float(np.exp(rng.uniform(np.log(10.0), np.log(30.0))))
        info = hide(world, "target_remount", size, rng, q=q)
        meas = world.campaign(q=q).meas
        expected, stepped, where = [], "the target", f"target re-mounted at pose {info['notes']['at_pose']}"
    meas = dataclasses.replace(meas, timestamp=None)
    d = diagnose(model, meas)
    follows = [x for f in d.findings if f["kind"] == "unexplained" for x in f.get("follows", [])]
    steps = [x for x in follows if x["what"].startswith("row order")]
    assert len(steps) == 1 and steps[0]["joints"] == expected and f"a step of {stepped}" in steps[0]["what"], \
        (follows, f"{where} by {size:.1f}x noise, seed {seed}")


@pytest.mark.slow
def test_a_step_in_the_sequence_column_is_a_model_extension(seed):
    """No timestamps but a `sequence` column (the order the poses were measured in, the Motoman's pose_id), the rows
    shuffled: a joint re-homed mid-session is a finding, placed by the sequence (not the rows), and the model
    predicts fresh poses in the robot's current state (after the step) far better than the geometry alone. Without
    the column a step is only what the residual follows (row order is a guess)."""
    model, world, j, size, step, meas = _rehomed(seed, None, (5.0, 20.0), (0.4, 0.8))
    order = np.random.default_rng((seed, 6)).permutation(meas.n_poses)
    shuffled = dataclasses.replace(meas.subset(order), timestamp=None, sequence=7.0 + 3.0 * order)
    d = diagnose(model, shuffled)
    where = f"{model.joint_names[j]} re-homed at pose {_first_after(step, meas)} by {size:.1f}x noise, seed {seed}: " \
            f"{_said(d)}"
    steps = [f for f in d.findings if str(f.get("form", "")).startswith("step[")]
    assert [f["joints"] for f in steps] == [[model.joint_names[j]]], where
    first_after = _first_after(step, meas)
    found = re.search(r"in time order between \S+ and \S+ \(sequence ([-\d.]+)\)", steps[0]["evidence"])
    assert found, where
    found_after = int(round((float(found.group(1)) - 7.0) / 3.0 + 0.5))  # the first pose it puts after the step
    # at the step, or off only by poses the step hardly moves (seed 95767128: the first pose after it moved 1.65x the
    # noise, and the step was placed after that pose)
    missed = range(min(found_after, first_after), max(found_after, first_after))
    assert all(_step_mm(world, meas, k) < 3.0 * world.noise_rms_mm(meas.joints) for k in missed), (found_after, where)
    fresh = world.sample_joints(100, np.random.default_rng((seed, 5)))
    now = dataclasses.replace(world.columns(fresh, None, False), timestamp=np.full(100, meas.timestamp[-1]))
    truth = world.true_points(fresh, now)
    err = {k: float(np.sqrt(np.mean(np.sum((c.predict(fresh, now) - truth) ** 2, axis=1))))
           for k, c in (("auto", d.calibration), ("geometric", d.geometric))}
    assert err["auto"] < 0.5 * err["geometric"], (err, where)


def _step_mm(world, meas, k: int) -> float:
    """How far the world's step in time order moves the point of pose k (mm): that pose before and after it."""
    t = meas.timestamp
    q = meas.joints[[0, k, k, -1]]
    cols = dataclasses.replace(world.columns(q, None, False), timestamp=np.array([t[0], t[0], t[-1], t[-1]]))
    p = world.true_points(q, cols)
    return float(np.linalg.norm(p[2] - p[1]))


def _burst(seed, first: int, size_mm: tuple[float, float]):
    """4-8 consecutive readings off by size_mm in a drawn direction, starting at a drawn row >= first and ending
    >= first rows before the session's end, diagnosed with `auto`: (the diagnosis, the bad point ids, where)."""
    rng = np.random.default_rng(seed)
    model = parse_model(arm6()) if seed % 2 else SPRAY
    meas = null_world(model, seed).campaign(n=120).meas
    m = int(rng.integers(4, 9))
    k = int(rng.integers(first, meas.n_poses - first - m))
    way = rng.normal(size=(m, 3))
    points = meas.points.copy()
    points[k:k + m] += way / np.linalg.norm(way, axis=1, keepdims=True) * rng.uniform(*size_mm, (m, 1))
    d = diagnose(model, dataclasses.replace(meas, points=points))
    return d, set(meas.point_ids[k:k + m]), (seed, m, k, d.notes)


def test_a_burst_of_absurd_readings_is_still_outliers(seed):
    """4-8 consecutive readings of something else (the beam caught elsewhere: 200-2000 mm off) also come in one
    run, but no robot's model is that far off: `auto` still down-weights them and names them."""
    d, bad, where = _burst(seed, 0, (200.0, 2000.0))
    assert d.loss == "huber" and bad <= set(d.calibration.metrics()["outliers"]), where


def test_a_burst_of_bad_readings_mid_session_is_still_outliers(seed):
    """4-8 consecutive readings 10-40 mm off in the middle of the session (an SMR knocked and re-seated): a run, and
    no larger than a robot's model error, but it ends again, where a warm-up starts a session and a re-homing lasts
    to its end. Kept at full weight, 6 readings 20 mm off left a clean spray7 17x the noise off on fresh poses."""
    d, bad, where = _burst(seed, 20, (10.0, 40.0))
    assert d.loss == "huber" and bad <= set(d.calibration.metrics()["outliers"]), where


@pytest.mark.slow
def test_a_sixth_of_the_readings_of_something_else_change_nothing(seed):
    """15-30 of 150 readings thrown 5-1000 mm off at random rows on a robot with no cause (an attacker, or a tracker
    that locked onto something else): they are named as outliers, the geometry is still calibrated (registration
    alone was chosen when the comparison counted them: 20-25 mm off on the other poses, and causes were found in
    that error) and nothing is found. The fit's own figures leave them out like the held-out ones."""
    rng = np.random.default_rng(seed)
    model = parse_model(arm6()) if seed % 2 else SPRAY
    meas = null_world(model, seed).campaign(n=150).meas
    bad = rng.choice(150, int(rng.integers(15, 31)), replace=False)
    way = rng.normal(size=(len(bad), 3))
    points = meas.points.copy()
    points[bad] += way / np.linalg.norm(way, axis=1, keepdims=True) * rng.uniform(5.0, 1000.0, (len(bad), 1))
    d = diagnose(model, dataclasses.replace(meas, points=points))
    where = (seed, len(bad), d.explanation)
    assert {meas.point_ids[i] for i in bad} <= set(d.calibration.metrics()["outliers"]), where
    assert d.selection["chosen"] != "registration" and not d.findings, where
    assert d.geometric.metrics()["holdout_rms_mm"] < 3 * d.noise_floor_mm, where
    m = d.calibration.metrics()  # the in-sample figures are the robot's too, the bad readings' beside them
    assert m["rms_mm"] < 3 * d.noise_floor_mm and m["max_mm"] < 5.0 <= m["max_with_outliers_mm"], (m, where)


def test_the_chance_of_so_few_runs_is_exact(seed):
    """The runs probability behind `auto`'s choice: bad readings placed at random fall into at most k runs of
    consecutive poses as often as the formula says: within 5 binomial std of 100000 random placements (0.008 at
    p = 0.5; a fixed 0.01 with 20000 placements was 2.8 std there, and a CI run drew seed 125862222 beyond it), or
    10 placements where p is so small that a count is Poisson (5 where 0.63 were expected: seed 10047)."""
    rng = np.random.default_rng(seed)
    N = int(rng.integers(30, 80))
    n = int(rng.integers(3, 10))
    draws = 100_000
    at = np.sort(np.argsort(rng.random((draws, N)), axis=1)[:, :n], axis=1)
    k = 1 + (np.diff(at, axis=1) > 1).sum(1)
    for kk in np.unique(k)[:4]:
        p = runs_probability(kk, n, N)
        assert abs(np.mean(k <= kk) - p) <= max(5 * np.sqrt(p * (1 - p) / draws), 10 / draws), (kk, n, N, seed, p)
    assert runs_probability(n, n, N) == pytest.approx(1.0)


def _held_out(distances_mm, outliers=()):
    """What holdout_gain reads of a calibration: its held-out distances, the poses it named as outliers and the
    independent unit of each row (None: one target, every row its own)."""
    d = np.asarray(distances_mm, float)
    keep = np.ones(len(d), bool)
    keep[np.asarray(outliers, int)] = False
    return SimpleNamespace(holdout_residual_mm=d, inliers=lambda: keep, pose_index=None)


def test_a_cause_that_brings_poses_back_from_the_outliers_gains_on_them(seed):
    """A geometric model that misses a cause concentrated on part of the workspace can flag a sixth of the poses as
    outliers under the Huber loss; the cause that explains them is confirmed on them (seed 609 of
    test_two_causes_together_are_both_found found nothing while the gain was left out). Poses both fits flag (bad
    readings) stay out: a model that only changes its error there gains nothing."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(120, 300))
    noise = np.abs(rng.normal(0.08, 0.02, n))
    hit = rng.choice(n, int(rng.integers(n // 10, n // 5)), replace=False)
    before = noise * rng.uniform(0.95, 1.05, n)
    before[hit] += rng.uniform(0.5, 1.5, len(hit))  # flagged by the geometric fit
    assert holdout_gain(_held_out(before, hit), _held_out(noise))[0] < 1e-3, seed
    bad = before.copy()
    bad[hit] += rng.uniform(100.0, 1000.0, len(hit))  # readings of something else: both fits flag them
    other = bad.copy()
    other[hit] *= rng.uniform(0.5, 0.9, len(hit))
    assert holdout_gain(_held_out(bad, hit), _held_out(other, hit)) == (1.0, 0.0), seed


def test_the_held_out_test_sees_a_broad_gain_a_few_poses_and_nothing(seed):
    """The paired held-out test behind every accepted cause: a gain on most poses is significant even when one pose
    the old model missed by 15 mm dominates the variance (the iiwa's upright pose: the t-test alone said p ~ 0.15);
    a gain on 10 poses of 120-300 (a play's switch) is significant; two models of the same noise are not, at about the
    nominal rate (Bonferroni: 3.6-4.1 % at 5 % over 4000 draws)."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(120, 300))
    before = np.abs(rng.normal(0.5, 0.15, n))
    broad = before * rng.uniform(0.8, 0.9, n)
    before[0], broad[0] = rng.uniform(12.0, 20.0), 1.0
    assert holdout_gain(_held_out(before), _held_out(broad))[0] < 1e-3, seed
    few = np.abs(before + rng.normal(0.0, 0.05, n))
    hit = rng.choice(np.arange(1, n), 10, replace=False)
    before_few = before.copy()
    before_few[hit] += rng.uniform(1.5, 2.5, 10)
    assert holdout_gain(_held_out(before_few), _held_out(few))[0] < 1e-2, seed
    same = [holdout_gain(_held_out(np.abs(rng.normal(0, 0.1, n))), _held_out(np.abs(rng.normal(0, 0.1, n))))[0]
            for _ in range(400)]
    assert np.mean(np.array(same) < 0.05) <= 0.075, (seed, np.mean(np.array(same) < 0.05))


def test_a_smooth_field_explains_no_noise_beyond_chance(seed):
    """The joint-space field that tells a named cause from part of a broader structure has a few hundred
    effective parameters: of a residual that is only noise it fits some 75 %, all of it chance. Counted beyond
    chance (less trace(H^2) / dof of its hat matrix H), its share is about zero: over 40 seeds mean 4e-5, std
    0.023, extremes -0.057 and 0.045."""
    meas = null_world(SPRAY, seed).campaign(n=150).meas
    geo = identify(SPRAY, meas)
    share = field_share(geo, meas, geo.sigma_mm, geo.x)
    assert abs(share) < 0.1, (seed, share)


def test_a_cause_half_the_noise_is_not_taken_for_part_of_a_field(seed):
    """A gear error whose unabsorbable part is 0.5-1x the noise RMS explains 20-50 % of the residual; the field
    explains more of it by chance alone. Compared beyond chance, the cause stands (the first rule dropped it as
    'part of a broader structure' on most such draws: benchmarks/detection.py, docs/RESULTS.md 3.2)."""
    size = _size(seed, 0.5, 1.0)
    world = World(SPRAY, seed)
    info = hide(world, "gear_error", size, np.random.default_rng((seed, 1)))
    meas = world.measure(info["q"])
    j, h = SPRAY.joint_names.index(info["joints"][0]), info["parameters"]["harmonic"]
    pool = [e for e in candidates(SPRAY, meas)[0]
            if isinstance(e, CyclicJointError) and e.joints == (j,) and e.harmonic == h]
    geo = identify(SPRAY, meas)
    ranked, share = screen(geo, meas, geo.sigma_mm, pool, geo.x), field_share(geo, meas, geo.sigma_mm, geo.x)
    assert len(ranked) == 1, (seed, info["parameters"])
    assert ranked[0].beyond_chance >= NAMED_SHARE * share, (seed, size, ranked[0].beyond_chance, share)


def test_the_same_joints_at_another_target_are_no_repeat(seed):
    """The floor's repeatability comes from poses measured again: the same joints, target, setup and payload. The
    same joints at another target (a marker per payload run, or the virtual points of a 6-D row) measure another
    point 100 mm away; taken for repeats they made the iiwa's floor 86 mm."""
    meas = null_world(SPRAY, seed).campaign(n=60, repeats=10).meas
    sigma = meas.noise_sigma_mm()
    two = dataclasses.replace(meas, joints=np.r_[meas.joints, meas.joints], points=np.r_[meas.points, meas.points + 100.0],
                              point_ids=list(meas.point_ids) + [f"{i}-b" for i in meas.point_ids],
                              target=np.r_[np.zeros(meas.n_poses, int), np.ones(meas.n_poses, int)])
    one, both = noise_floor_mm(meas, sigma), noise_floor_mm(two, np.r_[sigma, sigma])
    assert one[2] == both[2] == "repeats", (seed, one, both)
    assert both[0] == pytest.approx(one[0], rel=1e-9), (seed, one, both)


def test_repeats_tighter_than_the_instrument_are_not_a_repeatability_of_0_um(seed):
    """Repeated poses that spread no more than the instrument's noise do not resolve the robot's repeatability: the
    note says so instead of "robot repeatability 0 um" (the iiwa's report)."""
    meas = null_world(SPRAY, seed).campaign(n=40, repeats=10).meas
    again = np.flatnonzero(np.arange(meas.n_poses) >= 40)
    first = [int(np.flatnonzero((meas.joints[:40] == meas.joints[k]).all(1))[0]) for k in again]
    points = meas.points.copy()
    points[again] = points[first] + np.random.default_rng(seed).normal(size=(len(again), 3)) * 1e-6
    tight = dataclasses.replace(meas, points=points)
    floor, note, basis = noise_floor_mm(tight, tight.noise_sigma_mm())
    assert basis == "repeats" and "below what the instrument resolves" in note and " 0 um" not in note, note
    assert floor == pytest.approx(np.sqrt(3 * np.mean(tight.noise_sigma_mm() ** 2)), rel=1e-9), note


def test_a_play_read_off_the_noise_gains_nothing_on_held_out_poses(seed):
    """Nothing hidden: a sharp play whose switch the classifier reads off the residual fits the noise of the poses
    it was read from. Each fold finds the switch again on its own training poses, so held-out poses do not see that
    fit and the held-out mean square does not drop on average over the joints. With the switch read off all poses
    it dropped 2-6 % (mean ratio 0.964-0.977 over 4 seeds; 1.017-1.034 now)."""
    meas = null_world(SPRAY, seed).campaign(n=150).meas
    fit = _Fitter(SPRAY, meas, None, 5, None, 1.0)
    geo = fit()
    plays = [p for p in _identified_backlash(geo, meas, geo.sigma_mm, geo.x, [1, 2, 3]) if not p.fitted_softness]
    assert plays, seed  # J2-J4's loads change sign on the random poses
    ratios = [holdout_ms(fit([p], geo.x)) / holdout_ms(geo) for p in plays]
    assert np.mean(ratios) > 0.99, (ratios, seed)


@pytest.mark.parametrize("kind", PLAYS)
def test_the_play_search_stops_where_its_switch_has_settled(kind, seed, monkeypatch):
    """A hidden play (drawn joint, size, seed): the search for its switch stops once a pass moves no pose's flank
    by more than PLAY_SETTLED (a refit would give back nearly the same fit). It refits the play fewer times than
    running every pass, finds the same forms, and they fit the poses about as well (passes past the settled point only
    creep, or flip a pose that sits at the switch)."""
    world, info, meas = _world(kind, _size(seed), seed)
    fit = _Fitter(SPRAY, meas, None, 5, None, 1.0)
    geo = fit()
    j = SPRAY.joint_names.index(info["joints"][0])
    calls = []
    refit = plays_module._with_play_refitted

    def counted(*a, **k):
        calls.append(1)
        return refit(*a, **k)

    def rss(play):
        return float(np.sum(fit((play,), geo.x, folds=0).solution.residual ** 2))

    monkeypatch.setattr(plays_module, "_with_play_refitted", counted)
    settled = _identified_backlash(geo, meas, geo.sigma_mm, geo.x, [j])
    n_settled = len(calls)
    monkeypatch.setattr(plays_module, "PLAY_SETTLED", -1.0)  # never settled: every pass
    calls.clear()
    every = _identified_backlash(geo, meas, geo.sigma_mm, geo.x, [j])
    where = (kind, info["joints"], seed, n_settled, len(calls))
    assert settled and [p.fitted_softness for p in settled] == [p.fitted_softness for p in every], where
    # a switch that still moves in the last pass never settles: then the same passes, the same plays (CI seed
    # 858058188, soft play on J4: 14 fits either way) up to what the fits make of the last bits, which vary with the
    # arrays' memory alignment (seed 116552429: one _switch call, the same inputs to the bit, two answers 1e-7 apart;
    # the soft form of that hard play, in a flat valley, then lands up to 0.05 apart in flank, call after call)
    ctx = Context.at(SPRAY, geo.x, meas, geo.R0)
    assert n_settled < len(calls) or all(plays_module._flank_moved(a, b, ctx) <= 0.1
                                         for a, b in zip(settled, every)), where
    for a, b in zip(settled, every):
        assert rss(a) <= 1.05 * rss(b), (rss(a), rss(b), where)  # benchmarks.bench_play_search: 0.996-1.025


@pytest.mark.slow
def test_no_cause_means_no_finding(seed):
    """Wrong masses in the model, a robot repeating 2.5x worse than usual and two bad readings: nothing to find,
    the bad readings that stand out of the noise are named, in the notes as in the metrics."""
    for k in range(2):
        world = null_world(SPRAY, seed + k, outliers=2)
        camp = world.campaign(n=150)
        d = diagnose(SPRAY, camp.meas)
        assert d.findings == [], (seed + k, _said(d), d.explanation)
        # nothing left: what the std adds is the noise of the held-out excess, a fraction of the floor
        assert d.calibration.unmodelled_mm < 0.3 * d.noise_floor_mm, (d.calibration.unmodelled_mm, d.noise_floor_mm)
        assert "No cause was found" in d.explanation
        # a bad reading is named when it stands out of the noise: those past twice the outlier bound (OUTLIER_U robust
        # sigmas per axis) must be; a 0.54 mm one at a 0.144 mm floor was 3.9 sigmas after the fit (seed 1903190564)
        size = np.linalg.norm(camp.meas.points - camp.truth.points - camp.truth.noise, axis=1)
        clear = 2 * OUTLIER_U * d.noise_floor_mm / np.sqrt(3)
        bad = {camp.meas.point_ids[i] for i in camp.truth.outliers if size[i] > clear}
        assert bad <= set(d.calibration.metrics()["outliers"]), (seed + k, bad, d.calibration.metrics()["outliers"])
        if d.calibration.metrics()["outliers"]:  # both readings can be within the noise: then none is named
            said = next(n for n in d.notes if "(Huber loss)" in n)  # the notes name the same outliers as the metrics
            named = set(said.split("(Huber loss): ")[1].split(";")[0].split(", "))
            assert named == set(d.calibration.metrics()["outliers"]), (seed + k, said,
                                                                       d.calibration.metrics()["outliers"])
        assert _truth_error(world, d.calibration) < TRUTH_LIMIT, seed + k


def test_a_search_out_of_time_says_so_and_claims_no_cause_untested(seed):
    """A job's time budget can end the search (thousands of poses): the answer then names only what held-out poses
    confirmed, says in the verdict, the prose and the JSON that it is not complete, and is never silent on the
    structure left. A cause drawn at 3-8x the noise, a deadline already past: nothing was tested, so nothing is
    named; without the deadline the same data give a complete answer with a named cause."""
    rng = np.random.default_rng((seed, 11))
    world = World(SPRAY, seed)
    info = hide(world, str(rng.choice(["joint_spring", "gear_error", "encoder_scale"])),
                float(np.exp(rng.uniform(np.log(3.0), np.log(8.0)))), rng)
    meas = world.measure(info["q"])
    cut = diagnose(SPRAY, meas, deadline=time.monotonic())
    answer = cut.to_dict()
    assert cut.untested and answer["search_complete"] is False, (seed, cut.untested)
    assert [f["kind"] for f in cut.findings] == ["unexplained"], (seed, _said(cut))
    assert cut.verdict().startswith("search stopped at its time budget: no cause(s) confirmed"), cut.verdict()
    assert "not a complete answer" in cut.explanation and "complete." not in cut.explanation, cut.explanation
    full = diagnose(SPRAY, meas)
    assert full.untested is None and full.to_dict()["search_complete"] is True
    assert any(f["kind"] != "unexplained" for f in full.findings), (seed, _said(full))


def _beside(findings, kind, joints) -> dict | None:
    """A load-driven finding on the joint or link next to a hidden load-driven cause: the spring of J4 and the
    bending of the short link after it look alike on 150 poses when the mass data are 15 % off (the benchmark
    counts only exact names: docs/RESULTS.md 3.2)."""
    if kind not in LOAD_DRIVEN:
        return None
    near = {k for i in map(SPRAY.joint_names.index, joints) for k in (i - 1, i, i + 1)}
    return next((f for f in findings if f["kind"] in LOAD_DRIVEN
                 and {SPRAY.joint_names.index(j) for j in f["joints"]} <= near), None)


@pytest.mark.slow
def test_two_causes_together_are_both_found(seed):
    """A load-driven cause and one of another family, both 5x the noise, are named (or a look-alike is, see
    _implicated and _beside), and the extended model predicts the truth. The world's mass data are 15 % off and
    its centres of mass 30 mm off the model's: a load-driven cause computed from the model's leaves a load-shaped
    rest, which small further findings may take up (over 100 draws: a harmonic or compliance of a neighbouring
    joint at 2-18 % held-out gain, a play, an `unexplained` rest following a joint). They are judged by the truth
    error, not by their names; no-effect worlds have no findings (test_no_cause_means_no_finding). Known misses, 2 in
260 draws: seeds 2302256 and 1300698 (the bending of link J2 or J3 and J3's encoder scale, named as a soft play
on J3 and an `unexplained` rest at 2x the floor: the play's switch is identified on all poses before the folds,
which flatters it on held-out poses)."""
    rng = np.random.default_rng((seed, 3))
    world = World(SPRAY, seed)
    kinds = [str(rng.choice(["joint_spring", "cantilever"])),
             str(rng.choice(["gear_error", "rail_straightness", "encoder_scale"]))]
    first = hide(world, kinds[0], 5.0, rng)
    second = hide(world, kinds[1], 5.0, rng, q=first["q"])
    hidden = {(h["expected"], tuple(sorted(h["joints"]))) for h in (first, second)}
    d = diagnose(SPRAY, world.measure(first["q"]))
    # a finding names its cause, or says which look-alike causes this pose set cannot tell apart from it
    found = [_named(d.findings, h["expected"], h["joints"]) or _implicated(d.findings, h["expected"], h["joints"])
             or _beside(d.findings, h["expected"], h["joints"]) for h in (first, second)]
    assert all(found), (seed, hidden, _said(d))
    limit = max(TRUTH_LIMIT, BENDING_SHARE * 5.0) if kinds[0] == "cantilever" else TRUTH_LIMIT
    ratio = _truth_error(world, d.calibration)
    assert ratio < limit, (seed, hidden, ratio, _said(d))


def test_any_serial_chain_works(seed):
    model = parse_model(arm6())
    world, info, meas = _world("joint_spring", 6.0, seed, model)
    d = diagnose(model, meas)
    # named, or implicated as the blind test accepts (a compliance on several joints among them: CI seed 885389337
    # spread A3's spring over A2..A5, also on c65e151; issue 34 asks the search itself to prefer the single joint)
    assert _named(d.findings, "joint_compliance", info["joints"]) or _implicated(
        d.findings, "joint_compliance", info["joints"]), (seed, info["joints"], _said(d))


def test_auto_answer_carries_the_contract_diagnosis_and_restores(seed):
    world, info, meas = _world("gear_error", 5.0, seed)
    out = calibrate(SPRAY, meas, "auto")
    d = out["diagnosis"]
    assert set(d) >= {"noise_floor_mm", "geometric", "findings", "explanation"}
    assert set(d["geometric"]) >= {"rms_mm", "holdout_rms_mm"}
    f = d["findings"][0]
    assert set(f) >= {"kind", "joints", "holdout_rms_before_mm", "holdout_rms_after_mm", "gain_pct", "evidence"}
    where = (seed, info["parameters"], _said(type("D", (), {"findings": d["findings"]})))
    # named, or its look-alike named with it listed (a first harmonic over a short range looks like a scale error:
    # seed 755764221 named joint_scale[J2] with cyclic_joint_error[J2] indistinguishable)
    assert _named(d["findings"][:1], "cyclic_joint_error", info["joints"]), where
    if f["kind"] == "cyclic_joint_error":
        assert f["harmonic"] == info["cause"].harmonic, where
    else:
        assert info["cause"].harmonic == 1 and f["kind"] == "joint_scale", where
    assert out["model"] == ["geometric", f["kind"]], where
    robot = CalibratedRobot.from_state(SPRAY, out["robot_state"])
    assert _truth_error(world, robot, info, n=50) < TRUTH_LIMIT, where


def test_without_masses_the_service_says_so(seed):
    doc = spray7()
    for j in doc["joints"]:
        j.pop("mass"), j.pop("com")
    model = parse_model(doc)
    d = diagnose(model, World(model, seed).measure(n=100))
    assert any("no masses" in n for n in d.notes)


def test_a_cause_of_no_physical_size_is_said_to_be_a_correction(seed):
    """A play fitted on a drawn joint of a world with a hidden gear play (2-8x the noise), then its value set to a
    drawn multiple of the plausible turn: up to the limit the finding is physical, beyond it the answer says the
    size is not physical and names the joint (the iiwa's wrist "play" turned A5 by 75 deg)."""
    from calib_core.effects import Backlash

    rng = np.random.default_rng(seed)
    world, info, meas = _world("hard_backlash", _size(seed, 2.0, 8.0), seed)
    j = SPRAY.joint_names.index(info["joints"][0])
    cal = identify(SPRAY, meas, effects=(Backlash((j,)),), folds=0)
    name = f"{SPRAY.joint_names[j]}.backlash"
    for factor, physical in ((rng.uniform(0.05, 0.9), True), (rng.uniform(1.1, 20.0), False)):
        # the play is b: the joint moves by b/2 either side; prismatic joints are judged in mm
        limit = PLAUSIBLE_TRAVEL_MM if SPRAY.prismatic[j] else PLAUSIBLE_TURN_RAD
        cal.solution.x[-1] = 2.0 * factor * limit
        finding = {"kind": "backlash", "joints": [SPRAY.joint_names[j]], "parameters": [{"name": name}],
                   "evidence": "a play"}
        _judge_sizes(cal, [finding], meas)
        where = f"play on {SPRAY.joint_names[j]} at {factor:.2f}x the plausible size, seed {seed}: {finding}"
        assert finding.get("physical", True) is physical, where
        assert ("not physical" in finding["evidence"]) is (not physical), where
        assert physical or SPRAY.joint_names[j] in finding["evidence"], where


@pytest.mark.slow
@pytest.mark.parametrize("every", [True, False])
def test_a_compliance_spread_over_the_joints_replaces_the_one_found_first(every, seed):
    """The world's bearings tilt under their bending moments, and a spring winds every loaded joint (or one drawn
    joint), masses 15 % off. The search found the lateral form and that one joint's compliance, and identified the
    mass data under them. `_Search.spread` tries the compliance of every joint in its place, with the mass data
    identified again: taken where every joint gives (the error against the truth on fresh poses falls), and where
    one joint does, refused or harmless (the paired test at 5 % passes by chance: 1 of 11 development seeds, +8 %)."""
    rng = np.random.default_rng((seed, 21))
    world = World(SPRAY, int(rng.integers(2**31)))
    q = world.sample_joints(150, rng)
    cols = world.columns(q, [0.0, 10.0, 20.0])
    named, _ = candidates(SPRAY, cols)
    spread = next(e for e in named if type(e) is JointCompliance and len(e.joints) > 1)
    lateral = next(e for e in named if isinstance(e, LateralJointCompliance))
    noise = world.noise_rms_mm(q)
    bent = [SPRAY.joint_names[j] for j in lateral.joints]
    world.hide(size_cause(world, ElasticBearings(tuple(bent), tuple(rng.uniform(0.5, 2.0, len(bent)) * 1e-6)),
                          3 * noise, q, cols)[0])
    j = int(rng.choice(spread.joints))
    for k in spread.joints if every else (j,):
        spring = JointSpring(SPRAY.joint_names[k], compliance=1e-6)
        world.hide(size_cause(world, spring, rng.uniform(2, 4) * noise, q, cols)[0])
    meas = world.campaign(q, payload_kg=[0.0, 10.0, 20.0]).meas
    fit = _Fitter(SPRAY, meas, None, 5, None, 1.0)
    chosen = [lateral, JointCompliance((j,))]
    findings = [{"kind": e.kind, "joints": [], "form": e.label(SPRAY)} for e in chosen]
    notes: list[str] = []
    current = _identify_masses(fit(chosen), chosen, findings, SPRAY, meas, fit, notes)
    floor, _, _ = noise_floor_mm(meas, meas.noise_sigma_mm())
    search = _Search(SPRAY, meas, current.sigma_mm, ALPHA, fit, floor, named, {}, current, current.x,
                     chosen=list(chosen), findings=findings)
    fresh = world.sample_joints(100, np.random.default_rng((seed, 22)))
    fresh_cols = world.columns(fresh, [0.0, 10.0, 20.0])
    truth = world.true_points(fresh, fresh_cols)
    err = lambda cal: np.sqrt(np.mean(np.sum((cal.predict(fresh, fresh_cols) - truth) ** 2, 1)))  # noqa: E731
    took = search.spread(notes, lambda *a: None)
    where = f"seed {seed}, {'every joint' if every else SPRAY.joint_names[j]}: {search.rejected[-1:]}"
    if every:
        assert took and search.chosen[-1].joints == spread.joints, where
        assert not any(type(e) is JointCompliance and e.joints == (j,) for e in search.chosen), where
        assert err(search.current) < 0.7 * err(current), (err(current), err(search.current), where)
    else:  # harmless: within a quarter more, or by less than a fifth of the noise (seed 36604127: 0.029 -> 0.037 mm,
        # +28 %, a spread taken on 0.096 -> 0.093 mm held out; about 1 seed in 25 at +25 %)
        worse = err(search.current) - err(current)
        assert worse < max(0.25 * err(current), 0.2 * noise), (err(current), err(search.current), noise, where)
    assert len(search.findings) == len(search.chosen)


def test_an_svd_that_does_not_converge_falls_back_to_gesvd(monkeypatch, seed):
    """gesdd (numpy) failed on finite columns twice in CI inside load_mix_for; gesvd (scipy) gives the same
    decomposition there instead of a crashed diagnosis."""
    from calib_core.effects import gravity

    A = np.random.default_rng(seed).normal(size=(40, 5))
    want = np.linalg.svd(A, full_matrices=False)

    def fails(*args, **kwargs):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(np.linalg, "svd", fails)
    got = gravity._svd(A, full_matrices=False)
    assert np.allclose(got[1], want[1]) and np.allclose(np.abs(got[2]), np.abs(want[2]))
    assert np.allclose(gravity._svd(A, compute_uv=False), want[1])


def test_a_sharp_plays_softness_is_one_answer_whatever_the_memory_layout(seed):
    """A play that is sharp on the data (offsets b/2 sign(load) + noise, drawn features and switch): the soft fit's
    argument stays within a few SHARPEST, and the answer is the same with the features in C or Fortran order.
    Without the ridge on it the fit ran on along a flat valley to its evaluation cap (RMS 200-1200), and where it
    stopped followed rounding: arm6 play 2x #0 predicted new poses at 0.51, 0.62 or 0.88x the noise from run to run."""
    from calib_core.diagnosis.plays import SHARPEST, _softness

    rng = np.random.default_rng((seed, 21))
    N, k = int(rng.integers(100, 200)), int(rng.integers(4, 12))
    Z = np.linalg.qr(rng.normal(size=(N, k)))[0] * np.sqrt(N)  # unit-RMS orthogonal features, as _LoadFeatures
    truth = rng.normal(size=k)
    b = rng.uniform(1e-4, 1e-3)
    e = 0.5 * b * np.sign(Z @ truth) + rng.normal(0, 0.05 * b, N)
    w = rng.uniform(0.5, 2.0, N)
    start = truth / np.linalg.norm(truth) + rng.normal(0, 0.2, k)
    c = _softness(np.ascontiguousarray(Z), e, w, start)
    f = _softness(np.asfortranarray(Z), e, w, start)
    assert np.linalg.norm(c) < 5 * SHARPEST, (seed, np.linalg.norm(c))
    # one answer to rounding (1e-8-1e-7 of its size on 2 of 600 draws), where the unridged fits differed by O(1)
    assert np.abs(c - f).max() <= 1e-5 * np.linalg.norm(c), (seed, c, f)
    assert np.mean(np.sign(Z @ c) == np.sign(Z @ truth)) > 0.9, seed  # the switch is the play's


def test_a_plays_switch_is_the_weighted_logistic_optimum_then_the_tanh_fit(seed):
    """The switch search's convex start (a weighted logistic regression of sign(offset) on the load features, Newton)
    is scipy's optimum of the same objective (BFGS, a solver we did not write), and the switch it leads to separates
    the poses as the drawn play does: offsets b/2 sign(load) + noise of 5-25 % of b, drawn features and switch."""
    from scipy import optimize, special

    from calib_core.diagnosis.plays import LOGISTIC_RIDGE, _logistic, _switch

    rng = np.random.default_rng((seed, 22))
    N, k = int(rng.integers(100, 300)), int(rng.integers(3, 15))
    Z = np.linalg.qr(rng.normal(size=(N, k)))[0] * np.sqrt(N)
    truth = rng.normal(size=k)
    b = rng.uniform(1e-4, 1e-3)
    e = 0.5 * b * np.sign(Z @ truth) + rng.normal(0, rng.uniform(0.05, 0.25) * b, N)
    w = rng.uniform(0.5, 2.0, N)
    c = w * np.abs(e) / np.mean(w * np.abs(e))
    y = np.sign(e)

    def loss(beta):
        return float(np.sum(c * np.logaddexp(0.0, -y * (Z @ beta)))) + 0.5 * LOGISTIC_RIDGE * N * beta @ beta

    def grad(beta):
        return -Z.T @ (c * y * special.expit(-y * (Z @ beta))) + LOGISTIC_RIDGE * N * beta

    ref = optimize.minimize(loss, np.zeros(k), jac=grad, method="BFGS", options={"gtol": 1e-10}).x
    got = _logistic(Z, y, w * np.abs(e), rng.normal(size=k))
    cos = float(got @ ref / np.linalg.norm(got) / np.linalg.norm(ref))
    assert cos > 1 - 1e-6, (seed, cos)
    beta = _switch(Z, e, w, rng.normal(size=k))
    assert np.mean(np.sign(Z @ beta) == np.sign(Z @ truth)) > 0.9, seed


def test_a_switch_fit_takes_the_targets_of_one_pose_as_one(seed, monkeypatch):
    """Two targets per pose (equal load features, their own offsets and weights, a fifth weightless: a joint that does
    not move one of them): the tied rows (_tied, half of them) carry every row's sum of squares and gradient, and the
    switch and the softness fitted on them are those fitted on every row, to rounding (MINPACK follows the same steps:
    at most 5e-7 of the switch's size, 2e-8 of the softness's, over 300-400 draws; the softness is compared from one
    switch: its flat valley turns starts 5e-7 apart into answers 1e-4 apart)."""
    from calib_core.diagnosis import plays

    rng = np.random.default_rng((seed, 23))
    P, k = int(rng.integers(60, 150)), int(rng.integers(3, 12))
    Z = np.repeat(np.linalg.qr(rng.normal(size=(P, k)))[0] * np.sqrt(P), 2, axis=0)
    truth = rng.normal(size=k)
    b = rng.uniform(1e-4, 1e-3)
    e = 0.5 * b * np.sign(Z @ truth) + rng.normal(0, rng.uniform(0.05, 0.25) * b, 2 * P)
    w = rng.uniform(0.5, 2.0, 2 * P) * (rng.random(2 * P) > 0.2)
    Zt, et, swt, scatter = plays._tied(Z, e, np.sqrt(w))
    assert len(Zt) <= P, seed
    for beta in rng.normal(size=(3, k)):
        g, gt = np.tanh(Z @ beta), np.tanh(Zt @ beta)
        assert np.isclose(np.sum(w * (e - g) ** 2), np.sum((swt * (et - gt)) ** 2) + scatter**2, rtol=1e-12), seed
        d, dt = (1 - g**2)[:, None] * Z, (1 - gt**2)[:, None] * Zt
        assert np.allclose(d.T @ (w * (e - g)), dt.T @ (swt**2 * (et - gt)), rtol=1e-10, atol=1e-15), seed
    start = rng.normal(size=k)
    tied = plays._switch(Z, e, w, start)
    tied = tied, plays._softness(Z, e, w, tied)
    monkeypatch.setattr(plays, "_tied", lambda Z, e, sw: (Z, e, sw, 0.0))  # every row as it comes
    every = plays._switch(Z, e, w, start), plays._softness(Z, e, w, tied[0])  # the softness from the same switch
    for a, c in zip(tied, every):
        assert np.abs(a - c).max() <= 1e-5 * np.linalg.norm(c), (seed, a, c)


def test_a_look_alike_is_named_once_per_cause():
    """A bent link and its tilted form are one cause in the answer (the prose said "link_deflection J6,
    link_deflection J6"): the form that did best on held-out poses stands for it; other causes keep their order."""
    from calib_core.diagnosis.lookalikes import _merge_alike
    rng = np.random.default_rng()
    h = rng.uniform(0.05, 0.2, 4)
    plain = {"kind": "link_deflection", "joints": ["J6"], "form": "link_deflection[J6]", "holdout_rms_after_mm": h[0]}
    tilted = {**plain, "form": "link_deflection[J6] tilted", "holdout_rms_after_mm": h[1]}
    spring = {"kind": "joint_compliance", "joints": ["J4"], "form": "joint_compliance[J4]", "holdout_rms_after_mm": h[2]}
    h1 = {"kind": "cyclic_joint_error", "joints": ["J4"], "harmonic": 1, "holdout_rms_after_mm": h[3]}
    h2 = {**h1, "harmonic": 2}
    out = _merge_alike([plain, spring], [tilted, h1, h2])
    assert out == [plain if h[0] <= h[1] else tilted, spring, h1, h2]
