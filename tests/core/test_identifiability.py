import numpy as np

from calib_core import kinematics as K
from calib_core.identifiability import analyse
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_core.twin import sample_uniform

from .chains import random_chain


def _jacobian(model, q):
    """The nominal point Jacobian at the poses q, one row per coordinate."""
    x = K.nominal_vector(model)
    return K.Chain(model, x, q).jacobian().reshape(-1, len(x))


def _analyse(model, seed, n=120):
    q = sample_uniform(model, n, np.random.default_rng(seed))
    return analyse(_jacobian(model, q), K.parameter_names(model))


def _expected_rank(model):
    """Everett / Hollerbach for point measurements with base and tool identified: 4R + 2P + 3."""
    P = int(model.prismatic.sum())
    return 4 * (model.n_joints - P) + 2 * P + 3


def test_spray_robot_counts_and_parallel_axes(seed):
    model = parse_model(spray7())
    r = _analyse(model, seed).to_dict()
    assert r["rank"] == 27 == _expected_rank(model)
    assert r["n_parameters"] == 7 * 7 + 9
    ident = set(r["identifiable"])
    # J3 and J4 are parallel (alpha_3 = 0): beta enters for them and one of d3/d4 is redundant
    assert "J3.beta" in ident
    redundant = {e["name"]: e["confounded_with"] for e in r["redundant"]}
    assert redundant["J4.d"] == ["J3.d"]
    # the telescopic J6 is collinear with the forearm roll J5: its d and theta duplicate J5's
    assert redundant["J6.d"] == ["J5.d"] and redundant["J6.theta"] == ["J5.theta"]
    # the unknown base pose absorbs the first joint's placement
    assert redundant["J1.d"] == ["base.z"] and redundant["J1.theta"] == ["base.rz"]
    # no beta where consecutive axes are not parallel
    assert not {"J1.beta", "J2.beta", "J4.beta", "J6.beta", "J7.beta"} & ident
    assert np.isfinite(r["condition_number"]) and r["condition_number"] > 1
    assert 0 < r["observability_index"] < 1


def test_arm6_counts(seed):
    model = parse_model(arm6())
    r = _analyse(model, seed).to_dict()
    assert r["rank"] == 27
    assert "A2.beta" in r["identifiable"]  # A2 and A3 are parallel


def test_random_chains_follow_the_counting_rule(seed):
    rng = np.random.default_rng(seed)
    for _ in range(5):
        model = random_chain(rng)
        r = _analyse(model, int(rng.integers(1 << 30)), n=200)
        # a random chain can have more coincidences (e.g. collinear prismatic axes), never fewer
        assert r.rank <= _expected_rank(model), (model.to_dict(), r.to_dict())
        assert len(r.identifiable) + len(r.redundant) + len(r.nonfunctional) == K.G * model.n_joints + 9


def test_nonfunctional_parameters_are_named():
    doc = arm6()
    doc["tool"] = [0.0, 0.0, 0.0]  # the point on the last axis: the last rotation does nothing
    doc["joints"][-1]["d"] = 0.0
    r = _analyse(parse_model(doc), 1).to_dict()
    assert {"A6.theta", "A6.beta"} <= set(r["nonfunctional"])


def test_poor_pose_set_has_worse_conditioning(seed):
    model = parse_model(spray7())
    rich = _analyse(model, seed)
    q = sample_uniform(model, 120, np.random.default_rng(seed), margin=0.45)  # all near mid-range
    poor = analyse(_jacobian(model, q), K.parameter_names(model))
    assert poor.condition_number > 5 * rich.condition_number


def test_structural_analysis_is_cached_per_geometry():
    from calib_core.identifiability import structural

    a, b = structural(parse_model(spray7())), structural(parse_model(spray7()))
    assert a is b and a.rank == 27
    doc = spray7()
    doc["joints"][3]["a"] = 1400.0
    assert structural(parse_model(doc)) is not a


def test_assess_names_what_the_pose_set_lacks(seed):
    from calib_core.identifiability import assess

    model = parse_model(spray7())
    names = K.parameter_names(model)
    q = sample_uniform(model, 120, np.random.default_rng(seed))
    full = assess(model, q, _jacobian(model, q), names)
    assert full.complete and full.unidentifiable == [] and full.warnings() == []
    q[:, 3] = 0.2  # J4 frozen
    poor = assess(model, q, _jacobian(model, q), names)
    d = poor.to_dict()
    assert d["frozen_joints"] == ["J4"] and not d["complete"] and d["unidentifiable"]
    assert len(d["unidentifiable"]) == 27 - d["rank"]
    assert poor.warnings()[0].startswith("J4 never moved")
