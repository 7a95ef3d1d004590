"""Elastic structure with mass data identified from the data: the lateral (bearing) compliance of every joint and
the Gauss-Newton steps of the bodies' masses under the compliances found (calib_core.effects.gravity)."""
import dataclasses

import numpy as np

from calib_core import kinematics as K
from calib_core.diagnosis.fitter import _Fitter
from calib_core.diagnosis.lookalikes import STIFFENING, _refinements
from calib_core.diagnosis.masses import _identify_masses, _with_mass_doubt
from calib_core.diagnosis.plays import _LoadFeatures
from calib_core.effects import (Backlash, Context, JointCompliance, LateralJointCompliance, LinkDeflection,
                                RootTurnLinkDeflection, candidates, effect_from_state, effect_state)
from calib_core.effects.cartesian_effects import _beam
from calib_core.effects.gravity import (TILT_PRIOR_RAD, body_parameters, gravity_regressor, lateral_axes, mass_step,
                                       payload_load)
from calib_core.effects.joint_effects import PLAY_PRIOR_MM, PLAY_PRIOR_RAD
from calib_core.identify import CalibratedRobot, prealign
from calib_core.model import parse_model
from calib_core.robots import spray7
from calib_core.statics import distal_loads, gravity_moments, gravity_world, joint_loads
from calib_core.twin import Twin
from calib_core.uncertainty import prediction_std_mm

from .test_tree import torso_two_arms

TREE = parse_model(torso_two_arms(mass=True))
MOVING = tuple(j for j in range(TREE.n_joints) if TREE.moving[j])


def _poses(seed, n):
    """n poses of the tree (both targets, a payload on some), their chain on the nominal geometry."""
    meas = Twin(TREE, seed=seed, repeatability_mm=0.0, tracker_noise=False).measure(n=n)
    rng = np.random.default_rng((seed, 5))
    meas = dataclasses.replace(meas, payload=rng.choice([0.0, 5.0], n))
    x, R0 = prealign(TREE, meas)
    return meas, x, R0, K.Chain(TREE, x, meas.joints, R0, meas.labels)


def test_loads_from_mass_data_are_the_statics_on_a_tree(seed):
    meas, _, _, ch = _poses(seed, 40)
    pay = meas.payload_kg()
    want = joint_loads(ch, pay)
    M, S = distal_loads(ch, pay)
    g = gravity_world(ch)
    phi = body_parameters(TREE)
    moment = np.cross(S - M[..., None] * ch.o_theta, g) / 1000.0  # N*m about each joint's axis point
    assert np.allclose(joint_loads(ch, pay, phi), want, rtol=0, atol=1e-9 * np.abs(want).max())
    assert np.allclose(gravity_moments(ch, pay, phi), moment, atol=1e-9)
    bare = gravity_moments(ch, np.zeros_like(pay), phi)  # what the mass step's regressor columns must add up to
    for j in MOVING:
        carried = phi[TREE.descendants(j)].ravel()
        Y = gravity_regressor(ch, j) @ carried + payload_load(ch, pay, j)
        assert np.allclose(Y, want[:, j], rtol=0, atol=1e-9 * np.abs(want).max())
        for axis in lateral_axes(ch, j):
            assert np.allclose(gravity_regressor(ch, j, axis) @ carried, (bare[j] * axis).sum(1), atol=1e-9)


def test_every_bearing_at_once_is_a_candidate_when_the_model_has_masses():
    meas, *_ = _poses(1, 30)
    named, _ = candidates(TREE, meas)
    lateral = [e for e in named if isinstance(e, LateralJointCompliance)]
    assert len(lateral) == 1 and set(lateral[0].joints) == set(MOVING)
    bare = dataclasses.replace(TREE, mass=None, com=None)
    assert not any(isinstance(e, LateralJointCompliance) for e in candidates(bare, meas)[0])


def test_the_bearings_tilt_by_a_prior_size_and_a_play_by_a_fraction_of_a_degree(seed):
    """Every lateral compliance carries a ridge prior that is TILT_PRIOR_RAD of RMS tilt on the calibration poses
    under the model's masses, kept through a stored state; a gear play carries PLAY_PRIOR_RAD (mm on a rail)."""
    meas, *_ = _poses(seed, 30)
    e = next(c for c in candidates(TREE, meas)[0] if isinstance(c, LateralJointCompliance))
    ch = K.Chain(TREE, K.nominal_vector(TREE), meas.joints, None, meas.labels)
    moment = e._moments(Context(TREE, ch, meas))
    rms = np.array([np.sqrt(np.mean((moment[j] * a).sum(-1) ** 2)) for j in e.joints for a in lateral_axes(ch, j)])
    tilt = np.asarray(e.prior_stds(TREE)) * rms
    assert np.allclose(tilt[rms > 1e-12], TILT_PRIOR_RAD, rtol=1e-9)  # a moment of rounding gets no prior to speak of
    back, _ = effect_from_state(effect_state(e, np.zeros(len(e.parameter_names(TREE)))))
    assert back == e and np.array_equal(np.asarray(back.prior_stds(TREE)), np.asarray(e.prior_stds(TREE)))
    assert Backlash((MOVING[0],)).prior_stds(TREE) == PLAY_PRIOR_RAD
    assert Backlash((0,)).prior_stds(parse_model(spray7())) == PLAY_PRIOR_MM  # the rail


def test_the_tilt_prior_costs_nothing_where_the_bearings_are_of_physical_size(seed):
    """Drawn bearing compliances of physical size (tilts under a few mrad) on 10 um noise: fresh poses are predicted
    as well with the prior as without it (within 5 %)."""
    rng = np.random.default_rng((seed, 9))
    meas, fit, (joint, lateral), err = _elastic_world(seed, rng)
    x, R0 = prealign(TREE, meas)
    prior = LateralJointCompliance.for_data(MOVING, Context(TREE, K.Chain(TREE, x, meas.joints, R0, meas.labels), meas))
    assert prior.prior and not lateral.prior
    assert err(fit([joint, prior])) <= 1.05 * err(fit([joint, lateral])) + 1e-4


def _elastic_world(seed, rng, **identified):
    """The tree's joint and lateral compliances (drawn, rad/(N*m)) deflecting under `identified` (masses, gravity)
    instead of the model's: 200 measured poses (10 um noise), the fitter on them, the model's compliances fitted
    beside the geometry, and the error (mm RMS) of a calibration against the truth on 100 fresh poses."""
    effects = (JointCompliance(MOVING, **identified), LateralJointCompliance(MOVING, **identified))
    values = (rng.uniform(0.5, 2.0, len(MOVING)) * 1e-5, rng.uniform(0.5, 2.0, 2 * len(MOVING)) * 1e-5)
    meas, x, R0, _ = _poses(seed, 200)
    world = CalibratedRobot(TREE, x, R0, effects, values, x, ("",))
    truth = world.predict(meas.joints, meas)
    meas = dataclasses.replace(meas, points=truth + rng.normal(0, 0.01, truth.shape), sigma=np.full(200, 0.01))
    fresh, *_ = _poses(seed + 1, 100)
    fresh_truth = world.predict(fresh.joints, fresh)
    fit = _Fitter(TREE, meas, None, 5, None, 1.0)
    return meas, fit, [JointCompliance(MOVING), LateralJointCompliance(MOVING)], Fresh(fresh, fresh_truth)


@dataclasses.dataclass
class Fresh:
    """Fresh poses and their true points: a calibration's error there (mm RMS of the distance), and its RMS z."""

    meas: object
    truth: np.ndarray

    def __call__(self, cal) -> float:
        return float(np.sqrt(np.mean(np.sum((cal.predict(self.meas.joints, self.meas) - self.truth) ** 2, 1))))

    def z(self, cal) -> float:
        err = cal.predict(self.meas.joints, self.meas) - self.truth
        return float(np.sqrt(np.mean((err / prediction_std_mm(cal, self.meas.joints, self.meas)) ** 2)))


def test_mass_data_are_identified_under_the_compliances(seed):
    """Deflections made with mass data 0.6-1.6x the model's: fitting the compliances on the model's masses leaves
    a load-shaped error; the mass steps remove most of it on fresh poses and say so in a note."""
    rng = np.random.default_rng((seed, 6))
    phi = body_parameters(TREE)
    true = phi * rng.uniform(0.6, 1.6, len(phi))[:, None]
    true[:, 1:] += rng.normal(0, 20.0, (len(phi), 3)) * true[:, :1]  # centres of mass 20 mm off
    meas, fit, chosen, err = _elastic_world(seed, rng, masses=tuple(map(tuple, true)))
    before = fit(chosen)
    findings = [{"form": e.label(TREE), "kind": e.kind, "joints": []} for e in chosen]
    notes = []
    after = _identify_masses(before, chosen, findings, TREE, meas, fit, notes)

    assert err(after) < 0.5 * err(before), (err(before), err(after))
    assert all(e.masses for e in chosen), chosen
    assert any("mass data were identified" in n for n in notes), notes
    assert all("identified masses" in f["form"] for f in findings), findings

    # the masses came from these poses: their doubt widens the prediction std, never narrows it
    _assert_mass_doubt_widens(after, fit, seed)


def _assert_mass_doubt_widens(cal, fit, seed):
    """The mass data's doubt is set on `cal` and widens its prediction std at fresh poses, never narrows them (taken
    at the calibration's own estimate, a Schur complement: refitted, they narrowed by up to 8 %, seed 43)."""
    fresh, *_ = _poses(seed + 1, 100)
    sure = prediction_std_mm(cal, fresh.joints, fresh)
    _with_mass_doubt(cal, fit, TREE)
    assert cal.mass_doubt, "the compliances' mass data carry their doubt"
    doubted = prediction_std_mm(cal, fresh.joints, fresh)
    assert (doubted >= 0.999 * sure).all() and doubted.mean() > 1.05 * sure.mean(), (sure.mean(), doubted.mean())


def test_the_models_own_mass_data_carry_their_doubt_too(seed):
    """Compliances fitted on the model's mass data, which are 15 % and 30 mm off the world's: the prediction std
    propagate a mass step's doubt as they do for identified masses (they widen, never narrow), and the move its
    optimum would make, so that they cover the error the mass data leave (RMS z 2.5-3.1 without the doubt, 2.1 with
    its covariance alone, 0.77-0.90 with the move too; seeds 20-31)."""
    rng = np.random.default_rng((seed, 11))
    phi = body_parameters(TREE)
    true = phi * rng.uniform(0.85, 1.15, len(phi))[:, None]
    true[:, 1:] += rng.normal(0, 30.0, (len(phi), 3)) * true[:, :1]
    meas, fit, chosen, fresh = _elastic_world(seed, rng, masses=tuple(map(tuple, true)))
    cal = fit(chosen)
    assert not any(e.masses for e in cal.effects)
    _assert_mass_doubt_widens(cal, fit, seed)
    assert 0.6 < fresh.z(cal) < 1.4, fresh.z(cal)


def test_a_bent_links_mass_columns_add_up_to_its_bending(seed):
    """A link's bending is homogeneous of degree one in the mass data (each body's weight at its fixed centre of
    mass): the mass step's columns for it, weighted by the mass data themselves, give back the bending under the
    bodies' weight (no payload), on every link of the tree that has one. To 1 %, not to rounding: a body whose centre
    projects within a difference step of a beam's end is clamped there on one side of the step (a kink), which
    leaves up to 4.4e-4 of the bending on 25 drawn seeds (1e-7 without the clamp); wrong columns are off by O(1)."""
    meas, _, _, ch = _poses(seed, 30)
    meas = dataclasses.replace(meas, payload=np.zeros(meas.n_poses))
    ctx = Context(TREE, ch, meas)
    rng = np.random.default_rng((seed, 12))
    phi = body_parameters(TREE)
    for k in range(1, TREE.n_joints):
        e = LinkDeflection((k,))
        v = rng.uniform(0.5, 2.0, 2) * 1e-12
        want = e.displacement(ctx, v)
        if np.abs(want).max() < 1e-9:
            continue
        step = mass_step([(e, v)], TREE, TREE.gravity)
        cols = step.basis(ctx).dense(TREE.n_joints, len(step.prior))[1]
        got = cols[:, :, :-2] @ phi[list(step.bodies)].ravel()
        assert np.allclose(got, want, rtol=0, atol=1e-2 * np.abs(want).max()), (k, np.abs(got - want).max())


def test_a_bent_link_carries_the_doubt_of_the_mass_data_it_bends_under(seed):
    """A link's bending fitted on the model's mass data, which are 15 % and 30 mm off the world's: the prediction std
    widen by the mass step's doubt as a compliance's do."""
    rng = np.random.default_rng((seed, 13))
    meas, x, R0, _ = _poses(seed, 200)
    e = LinkDeflection((TREE.joint_names.index("T3"),))  # the torso link: both arms on it, ~0.4 mm of bending
    phi = body_parameters(TREE)
    true = phi * rng.uniform(0.85, 1.15, len(phi))[:, None]
    true[:, 1:] += rng.normal(0, 30.0, (len(phi), 3)) * true[:, :1]
    com = np.where(true[:, :1] > 0, true[:, 1:] / np.where(true[:, :1] > 0, true[:, :1], 1.0), TREE.com)
    world = CalibratedRobot(dataclasses.replace(TREE, mass=true[:, 0], com=com), x, R0, (e,),
                            (np.array([2e-11, 1e-11]),), x, ("",))
    truth = world.predict(meas.joints, meas)
    meas = dataclasses.replace(meas, points=truth + rng.normal(0, 0.01, truth.shape), sigma=np.full(200, 0.01))
    fit = _Fitter(TREE, meas, None, 5, None, 1.0)
    cal = fit([e])
    _assert_mass_doubt_widens(cal, fit, seed)
    assert [c for c, _ in cal.mass_doubt[0].causes] == [e], "the mass step carries the bent link"


def test_gravity_direction_is_identified_with_the_mass_data(seed):
    """A base frame 10-30 mrad off level (the world's gravity tilted against the model's base z, about a drawn axis):
    on the model's gravity a pitch joint's large torque leaks into the bending moments across it as a load-shaped
    error. The mass steps identify the direction too: it lands within a third of the tilt of the truth, the error on
    fresh poses at least halves, and the note gives the tilt found. On 2 of 3 drawn worlds. From the model's gravity
    alone the first step can trade the tilt for the first moments, or (the torso's vertical T1, compliant too, a
    saddle of the bilinear fit) turn gravity by 0.9 mrad where 25 are needed, and stop; the second start, from the
    best of a ring of tilts (masses._tilt_scan), reaches it: 0 of 120 worlds missed (seeds 400-439), 6 before the
    ring (the test failed on seeds 1402013346 and 285246627)."""
    from calib_core.effects.gravity import tilted

    angle = lambda a, b: float(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))  # noqa: E731
    failed = []
    for k in range(3):
        rng = np.random.default_rng((seed, 7, k))
        tilt = rng.uniform(0.010, 0.030) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
        g_true = tilted(TREE.gravity, tilt)
        meas, fit, chosen, err = _elastic_world(seed + k, rng, masses=tuple(map(tuple, body_parameters(TREE))),
                                                gravity=tuple(g_true))
        before = fit(chosen)
        notes = []
        after = _identify_masses(before, chosen, [], TREE, meas, fit, notes)
        if not any("mrad off the model's base z" in n for n in notes):  # held-out poses refused the steps' answer
            failed.append((k, "refused", err(before)))
            continue
        found = np.asarray(chosen[1].gravity)
        assert found.shape == (3,)
        if not (angle(found, g_true) < angle(TREE.gravity, g_true) / 3 and err(after) < 0.5 * err(before)):
            failed.append((k, angle(found, g_true), angle(TREE.gravity, g_true), err(before), err(after)))
    assert len(failed) <= 1, (seed, failed)


def test_a_vertical_axis_carries_no_identified_load(seed):
    """Gravity has no moment about a vertical axis: its regressor is rounding (1e-17), which normalised to a unit
    load had become a load of 1e20 x its features, jumping at every joint move (the Motoman's torso axis E: the
    extended model's dp/dq reached 9e4 mm/rad and compensation missed its targets). Each joint of the drawn arm
    gets an identified load exactly when gravity has a moment about its axis at the poses."""
    from calib_core.effects.gravity import load_mix_for
    from calib_core.robots import arm6, spray7

    model = parse_model(arm6() if seed % 2 else spray7())
    meas = Twin(model, seed=seed, repeatability_mm=0.0, tracker_noise=False).measure(n=40)
    x, R0 = prealign(model, meas)
    chain = K.Chain(model, x, meas.joints, R0, meas.labels)
    g = gravity_world(chain)
    for j in range(model.n_joints):
        along = np.abs((chain.z_axis[j] * g).sum(-1)) / np.linalg.norm(g)  # |cos| of the axis against gravity
        no_moment = (along > 1.0 - 1e-12).all() if not model.prismatic[j] else (along < 1e-12).all()
        assert (load_mix_for(chain, j) is None) == no_moment, (model.joint_names[j], along.min(), seed)
        assert (_LoadFeatures.of(chain, meas, j) is None) == no_moment, (model.joint_names[j], seed)


def test_a_spring_on_a_plays_identified_load_bends_less_and_less_with_it(seed):
    """The stiffening spring tried beside a play found on an identified load: it deflects with that load's sign,
    monotonically, ever less per unit of load, and its parameter is the deflection at the largest load (rad)."""
    from calib_core.effects import Backlash
    from calib_core.effects.joint_effects import hardening

    meas, _, _, ch = _poses(seed, 60)
    ctx = Context(TREE, ch, meas)
    rng = np.random.default_rng((seed, 6))
    j = int(rng.choice([k for k in MOVING if np.ptp(ctx.loads[:, k]) > 0]))
    coef = tuple(rng.normal(size=gravity_regressor(ch, j).shape[1] + 1))
    load = Backlash((j,), transition=1.0, load_coef=coef).load(ctx)
    r = float(rng.choice(STIFFENING))
    spring = JointCompliance((j,), stiffening=r, load_scale=float(np.abs(load).max()), load_coef=coef)
    g = spring.basis(ctx).joint[:, j, 0]
    order = np.argsort(np.abs(load))
    assert np.all(np.sign(g) == np.sign(load)), seed
    assert np.all(np.diff(np.abs(g)[order]) >= -1e-12), seed
    assert np.all(np.diff((np.abs(g) / np.maximum(np.abs(load), 1e-300))[order][1:]) <= 1e-12), seed
    assert np.isclose(np.abs(g).max(), hardening(np.array(1.0), r)), seed
    assert spring.parameter_units(TREE) == ["rad" if not TREE.prismatic[j] else "mm"], seed


def test_a_spring_on_identified_mass_data_stiffens_on_that_mass_data(seed):
    """The stiffening forms tried for a found spring deflect under the mass data and gravity it carries (identified
    under it), not the model's: a spring narrowed from a spread compliance on identified masses was refined on the
    model's 15 %-off masses, or not at all (the blind test's stiffening spring, seed 49842499). The largest load
    is theirs, and each form bends as `hardening` of their load."""
    from calib_core.effects import loads
    from calib_core.effects.joint_effects import hardening

    meas, _, _, ch = _poses(seed, 60)
    ctx = Context(TREE, ch, meas)
    rng = np.random.default_rng((seed, 7))
    j = int(rng.choice([k for k in MOVING if np.ptp(ctx.loads[:, k]) > 0]))
    phi = body_parameters(TREE) * rng.uniform(0.6, 1.4, (TREE.n_joints, 1))
    g = np.asarray(TREE.gravity, float) + rng.normal(0.0, 0.3, 3)
    spring = JointCompliance((j,), masses=tuple(map(tuple, phi)), gravity=tuple(g))
    own = loads(ch, meas, phi, g)[:, j]
    assert not np.allclose(own, ctx.loads[:, j]), seed
    stiff = [f for f in _refinements(spring, {}, {}, ctx) if type(f) is JointCompliance and f.stiffening]
    assert sorted(f.stiffening for f in stiff) == sorted(STIFFENING), seed
    for f in stiff:
        assert (f.masses, f.gravity) == (spring.masses, spring.gravity), seed
        assert np.isclose(f.load_scale, np.abs(own).max()), seed
        assert np.allclose(f.basis(ctx).joint[:, j, 0], hardening(own / f.load_scale, f.stiffening) * f.load_scale), seed
    plain = [f for f in _refinements(JointCompliance((j,)), {}, {}, ctx) if type(f) is JointCompliance and f.stiffening]
    assert all(not f.masses and np.isclose(f.load_scale, np.abs(ctx.loads[:, j]).max()) for f in plain), seed


def test_positions_tell_masses_only_up_to_a_scale_unless_a_known_payload_varies(seed):
    """Why the mass note says the identified masses' common scale is the model's when no payload varies: a spring
    under twice every body's mass data bends exactly as one half as stiff (so positions cannot tell them), and with
    a payload of known kg that changes between poses it does not."""
    meas, _, _, ch = _poses(seed, 60)  # payloads 0 / 5 kg drawn per pose
    rng = np.random.default_rng((seed, 8))
    phi = body_parameters(TREE) * rng.uniform(0.7, 1.3, (TREE.n_joints, 1))
    for payload, proportional in ((None, True), (meas.payload, False)):
        ctx = Context(TREE, ch, dataclasses.replace(meas, payload=payload))
        j = int(rng.choice([k for k in MOVING if np.ptp(ctx.loads[:, k]) > 0]))
        bend = [JointCompliance((j,), masses=tuple(map(tuple, k * phi))).basis(ctx).joint[:, j, 0] for k in (1, 2)]
        assert np.allclose(bend[1], 2 * bend[0], rtol=1e-12, atol=1e-15) == proportional, (seed, payload is None)


def _energy_loads(meas, x, R0, h=1e-6):
    """The gravity + payload load on each actuated joint's drive (N, n_act) N*m, from the potential energy of the
    tree's bodies and payload (J, mm -> m) differentiated along each actuated coordinate, the coupled rows following
    it: load = -dV/dq, the test's own statics (no moment sums)."""
    q_act = meas.joints[:, TREE.actuated]

    def V(qa):
        ch = K.Chain(TREE, x, TREE.expand_joints(qa), R0, meas.labels)
        gw = ch.Rb @ TREE.gravity
        com = ch.o_beta + np.einsum("jnab,jb->jna", ch.R, TREE.com)
        return -(np.einsum("j,jna,a->n", TREE.mass, com, gw) + meas.payload_kg() * (ch.p @ gw)) / 1000.0

    out = np.empty_like(q_act)
    for a in range(q_act.shape[1]):
        d = np.zeros(q_act.shape[1])
        d[a] = h
        out[:, a] = -(V(q_act + d) - V(q_act - d)) / (2 * h)
    return out


def test_a_drive_carries_the_loads_of_the_coupled_rows_it_moves(seed):
    """T4 follows T2 and T3 (q4 = -q2 - q3): the drives of T2 and T3 hold T4's load too, by the coupling's
    coefficients. The loads of every drive equal the potential energy's slope along its coordinate (the coupled
    row moving with it), and the identified-load regressors and the mass step's columns add up to them."""
    from calib_core.effects import loads
    from calib_core.effects.gravity import drive_bodies, drive_payload_load, drive_regressor, mass_step

    meas, x, R0, ch = _poses(seed, 40)
    want = _energy_loads(meas, x, R0)
    got = loads(ch, meas)
    scale = np.abs(want).max()
    assert np.allclose(got[:, TREE.actuated], want, rtol=0, atol=1e-6 * scale), np.abs(got[:, TREE.actuated] - want)
    t2, t4 = TREE.joint_names.index("T2"), TREE.joint_names.index("T4")
    assert np.abs(got[:, t2] - joint_loads(ch, meas.payload_kg())[:, t2]).max() > 0.05 * scale  # T4's load is in
    phi = body_parameters(TREE)
    for j in TREE.actuated:
        Y = drive_regressor(ch, j) @ phi[drive_bodies(TREE, j)].ravel() + drive_payload_load(ch, meas.payload_kg(), j)
        assert np.allclose(Y, got[:, j], rtol=0, atol=1e-9 * scale), TREE.joint_names[j]

    # the mass step's columns are the compliances' deflection per unit mass data, the coupled row moving too
    rng = np.random.default_rng((seed, 12))
    effect = JointCompliance(MOVING)
    v = rng.uniform(0.5, 2.0, len(MOVING)) * 1e-5
    ctx = Context(TREE, ch, meas)
    step = mass_step([(effect, v)], TREE, TREE.gravity)
    cols = step.basis(ctx).joint
    body, h = TREE.joint_names.index("T3"), 1e-3  # T3's mass, carried by the drives of T1-T3 and by T4
    bumped = phi.copy()
    bumped[body, 0] += h
    moved = (dataclasses.replace(effect, masses=tuple(map(tuple, bumped))).basis(ctx).joint
             - dataclasses.replace(effect, masses=tuple(map(tuple, phi))).basis(ctx).joint) @ v / h
    k = 4 * step.bodies.index(body)
    assert np.allclose(cols[:, :, k], moved, rtol=0, atol=1e-6 * np.abs(moved).max()), np.abs(cols[:, :, k] - moved)
    assert np.abs(moved[:, t4]).max() > 0.1 * np.abs(moved[:, t2]).max()  # the coupled row moves with its drives


def test_the_compliance_of_a_coupled_drive_is_identified_from_its_deflection(seed):
    """A world whose torso drives (T2, T3) deflect by a drawn compliance times their load from the potential energy
    (the coupled T4 turning with them, as the linkage makes it), 10 um noise: the joint compliance of the model
    recovers each drive's compliance within 5 % and predicts fresh poses to within the noise. Each drive's own load
    alone, moving its own row alone (the form before), gave 38-63 % off and T3 of the wrong sign (seeds 1, 2)."""
    from calib_core.identify import identify

    rng = np.random.default_rng((seed, 13))
    drives = [TREE.joint_names.index(n) for n in ("T2", "T3")]
    c = rng.uniform(0.5, 3.0, 2) * 1e-5  # rad/(N*m)

    def world(meas, x, R0):
        load = _energy_loads(meas, x, R0)
        qa = meas.joints[:, TREE.actuated].copy()
        for j, cj in zip(drives, c):
            a = list(TREE.actuated).index(j)
            qa[:, a] += cj * load[:, a]
        return K.forward(TREE, x, TREE.expand_joints(qa), R0, meas.labels)

    meas, x, R0, _ = _poses(seed, 200)
    truth = world(meas, x, R0)
    meas = dataclasses.replace(meas, points=truth + rng.normal(0, 0.01, truth.shape), sigma=np.full(200, 0.01))
    cal = identify(TREE, meas, effects=(JointCompliance(tuple(drives)),), folds=0)
    got = cal.effect_values[0]  # within 0.4 % on seeds 1-5 (the std say 0.05 %: the base the loads are taken on
    assert np.allclose(got, c, rtol=0.05, atol=0), (got, c, seed)  # moves with the fit)
    fresh, *_ = _poses(seed + 1, 100)
    err = cal.predict(fresh.joints, fresh) - world(fresh, x, R0)
    assert np.sqrt(np.mean(np.sum(err**2, 1))) < 0.01, (np.sqrt(np.mean(np.sum(err**2, 1))), seed)


def test_a_tilted_base_springs_mass_columns_are_its_deflection_per_unit_mass_data(seed):
    """A spring on a vertical axis under a tilted base (TiltedCompliance: compliance x tilt per horizontal axis) is
    linear in the mass data too: the mass step's columns for it are the change of its deflection per unit change of
    each body's mass and first moment (central differences on a drawn body, a drawn column), so that the mass data
    are identified under it as under any spring (a base tilted, masses 15 % off: A1's scale had taken their part)."""
    from calib_core.effects import TiltedCompliance

    meas, _, _, ch = _poses(seed, 40)
    ctx = Context(TREE, ch, meas)
    rng = np.random.default_rng((seed, 14))
    t1 = TREE.joint_names.index("T1")  # the torso's vertical axis: no load from the model's gravity
    effect = TiltedCompliance((t1,))
    v = rng.normal(0, 1e-6, 2)
    step = mass_step([(effect, v)], TREE, TREE.gravity)
    cols = step.basis(ctx).joint
    phi = body_parameters(TREE)
    body = int(rng.choice(step.bodies))
    c = int(rng.integers(4))
    h = 1e-3 * max(phi[body, 0], 1.0) * (1.0 if c == 0 else 100.0)
    up, down = phi.copy(), phi.copy()
    up[body, c] += h
    down[body, c] -= h
    moved = (dataclasses.replace(effect, masses=tuple(map(tuple, up))).basis(ctx).joint
             - dataclasses.replace(effect, masses=tuple(map(tuple, down))).basis(ctx).joint) @ v / (2 * h)
    k = 4 * step.bodies.index(body) + c
    # to 1e-6 of the step's largest column: a column the spring does not feel is zero up to rounding on both sides
    # (seed 951214586: Rplate's first moment, 5e-18 against 1e-17)
    scale = max(np.abs(moved).max(), np.abs(cols).max())
    assert np.allclose(cols[:, :, k], moved, rtol=0, atol=1e-6 * scale), (TREE.joint_names[body], c)


def test_a_links_root_turn_is_its_bending_and_a_turn_about_its_root(seed):
    """RootTurnLinkDeflection on every revolute link of the tree: its first two columns are the plain bending's, its
    third moves each target as a turn about the link's root (perpendicular to the lever from the root), growing with
    the load; its state comes back as itself."""
    meas, _, _, ch = _poses(seed, 30)
    ctx = Context(TREE, ch, meas)
    heavy = dataclasses.replace(meas, payload=meas.payload_kg() + 10.0)
    done = 0
    for k in range(1, TREE.n_joints):
        if TREE.prismatic[k]:
            continue
        e = RootTurnLinkDeflection((k,))
        assert e.parameter_names(TREE)[2] == f"{TREE.joint_names[k]}.root_compliance"
        assert e.parameter_units(TREE)[2] == "rad/(N*mm)" and e.label(TREE).endswith(" root")
        cart = e.basis(ctx).cart
        assert np.array_equal(cart[:, :, :2], LinkDeflection((k,)).basis(ctx).cart)
        turn = cart[:, :, 2]
        if np.abs(turn).max() < 1e-9:
            continue
        start = _beam(ch, k, None)[0]
        lever = ch.p - start
        scale = np.abs(lever).max() * np.abs(turn).max()
        assert np.allclose((turn * lever).sum(1), 0.0, atol=1e-9 * scale)  # a turn about the root
        more = e.basis(Context(TREE, ch, heavy)).cart[:, :, 2]
        assert np.linalg.norm(more) > np.linalg.norm(turn)  # 10 kg more at each tool: more moment at the root
        back, values = effect_from_state(effect_state(e, np.array([1e-12, 2e-12, 3e-9])))
        assert back == e and type(back) is RootTurnLinkDeflection and values[2] == 3e-9
        done += 1
    assert done > 3


def test_a_found_revolute_links_richer_forms_include_its_root_turn():
    """The refinements of a found bending link: its root turn on a revolute link; a telescopic stage's guide is a
    candidate of its own (spray7's J6), not a refinement."""
    model = parse_model(spray7())
    meas = Twin(model, seed=4, repeatability_mm=0.0, tracker_noise=False).measure(n=20)
    ctx = Context(model, K.Chain(model, K.nominal_vector(model), meas.joints, None, meas.labels), meas)
    for k in range(1, model.n_joints):
        forms = _refinements(LinkDeflection((k,)), {}, {}, ctx)
        assert (RootTurnLinkDeflection((k,)) in forms) == (not model.prismatic[k]), model.joint_names[k]


def test_the_targets_of_one_pose_share_one_row_of_load_features(seed):
    """Both targets measured at each pose of a torso carrying two arms, the rows in a drawn order: every joint's
    identified-load features are one row, to the bit, for the two targets of a pose (the SVD that makes them gave the
    two rows different last bits on Agile Justin: 397 distinct rows for 350 poses), so the play fits take each pose
    once (plays._tied: 30 rows where 60, none for the weightless rows of a joint that does not move a target)."""
    from calib_core.diagnosis.plays import _tied
    from calib_core.io import Measurements

    model = parse_model(torso_two_arms(mass=True))
    rng = np.random.default_rng((seed, 24))
    q = Twin(model, seed=seed, repeatability_mm=0.0, tracker_noise=False).measure(n=30).joints
    order = rng.permutation(60)
    meas = Measurements(joints=np.repeat(q, 2, axis=0)[order], points=np.zeros((60, 3)),
                        target=np.tile([0, 1], 30)[order])
    chain = K.Chain(model, K.nominal_vector(model), meas.joints, None, meas.labels)
    pose = np.repeat(np.arange(30), 2)[order]
    first = np.array([np.flatnonzero(pose == p)[0] for p in pose])  # each row's pose's first row
    looked = 0
    for j in np.flatnonzero(model.moving):
        feats = _LoadFeatures.of(chain, meas, j)
        if feats is None:
            continue
        looked += 1
        assert np.array_equal(feats.Z, feats.Z[first]), (model.joint_names[j], seed)
        w = rng.uniform(0.5, 2.0, 60)
        if model.joint_names[j][0] in "LR":  # an arm's joint moves one hand's target: the other's rows weigh nothing
            w = w * (meas.target == model.target_names.index("left" if model.joint_names[j][0] == "L" else "right"))
        assert len(_tied(feats.Z, rng.normal(size=60), np.sqrt(w))[0]) <= 30, (model.joint_names[j], seed)
    assert looked >= 5, seed
