"""Issue 34's mechanisms, found blind: the robot, the mechanism's joints or link, its size and the seed are drawn
through the independent world (calib_world), and the diagnosis must name it right (or, for a target re-mounted
mid-campaign, say it is a step in time order at the re-mount), name nothing else physical, and predict fresh poses
with it; a no-effect draw of the same settings names nothing."""
import dataclasses

import numpy as np
import pytest

from calib_core.diagnosis import diagnose
from calib_core.diagnosis.findings import is_named, named_joints
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_world import World, hide

ROBOTS = {"spray7": parse_model(spray7()), "arm6": parse_model(arm6())}
LOAD_CYCLE_KG = {"spray7": [0.0, 10.0, 20.0], "arm6": [0.0, 5.0]}
"""The payload column of load-driven draws, as benchmarks/detection.py measures them."""
SIZES = (1.5, 4.0)
"""Drawn log-uniformly (x the noise RMS of the unabsorbable part); the benchmark measures from 1x."""
TRUTH_LIMIT = 0.8
"""Fresh poses against the world's noise-free truth, RMS over the best 95 % / noise RMS (a pose measured between
the two poses a step fell between may sit on either side of it). The benchmark's median is 0.2-0.3x; a single draw
must stay below this, where the geometry alone leaves 1.5-4x."""


def _draw(kind: str, seed: int, size: float | None = None):
    rng = np.random.default_rng((seed, 34))
    robot = str(rng.choice(sorted(ROBOTS)))
    model = ROBOTS[robot]
    size = float(np.exp(rng.uniform(*np.log(SIZES)))) if size is None else size
    world = World(model, seed)
    q = world.sample_joints(150, rng)
    payload = LOAD_CYCLE_KG[robot] if kind in ("play_load_sign", "two_joint_springs", "tilted_base_spring") else None
    info = hide(world, kind, size, rng, q=q, payload_kg=payload)
    camp = world.campaign(q, payload_kg=payload, temperature=info["temperature"])
    where = f"{kind} on {robot} {info['parameters']} at {size:.2f}x the noise, seed {seed}"
    return model, world, info, camp, payload, where


def _truth_error(world, cal, info, camp, payload, seed) -> float:
    rv = np.random.default_rng((seed, 35))
    q = world.sample_joints(100, rv)
    t = np.linspace(camp.meas.timestamp[0], camp.meas.timestamp[-1], 100)
    cols = dataclasses.replace(world.columns(q, payload, info["temperature"]), timestamp=t,
                               temperature=world.temperature_at(t) if info["temperature"] else None)
    d = np.sort(np.linalg.norm(cal.predict(q, cols) - world.true_points(q, cols), axis=1))[:95]
    return float(np.sqrt(np.mean(d**2))) / world.noise_rms_mm(q)


def _said(d) -> list:
    return [(f["kind"], f["joints"], f.get("significant_joints"), f.get("form")) for f in d.findings]


def test_a_play_whose_side_follows_the_true_load_is_named_for_its_joint(seed):
    """The world's play sits on the flank its true load pushes it to, the model's mass data 15 % off (a few poses'
    model load has the other sign): named a play of that joint and nothing else physical, and fresh poses predicted
    (the best 95 %: a fresh pose within the switch's doubt may sit on either flank, RESULTS 3.17)."""
    model, world, info, camp, payload, where = _draw("play_load_sign", seed)
    d = diagnose(model, camp.meas)
    where += f": said {_said(d)}"
    named = [f for f in d.findings if is_named(f)]
    assert [(f["kind"], f["joints"]) for f in named] == [("backlash", info["joints"])], where
    assert _truth_error(world, d.calibration, info, camp, payload, seed) < TRUTH_LIMIT, where


def test_springs_on_two_joints_are_named_for_those_two(seed):
    """Three drawn worlds; the form fitted is on the two joints (one finding, or one per joint), not a spread
    compliance of five, on at least two. The benchmark names both right in 93-100 % of draws: on spray7 the two
    parallel pitch joints J3, J4 look alike, and a spring on J3 was also given to J4 (seed 2116236994, the same at
    ca02422), so one world in three may miss."""
    failed = []
    for s in (seed, seed + 1, seed + 2):
        model, world, info, camp, payload, where = _draw("two_joint_springs", s)
        d = diagnose(model, camp.meas)
        where += f": said {_said(d)}"
        hidden = set(info["joints"])
        named = [f for f in d.findings if is_named(f)]
        springs = [f for f in named if f["kind"] == "joint_compliance"]
        if not (set().union(*[set(f["joints"]) for f in springs]) == hidden
                and all(set(named_joints(f)[0]) <= hidden for f in named)):
            failed.append(where)
            continue
        assert _truth_error(world, d.calibration, info, camp, payload, s) < TRUTH_LIMIT, where
    assert len(failed) <= 1, failed


def test_a_target_remounted_mid_campaign_is_a_step_of_the_target_in_time_order(seed):
    model, world, info, camp, payload, where = _draw("target_remount", seed)
    d = diagnose(model, camp.meas)
    where += f": said {_said(d)}"
    n = info["notes"]["at_pose"]  # 0-based index in time order of the first pose after the re-mount
    ids = camp.meas.point_ids
    step = [f for f in d.findings if str(f.get("form", "")).startswith("step[target")]
    assert len(step) == 1, where
    assert f"between {ids[n - 1]} and {ids[n]}" in step[0]["evidence"], where
    assert not any(is_named(f) for f in d.findings), where  # no physical name: no thermal drift, no joint cause
    assert "follows nothing: not time order" not in " ".join(d.notes), where  # what is left follows nothing more
    assert _truth_error(world, d.calibration, info, camp, payload, seed) < TRUTH_LIMIT, where


def test_one_link_growing_with_temperature_is_named_for_that_link(seed):
    model, world, info, camp, payload, where = _draw("link_thermal_growth", seed)
    d = diagnose(model, camp.meas)
    where += f": said {_said(d)}"
    named = [f for f in d.findings if is_named(f)]
    assert named and all(f["kind"] == "thermal_drift" for f in named), where
    link = info["parameters"]["link"]
    assert any(f.get("form") == f"thermal_drift[link {link}]" for f in named), where
    assert _truth_error(world, d.calibration, info, camp, payload, seed) < TRUTH_LIMIT, where


def test_a_spring_under_a_tilted_base_is_named_for_its_joint(seed):
    """Gravity 3-10 deg off the model's, a spring on the joint the tilt loads (arm6 A1, a vertical axis the model's
    gravity gives no load; spray7 J2): the compliance is named for that joint (on the vertical axis as the form
    `tilted base`) and predicts fresh poses. (The benchmark also counts a small extra name, a scale error of 2-3 %
    gain, in 1 of 15 draws per robot: not asserted here.)"""
    model, world, info, camp, payload, where = _draw("tilted_base_spring", seed)
    d = diagnose(model, camp.meas)
    where += f": said {_said(d)}"
    springs = [f for f in d.findings if is_named(f) and f["kind"] == "joint_compliance"]
    assert springs and set().union(*[set(named_joints(f)[0]) for f in springs]) == set(info["joints"]), where
    assert _truth_error(world, d.calibration, info, camp, payload, seed) < TRUTH_LIMIT, where


def test_a_sag_under_a_tilted_base_is_named_for_its_link(seed):
    """Gravity 3-10 deg off the model's, a link of spray7 bending under it at 3-5x the noise: part of its sag turns
    sideways. On at least three of five drawn worlds the bending link is named for its link (the form `tilted base`
    takes the sideways part) and fresh poses are predicted within TRUTH_LIMIT. Before that form the sideways part went
    to joint scales, springs and plays on the joints before the link and fresh poses were off by 0.58-0.92x the noise
    at 4x (one world: 4 of 8 seeds failed). Still missed in about one world in nine: J3's link taken for J3's spring
    (seed 36), J5's link left plain with fresh poses beyond the limit (seed 209); not asserted: that nothing else is
    named (RESULTS 3.17). arm6's last link A6 is not met (seeds 23, 30: A4 and A5's compliance beside it, fresh poses
    beyond the limit), so the worlds are spray7's."""
    spray = [s for s in range(seed, seed + 60) if str(np.random.default_rng((s, 34)).choice(sorted(ROBOTS))) == "spray7"]
    failed = []
    for s in spray[:5]:
        size = float(np.random.default_rng((s, 36)).uniform(3.0, 5.0))
        model, world, info, camp, payload, where = _draw("tilted_base_sag", s, size=size)
        d = diagnose(model, camp.meas)
        links = [f for f in d.findings if is_named(f) and f["kind"] == "link_deflection"]
        if not (any(set(named_joints(f)[0]) == set(info["joints"]) for f in links)
                and _truth_error(world, d.calibration, info, camp, payload, s) < TRUTH_LIMIT):
            failed.append(f"{where}: said {_said(d)}")
    assert len(failed) <= 2, failed


TELESCOPE_LIMIT = 0.5
"""A telescopic stage's sag predicted on fresh poses within this (x the noise; the benchmark's 4x draws 0.24-0.41)."""


def _telescope(seed: int, stream: int) -> tuple[str, list[dict], float]:
    """One telescopic world of spray7 drawn at 1.5-4x the noise, diagnosed blind: (what it said, its named findings,
    the final model's error against the truth at fresh poses, x the noise)."""
    rng = np.random.default_rng((seed, stream))
    size = float(np.exp(rng.uniform(*np.log(SIZES))))
    model, world = ROBOTS["spray7"], World(ROBOTS["spray7"], seed)
    q = world.sample_joints(150, rng)
    info = hide(world, "telescopic_sag", size, rng, q=q)
    camp = world.campaign(q, temperature=info["temperature"])
    d = diagnose(model, camp.meas)
    where = f"telescopic sag {info['parameters']} at {size:.2f}x the noise, seed {seed}: said {_said(d)}"
    return where, [f for f in d.findings if is_named(f)], _truth_error(world, d.calibration, info, camp, None, seed)


def test_a_telescopic_stages_sag_is_its_link_and_nothing_else(seed):
    """spray7's telescopic forearm (J6) sags as a tube: it bends under what it carries and its own weight, which
    grows with the length that is out, and it turns in its guide under the bending moment there (the world draws the
    guide at 0.3-1.5x the tube's bending). Two worlds drawn at 1.5-4x the noise: in each a bending link is named and
    nothing else physical, fresh poses within TELESCOPE_LIMIT, and J6's link alone in at least one. Without the
    guide's turn (GuidedLinkDeflection) a play on J6 took what the bending left at 4x (benchmarks.detection, issue
    34: 1 of 15 draws, 0.39x the noise, now 0.24); as the stage's only form, J5's link was named at 1.5-2x in 7 of
    40 seeds (200-239); with it, in 4 of 201 (seeds 1000-1039, 2000-2159 and 983100358, which failed a test run: J5's
    link bending up under its own weight at -9.5 std, the guided stage as good held out), until a link bending the
    wrong way gave way to one that does not (lookalikes._bends_up); then 1 of 160 (seeds 3000-3159: 3054, the
    lateral form of every joint, J5 and J6 significant): one world a run would fail a CI run in about 160."""
    draws = [_telescope(seed, 37), _telescope(seed + 1, 38)]
    for where, named, error in draws:
        assert named and all(f["kind"] == "link_deflection" for f in named), where
        assert error < TELESCOPE_LIMIT, where
    alone = [w for w, named, _ in draws if [(f["kind"], named_joints(f)[0]) for f in named] == [("link_deflection",
                                                                                                 ["J6"])]]
    assert alone, [w for w, _, _ in draws]


@pytest.mark.parametrize("kind", ["play_load_sign", "two_joint_springs", "target_remount", "link_thermal_growth", "tilted_base_spring",
                                  "tilted_base_sag"])
def test_no_mechanism_means_no_finding(kind, seed):
    model, world, info, camp, payload, where = _draw(kind, seed, size=0.0)
    d = diagnose(model, camp.meas)
    assert d.findings == [], f"{where}: said {_said(d)}"
