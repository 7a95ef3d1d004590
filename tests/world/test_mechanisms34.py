"""Issue 34's mechanisms are physically right in the world's own mechanics (checked against hand-made cases)."""
import numpy as np
import pytest

from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_world import (EXPECTED, MECHANISMS_34, Cantilever, GearPlay, JointSpring, JointSprings, LinkGrowth,
                         TargetStep, TelescopicSag, TiltedBase, World, hide)
from calib_world.mechanics import Context, simulate
from calib_world.robot import rotvec
from calib_world.scenarios import PLAY_SIGN_SHARE, TILT_MADE_SHARE, model_loads, with_gravity


def _exact(doc, seed, **kw):
    """A noise-free world with wrong masses (15 %, as the benchmark's) and the true geometry's errors."""
    return World(parse_model(doc()), seed, noise=False, **kw)


def _ctx(world, q, payload=None, temperature=None):
    N = len(q)
    return Context(world.robot, q, world.start_time + 20.0 * np.arange(N),
                   np.full(N, world.ambient_degC) if temperature is None else np.asarray(temperature, float),
                   np.zeros(N) if payload is None else np.broadcast_to(np.asarray(payload, float), (N,)).copy(),
                   world.ambient_degC)


# ------------------------------------------------------------------------------------------ a. play and load sign
@pytest.mark.parametrize("doc", [spray7, arm6])
def test_play_side_follows_the_true_load_not_the_models(doc, seed):
    world = _exact(doc, seed)
    r = world.robot
    rng = np.random.default_rng(seed)
    q = world.sample_joints(3000, rng)
    payload = rng.choice([0.0, 10.0, 20.0], len(q))
    tau = r.joint_loads(q, payload)
    tau_model = model_loads(world, q, payload)  # the model's masses (15 % off) on the same geometry
    wrong = np.mean(np.sign(tau) != np.sign(tau_model), axis=0)
    span = np.ptp(tau, axis=0)
    wrong[span < 0.05 * span.max()] = 0.0  # a vertical axis carries only the levelling error's load
    j = int(np.argmax(wrong))
    assert wrong[j] > 0, f"no pose where the model's masses give the other side (seed {seed})"
    play = GearPlay(j, 2e-3 if r.prismatic[j] else 2e-4)
    dq = play.joint_offset(_ctx(world, q, payload))
    assert np.all(dq[:, np.arange(r.n) != j] == 0)
    assert np.array_equal(dq[:, j], 0.5 * play.play * np.sign(tau[:, j]))  # the side the true load pushes to
    flip = np.sign(tau[:, j]) != np.sign(tau_model[:, j])
    assert np.all(np.sign(dq[flip, j]) == -np.sign(tau_model[flip, j]))
    # the tool point moves as the world's FK moved by that half play, and the side flips with the load
    k = slice(0, 40)
    cols = world.columns(q[k], payload[k])
    d = world.displacement(play, q[k], cols)
    assert np.allclose(d, r.point(q[k], dq[k]) - r.point(q[k]), atol=1e-9)
    # the same pose with the load's sign reversed (gravity upside down) goes to the other flank
    upside = with_gravity(r, -r.gravity)
    dq_up = play.joint_offset(Context(upside, q, np.zeros(len(q)), np.full(len(q), 20.0), payload))
    assert np.array_equal(dq_up[:, j], -dq[:, j])


def test_play_load_sign_draws_a_joint_whose_load_changes_sign(seed):
    model = parse_model(arm6())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    info = hide(world, "play_load_sign", 2.0, rng, n=60, payload_kg=[0.0, 5.0])
    j = world.robot.names.index(info["joints"][0])
    share = np.mean(world.robot.joint_loads(info["q"], world.columns(info["q"], [0.0, 5.0]).payload_kg())[:, j] > 0)
    assert PLAY_SIGN_SHARE[0] <= share <= PLAY_SIGN_SHARE[1] and info["notes"]["true_load_positive_share"] == share
    assert info["expected"] == "backlash" and info["notes"]["model_side_wrong_share"] is not None


# ------------------------------------------------------------------------------------------ b. one link grows
@pytest.mark.parametrize("doc", [spray7, arm6])
def test_link_grows_along_its_length_only_and_with_the_temperature(doc, seed):
    world = _exact(doc, seed)
    r = world.robot
    rng = np.random.default_rng(seed)
    k = int(np.argmax(np.hypot(r.geometry[:, 0], r.geometry[:, 2]) * ~r.prismatic))
    q = world.sample_joints(30, rng)
    rise = rng.uniform(-3.0, 8.0, len(q))
    grow = LinkGrowth(k, 2e-5)
    geo = np.broadcast_to(r.geometry, (len(q), r.n, 5)).copy()
    g2, tool = grow.geometry(_ctx(world, q, temperature=world.ambient_degC + rise), geo, r.tool)
    assert np.array_equal(tool, r.tool)
    cold, warm = r.frames(q), r.frames(q, geometry=g2)
    seg0 = np.diff(np.concatenate([cold.base[:, None, :3, 3], cold.origins], 1), axis=1)  # (N, n, 3) joint to joint
    seg1 = np.diff(np.concatenate([warm.base[:, None, :3, 3], warm.origins], 1), axis=1)
    others = np.arange(r.n) != k
    assert np.allclose(seg1[:, others], seg0[:, others], atol=1e-9)  # no other link changes length or direction
    assert np.allclose(warm.frames[..., :3, :3], cold.frames[..., :3, :3], atol=1e-12)  # no frame turns
    L = np.linalg.norm(seg0[:, k], axis=1)
    assert np.allclose(seg1[:, k], seg0[:, k] * (1 + 2e-5 * rise)[:, None], atol=1e-9)  # along the link, x rise
    assert np.allclose(np.linalg.norm(seg1[:, k], axis=1) - L, 2e-5 * rise * L, atol=1e-9)
    # the tool point's move is linear in the temperature rise: twice the rise, twice the move
    move = lambda t: simulate(r, [grow], _ctx(world, q, temperature=t)) - r.point(q)  # noqa: E731
    d1, d2 = move(world.ambient_degC + rise), move(world.ambient_degC + 2 * rise)
    assert np.allclose(d2, 2 * d1, rtol=1e-6, atol=1e-9) and np.abs(d1).max() > 1e-3


def test_link_thermal_growth_logs_a_temperature_that_is_not_the_time_order(seed):
    model = parse_model(spray7())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    info = hide(world, "link_thermal_growth", 2.0, rng, n=80)
    cols = world.columns(info["q"], temperature=True)
    assert info["temperature"] and info["joints"] == [] and info["expected"] == "thermal_drift"
    assert world.hvac is not None and abs(np.corrcoef(cols.temperature, cols.timestamp)[0, 1]) < 0.995
    assert abs(world.temperature_at(np.array([world.start_time]))[0] - world.ambient_degC) < 1e-12


# ------------------------------------------------------------------------------------------ c. target re-mounted
@pytest.mark.parametrize("doc", [spray7, arm6])
def test_target_step_happens_at_pose_n_in_the_flange_frame(doc, seed):
    model = parse_model(doc())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng, noise=False)
    info = hide(world, "target_remount", 3.0, rng, n=80)
    step, q = info["cause"], info["q"]
    assert isinstance(step, TargetStep) and 0.3 * 80 <= step.at_pose <= 0.7 * 80 + 1
    camp = world.campaign(q)
    d = camp.truth.displacement
    N = step.at_pose
    assert camp.meas.timestamp[N] == step.at_time
    assert np.abs(d[:N]).max() < 1e-12  # before pose N in time order: nothing
    R = world.robot.frames(q).frames[:, -1, :3, :3]
    assert np.allclose(d[N:], np.einsum("nab,b->na", R[N:], step.offset_mm), atol=1e-9)  # after: the offset
    assert np.linalg.norm(step.offset_mm) > 0


# ------------------------------------------------------------------------------------------ d. tilted base
def _beam(L=1200.0, m_tip=50.0):
    """B1 vertical, a horizontal arm of length L along x to B2, a point mass at B2, gravity -z."""
    doc = {"name": "beam", "convention": "mdh", "units": {"length": "mm", "angle": "deg"},
           "joints": [{"name": "B1", "type": "revolute", "limits": [-90, 90], "mass": 0.0, "com": [0, 0, 0]},
                      {"name": "B2", "type": "revolute", "a": L, "limits": [-90, 90], "mass": m_tip,
                       "com": [0, 0, 0]}],
           "tool": [0.0, 0.0, 0.0], "gravity": [0, 0, -9.81]}
    return parse_model(doc)


def _level(model, seed):
    return World(model, seed, geometry_error=0.0, tool_error_mm=0.0, mass_error=0.0, level_error_rad=0.0,
                 noise=False)


def test_tilted_base_turns_the_sag_and_loads_a_vertical_axis(seed):
    world = _level(_beam(), seed)
    rng = np.random.default_rng(seed)
    q = world.sample_joints(20, rng)
    R = world.robot.base[:3, :3]
    beam = Cantilever("B2", 3e11, own_mass_kg=0.0)
    level = world.displacement(beam, q) @ R  # robot base frame
    th = float(np.radians(rng.uniform(2.0, 10.0)))
    # tilt about the beam's own direction (at q1 = 0: x) only turns the sag by the tilt; about y, shortens it
    q0 = q.copy()
    q0[:, 0] = 0.0
    flat = world.displacement(beam, q0) @ R
    along = world.displacement(TiltedBase((th, 0.0, 0.0), (beam,)), q0) @ R
    cosang = (along * flat).sum(1) / np.linalg.norm(along, axis=1) / np.linalg.norm(flat, axis=1)
    assert np.allclose(np.arccos(np.clip(cosang, -1, 1)), th, atol=1e-6)
    assert np.allclose(np.linalg.norm(along, axis=1), np.linalg.norm(flat, axis=1), rtol=1e-6)
    g_t = rotvec(np.array([th, 0.0, 0.0])) @ world.robot.gravity
    assert np.allclose(along / np.linalg.norm(along, axis=1)[:, None], g_t / np.linalg.norm(g_t), atol=1e-6)
    across = world.displacement(TiltedBase((0.0, th, 0.0), (beam,)), q0) @ R
    assert np.allclose(np.linalg.norm(across, axis=1), np.cos(th) * np.linalg.norm(flat, axis=1), rtol=1e-6)
    assert np.abs(level).max() > 1e-3
    # the vertical axis carries no load level; tilted, its spring winds it by c x the tilt's share of the weight
    spring = JointSpring("B1", 1e-5)
    assert np.abs(world.displacement(spring, q)).max() < 1e-12
    tilted = TiltedBase((th, 0.0, 0.0), (spring,))
    dq = tilted.joint_offset(_ctx(world, q))
    expect = 50.0 * 9.81 * np.sin(th) * 1.2 * np.cos(q[:, 0])  # N*m: m g sin(tilt) x the arm's reach along x
    assert np.allclose(np.abs(dq[:, 0]), 1e-5 * np.abs(expect), rtol=1e-9)
    assert np.abs(dq[:, 1]).max() == 0 and tilted.scaled(0.0).joint_offset(_ctx(world, q)).max() == 0


def test_tilted_base_spring_sits_where_the_tilt_makes_the_load(seed):
    model = parse_model(arm6())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    info = hide(world, "tilted_base_spring", 2.0, rng, n=60, payload_kg=[0.0, 5.0])
    tb = info["cause"]
    j = world.robot.names.index(info["joints"][0])
    assert isinstance(tb, TiltedBase) and 3.0 <= np.degrees(np.linalg.norm(tb.tilt_rad)) <= 10.0
    g = world.robot.gravity
    assert abs(np.asarray(tb.tilt_rad) @ g) < 1e-12 * np.linalg.norm(g)  # about a horizontal axis
    pl = world.columns(info["q"], [0.0, 5.0]).payload_kg()
    t0 = world.robot.joint_loads(info["q"], pl)[:, j]
    t1 = with_gravity(world.robot, rotvec(np.asarray(tb.tilt_rad)) @ g).joint_loads(info["q"], pl)[:, j]
    assert np.sqrt(np.mean((t1 - t0) ** 2) / np.mean(t1**2)) >= TILT_MADE_SHARE
    assert info["joints"] == ["A1"]  # arm6's vertical axis: the only one the tilt loads this much


# ------------------------------------------------------------------------------------------ e. telescopic stage
def _telescope():
    """B1 vertical at the origin; B2 a horizontal telescopic stage (along -y of the base) out by q2 mm; no masses."""
    doc = {"name": "telescope", "convention": "mdh", "units": {"length": "mm", "angle": "deg"},
           "joints": [{"name": "B1", "type": "revolute", "limits": [-90, 90], "mass": 0.0, "com": [0, 0, 0]},
                      {"name": "B2", "type": "prismatic", "alpha": 90, "limits": [500, 2500], "mass": 0.0,
                       "com": [0, 0, 0]}],
           "tool": [0.0, 0.0, 0.0], "gravity": [0, 0, -9.81]}
    return parse_model(doc)


def test_telescopic_sag_is_beam_theory_and_grows_with_extension_and_payload(seed):
    world = _level(_telescope(), seed)
    rng = np.random.default_rng(seed)
    q = world.sample_joints(30, rng)
    payload = rng.uniform(0.0, 20.0, len(q))
    EI, rho, cg = 5e11, 0.01, 3e-7
    stage = TelescopicSag("B2", EI, tube_kg_per_mm=rho, guide_compliance=cg)
    cols = world.columns(q, payload)
    d = world.displacement(stage, q, cols) @ world.robot.base[:3, :3]
    L, P, w = q[:, 1], payload * 9.81, rho * 9.81
    beam = P * L**3 / (3 * EI) + w * L**4 / (8 * EI)  # payload at the tip, the tube's own weight along L
    guide = cg * (P * L + w * L**2 / 2) / 1000.0 * L  # the root turns by c x the moment there (N*m)
    assert np.allclose(-d[:, 2], beam + guide, rtol=2e-3), (d[:3], (beam + guide)[:3])
    assert np.abs(d[:, :2]).max() < 0.02 * np.abs(d[:, 2]).max()
    # further out and heavier: more sag, at every pose
    longer, heavier = q.copy(), payload + 5.0
    longer[:, 1] = np.minimum(q[:, 1] + 300.0, 2500.0)
    sag = lambda qq, pl: np.linalg.norm(world.displacement(stage, qq, world.columns(qq, pl)), axis=1)  # noqa: E731
    s0 = sag(q, payload)
    assert np.all(sag(longer, payload)[longer[:, 1] > q[:, 1]] > s0[longer[:, 1] > q[:, 1]])
    assert np.all(sag(q, heavier) > s0)
    assert np.abs(world.displacement(stage.scaled(0.0), q, cols)).max() == 0


def test_spray7_telescopic_sag_grows_with_extension(seed):
    world = World(parse_model(spray7()), seed, noise=False)
    q = world.sample_joints(40)
    stage = TelescopicSag("J6", 5e11, tube_kg_per_mm=0.01, guide_compliance=3e-7)
    short, long = q.copy(), q.copy()
    short[:, 5], long[:, 5] = 1700.0, 2300.0
    s = np.linalg.norm(world.displacement(stage, short, world.columns(short, 10.0)), axis=1)
    ln = np.linalg.norm(world.displacement(stage, long, world.columns(long, 10.0)), axis=1)
    assert np.mean(ln > s) >= 0.9 and np.sqrt(np.mean(ln**2)) > 1.5 * np.sqrt(np.mean(s**2)), seed


# ------------------------------------------------------------------------------------------ f. two springs of several
@pytest.mark.parametrize("doc", [spray7, arm6])
def test_only_the_two_springy_joints_deflect(doc, seed):
    world = _exact(doc, seed)
    r = world.robot
    rng = np.random.default_rng(seed)
    q = world.sample_joints(50, rng)
    a, b = (int(j) for j in sorted(rng.choice(np.arange(1, r.n), 2, replace=False)))
    ctx = _ctx(world, q, rng.uniform(0, 10, len(q)))
    ca, cb = (1e-4 / max(np.abs(ctx.loads[:, j]).max(), 1e-300) for j in (a, b))  # 0.1 mrad (0.1 um) at most
    springs = JointSprings((a, b), (ca, cb))
    dq = springs.joint_offset(ctx)
    stiff = np.setdiff1d(np.arange(r.n), [a, b])
    assert np.all(dq[:, stiff] == 0)
    assert np.allclose(dq[:, a], ca * ctx.loads[:, a]) and np.allclose(dq[:, b], cb * ctx.loads[:, b])
    assert springs.joints(r) == [r.names[a], r.names[b]]
    one = world.displacement(JointSpring(a, ca), q) + world.displacement(JointSpring(b, cb), q)
    both = world.displacement(springs, q)
    assert np.abs(both - one).max() < 1e-3 * np.abs(both).max() + 1e-9  # small deflections superpose


# ------------------------------------------------------------------------------------------ every mechanism, sized
@pytest.mark.parametrize("kind", MECHANISMS_34)
@pytest.mark.parametrize("doc", [spray7, arm6])
def test_every_mechanism_has_the_requested_size_and_a_no_effect_draw(doc, kind, seed):
    model = parse_model(doc())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    if doc is arm6 and kind == "telescopic_sag":
        with pytest.raises(ValueError):
            hide(world, kind, 2.0, rng, n=40)
        return
    size = float(rng.uniform(1.0, 6.0))
    info = hide(world, kind, size, rng, n=40, payload_kg=[0.0, 15.0])
    q, cause = info["q"], info["cause"]
    cols = world.columns(q, [0.0, 15.0], info["temperature"])
    got = world.unabsorbed_rms(cause, q, cols)
    assert abs(got / (size * world.noise_rms_mm(q)) - 1) < 1e-6, f"{kind}: seed {seed}"
    assert info["expected"] == EXPECTED[kind]
    camp = world.campaign(q, payload_kg=[0.0, 15.0], temperature=info["temperature"])
    assert np.allclose(camp.truth.displacement, world.displacement(cause, q, cols), atol=1e-9)
    none = World(model, rng=rng)
    info0 = hide(none, kind, 0.0, rng, n=40, payload_kg=[0.0, 15.0])
    cols0 = none.columns(info0["q"], [0.0, 15.0], info0["temperature"])
    assert np.abs(none.displacement(info0["cause"], info0["q"], cols0)).max() < 1e-12, kind
    assert info0["unabsorbed_rms_mm"] == 0.0 and none.causes == [info0["cause"]]


def test_two_joint_springs_both_show(seed):
    model = parse_model(spray7())
    rng = np.random.default_rng(seed)
    world = World(model, rng=rng)
    info = hide(world, "two_joint_springs", 3.0, rng, n=40, payload_kg=[0.0, 10.0])
    springs, q = info["cause"], info["q"]
    cols = world.columns(q, [0.0, 10.0])
    alone = [world.unabsorbed_rms(JointSprings((j,), (c,)), q, cols) for j, c in zip(springs.springs,
                                                                                   springs.compliance)]
    assert len(info["joints"]) == 2 and 0.5 - 1e-9 <= alone[1] / alone[0] <= 2.0 + 1e-9, (alone, seed)

