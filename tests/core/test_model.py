import math

import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.model import ModelError, parse_model
from calib_core.robots import arm6, spray7


def test_reference_robots_parse():
    m = parse_model(spray7())
    assert m.joint_names == ("J1", "J2", "J3", "J4", "J5", "J6", "J7")
    assert list(m.prismatic) == [True, False, False, False, False, True, False]
    assert m.geometry[3, 0] == 1350.0 and math.isclose(m.geometry[1, 1], -math.pi / 2)
    assert parse_model(arm6()).n_joints == 6


def _dh_fk(rows, q, tool):
    """Textbook standard DH product Rz(th) Tz(d) Tx(a) Rx(al), one pose at a time."""
    T = np.eye(4)
    for (a, al, d, th), qi in zip(rows, q):
        c, s, ca, sa = math.cos(th + qi), math.sin(th + qi), math.cos(al), math.sin(al)
        T = T @ np.array([[c, -s * ca, s * sa, a * c], [s, c * ca, -c * sa, a * s], [0, sa, ca, d], [0, 0, 0, 1]])
    return (T @ np.r_[tool, 1.0])[:3]


def test_standard_dh_converts_exactly_to_mdh(seed):
    doc = arm6()
    m = parse_model(doc)
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3, 3, (20, 6))
    rows = [(j["a"], math.radians(j["alpha"]), j["d"], math.radians(j["theta"])) for j in doc["joints"]]
    expected = np.array([_dh_fk(rows, qi, np.array(doc["tool"])) for qi in q])
    got = K.forward(m, K.nominal_vector(m), q)
    assert np.abs(got - expected).max() < 1e-9, f"seed {seed}"


def test_units_metres_and_radians_equal_mm_and_degrees():
    a = spray7()
    b = spray7()
    b["units"] = {"length": "m", "angle": "rad"}
    for j in b["joints"]:
        for k in ("a", "d"):
            j[k] /= 1000.0
        for k in ("alpha", "theta", "beta"):
            j[k] = math.radians(j[k])
        j["limits"] = [v / 1000.0 if j["type"] == "prismatic" else math.radians(v) for v in j["limits"]]
        j["com"] = [v / 1000.0 for v in j["com"]]
    b["tool"] = [v / 1000.0 for v in b["tool"]]
    ma, mb = parse_model(a), parse_model(b)
    assert np.allclose(ma.geometry, mb.geometry) and np.allclose(ma.limits, mb.limits)
    assert np.allclose(ma.tool, mb.tool) and np.allclose(ma.com, mb.com)


def _errors(doc) -> list[dict]:
    """The errors parse_model names for a model it must refuse."""
    with pytest.raises(ModelError) as exc:
        parse_model(doc)
    return exc.value.errors


@pytest.mark.parametrize("mutate, field, text", [
    (lambda d: d.update(joints=[]), "joints", "at least one joint"),
    (lambda d: d["joints"][1].update(name="J1"), "joints[1].name", "duplicate"),
    (lambda d: d["joints"][2].update(limits=[80, -80]), "joints[2].limits", "below upper"),
    (lambda d: d["joints"][3].update(a=float("nan")), "joints[3].a", "finite"),
    (lambda d: d.update(units={"length": "inch", "angle": "deg"}), "units.length", "unknown length unit"),
    (lambda d: d.update(units={"length": "mm", "angle": "grad"}), "units.angle", "unknown angle unit"),
    (lambda d: d["joints"][0].update(type="spherical"), "joints[0].type", "revolute"),
    (lambda d: d.update(tool=[1, 2]), "tool", "3 numbers"),
    (lambda d: d["joints"][4].pop("mass"), "joints", "every joint or for none"),
    (lambda d: d.update(convention="dh") or d["joints"][3].update(beta=1.0), "joints[3].beta", "no beta"),
])
def test_bad_models_are_rejected_with_the_field_named(mutate, field, text):
    doc = spray7()
    mutate(doc)
    errs = _errors(doc)
    assert any(e["field"] == field and text in e["message"] for e in errs), errs


def test_every_problem_is_listed_at_once():
    doc = spray7()
    doc["joints"][1]["name"] = "J1"
    doc["joints"][2]["limits"] = [5, 5]
    doc["units"] = {"length": "furlong"}
    assert len(_errors(doc)) == 3


def test_to_dict_round_trips():
    m = parse_model(spray7())
    m2 = parse_model(m.to_dict())
    assert np.allclose(m.geometry, m2.geometry) and np.allclose(m.limits, m2.limits) and np.allclose(m.tool, m2.tool)
    d = parse_model(arm6())
    assert np.allclose(parse_model(d.to_dict()).geometry, d.geometry)


# Issue 10: plausibility ranges, CSV-safe joint names, PostgreSQL-safe strings, plain words.

def _metres(doc):
    doc["units"] = {"length": "m", "angle": "deg"}
    return doc


@pytest.mark.parametrize("mutate, field, text", [
    (lambda d: d["joints"][3].update(a=1e200), "joints[3].a", "at most 100000 mm"),
    (lambda d: _metres(d)["joints"][3].update(a=1e3), "joints[3].a", "at most 100 m"),
    (lambda d: d["joints"][2].update(d=-1e305), "joints[2].d", "at most 100000 mm"),
    (lambda d: d["joints"][2].update(theta=1e200), "joints[2].theta", "at most 720 deg"),
    (lambda d: d["joints"][1].update(mass=1e308), "joints[1].mass", "between 0 and 100000 kg"),
    (lambda d: d["joints"][1].update(com=[0, 1e200, 0]), "joints[1].com[1]", "at most 100000 mm"),
    (lambda d: d.update(tool=[1e305, 0, 0]), "tool[0]", "at most 100000 mm"),
    (lambda d: d.update(gravity=[0, 0, -9810]), "gravity", "not mm/s^2"),
    (lambda d: d["joints"][0].update(limits=[0, 1e9]), "joints[0].limits[1]", "at most 100000 mm"),
    (lambda d: d["joints"][1].update(limits=[-1e9, 1e9]), "joints[1].limits[0]", "36000 deg"),
])
def test_implausible_values_are_rejected_with_the_range(mutate, field, text):
    doc = spray7()
    mutate(doc)
    errs = _errors(doc)
    assert any(e["field"] == field and text in e["message"] for e in errs), errs


@pytest.mark.parametrize("name", ["point", "x", "y", "z", "timestamp", "temperature", "payload", "payload_kg",
                                  "sigma", "target", "setup", "qw", "qx", "qy", "qz", "tau_J1"])
def test_joint_names_that_are_csv_columns_are_rejected(name):
    doc = spray7()
    doc["joints"][2]["name"] = name
    errs = _errors(doc)
    assert [e["field"] for e in errs] == ["joints[2].name"], errs


@pytest.mark.parametrize("name", ["J,3", 'J"3', "J\n3", "J\r3", "J\x003", "J\t3", " J3", "J3 ", "", "   ",
                                  "#J3", "//J3", "J\u20283", "J" * 101, 3, None, ["J3"]])
def test_joint_names_that_cannot_be_csv_headers_are_rejected(name):
    doc = spray7()
    doc["joints"][2]["name"] = name
    errs = _errors(doc)
    assert [e["field"] for e in errs] == ["joints[2].name"], errs
    assert "unhashable" not in errs[0]["message"] and "'list'" not in errs[0]["message"]


def test_joint_names_with_spaces_dots_dollars_and_case_variants_are_legal():
    doc = spray7()
    for j, name in zip(doc["joints"], ["Joint 1", "J.2", "J$3", "X", "Point", "tau", "J-7"]):
        j["name"] = name
    assert parse_model(doc).joint_names[3] == "X"  # CSV columns match case-sensitively: 'X' is not 'x'


@pytest.mark.parametrize("name, text", [("r" * 201, "at most 200"), ("spray\x007", "NUL"), ("spray\n7", "line breaks")])
def test_robot_names_the_database_cannot_hold_are_rejected(name, text):
    doc = spray7()
    doc["name"] = name
    errs = _errors(doc)
    assert any(e["field"] == "name" and text in e["message"] for e in errs), errs
    doc["name"] = "r" * 200
    assert parse_model(doc).name == "r" * 200


def _nested(depth):
    v = [1]
    for _ in range(depth):
        v = [v]
    return v


def test_nan_nul_and_deep_nesting_anywhere_are_named():
    for extra, field, text in [({"note": float("nan")}, "note", "finite"),
                               ({"joints_extra": [1.0, float("inf")]}, "joints_extra[1]", "finite"),
                               ({"note": "a\x00b"}, "note", "NUL"),
                               ({"note": _nested(25)}, "note", "nested deeper")]:
        errs = _errors({**spray7(), **extra})
        assert any(e["field"].startswith(field) and text in e["message"] for e in errs), errs
    deep = {**spray7(), "note": []}
    node = deep["note"]
    for _ in range(100_000):  # far deeper than Python's recursion limit
        node.append([])
        node = node[0]
    with pytest.raises(ModelError):
        parse_model(deep)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.update(units={"length": ["mm"], "angle": "deg"}), "units.length"),
    (lambda d: d.update(units={"length": "mm", "angle": {"a": 1}}), "units.angle"),
    (lambda d: d.update(convention=["mdh"]), "convention"),
    (lambda d: d["joints"][0].update(type=["prismatic"]), "joints[0].type"),
])
def test_wrong_kinds_are_named_in_plain_words(mutate, field):
    doc = spray7()
    mutate(doc)
    with pytest.raises(ModelError) as exc:
        parse_model(doc)
    assert any(e["field"] == field for e in exc.value.errors), exc.value.errors
    assert "unhashable" not in str(exc.value)


@pytest.mark.parametrize("mutate, field, nearest", [
    (lambda d: d.update(convetion=d.pop("convention", "mdh")), "convetion", "convention"),
    (lambda d: d.update(Joints=[]), "Joints", "joints"),
    (lambda d: d.update(gravty=[0, 0, -9.81]), "gravty", "gravity"),
    (lambda d: d.update(tools=[0, 0, 100]), "tools", "tool"),
    (lambda d: d["units"].update(lenght="m"), "units.lenght", "length"),
    (lambda d: d["joints"][1].update(alpah=3.0), "joints[1].alpah", "alpha"),
    (lambda d: d["joints"][2].update(masss=1.0), "joints[2].masss", "mass"),
    (lambda d: d["joints"][3].update(limit=[-10, 10]), "joints[3].limit", "limits"),
    (lambda d: d["joints"][0].update(parnet="base"), "joints[0].parnet", "parent"),
    (lambda d: d["joints"][4].update(coupling={"J2": 1.0}), "joints[4].coupling", "coupled"),
    (lambda d: d.pop("tool") and d.update(targets=[{"name": "t", "parent": "J7", "xzy": [0, 0, 1]}]),
     "targets[0].xzy", "xyz"),
])
def test_a_misspelt_key_is_refused_with_the_nearest_valid_one(mutate, field, nearest):
    """A typo must never calibrate another robot (issue 31: "convetion": "dh" was read as MD-H; "alpah" made alpha
    0): every key at every level is one the contract or the docs define, else a 422 naming it and the nearest."""
    doc = spray7()
    mutate(doc)
    errs = _errors(doc)
    assert any(e["field"] == field and f"did you mean '{nearest}'" in e["message"] for e in errs), errs


def test_the_users_own_data_goes_under_meta():
    doc = spray7()
    doc["meta"] = {"cell": "paint line 2", "serial": 4711}
    doc["joints"][0]["meta"] = {"drive": "SEW"}
    assert parse_model(doc).n_joints == len(doc["joints"])
    doc["colour"] = "red"
    assert [e["field"] for e in _errors(doc)] == ["colour"]


def test_unknown_keys_get_a_bounded_answer():
    """An attacker's document of 10,000 unknown keys, one of them 5,000 characters long: at most 50 problems, each
    key echoed to 80 characters."""
    doc = spray7()
    doc["k" * 5000] = 1
    doc.update({f"junk{i}": i for i in range(10_000)})
    errs = _errors(doc)
    assert len(errs) <= 50 and max(len(e["field"]) for e in errs) <= 80, (len(errs), errs[0]["field"][:90])
