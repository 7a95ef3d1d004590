"""URDF in and out (contract section 5): URDF -> model -> URDF -> model keeps the kinematics to 1e-9, checked
against plain 4x4 products of the URDF origins (mimic joints included) and of the model's own rows, both computed
here (no MD-H fold, no calib_core.kinematics involved): serial chains in the MD-H form, trees with fixed and mimic
joints in the xyz form, calibrated models exported with their identified geometry."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.frames import mdh_transform
from calib_core.model import LENGTH_TO_MM, parse_model
from calib_core.urdf import CONTINUOUS_LIMIT_RAD, UrdfError, parse_urdf
from calib_core.urdf_write import calibrated_model_dict, to_urdf

HILTI = Path(__file__).resolve().parents[3] / "shared" / "datasets" / "hilti_trailblazer" / "trailblazer.urdf"

# A UR-like arm on a linear track: fixed joints (mount, flange, tool), axes that are not z (y, -y, x and a
# skew unit vector), a continuous wrist, a prismatic track, an elbow tilted by 1e-7 rad (nearly parallel
# axes: Hayati beta), inertials with offset origins, a sensor fixed to the forearm (lumped into its body), and
# a gripper finger off the chain that mimics another joint.
UR_LIKE = """<?xml version="1.0" encoding="UTF-8"?>
<robot name="ur_like">
  <link name="world"/>
  <link name="track"><inertial><origin xyz="0 0 0.05"/><mass value="20"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="carriage"><inertial><origin xyz="0.01 0 0.02" rpy="0.1 0 0"/><mass value="8"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="base_link"/>
  <link name="shoulder_link"><inertial><origin xyz="0 0 0.02"/><mass value="3.7"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="upper_arm_link"><inertial><origin xyz="-0.2125 0 0.138"/><mass value="8.393"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="forearm_link"><inertial><origin xyz="-0.196 0 0.0165"/><mass value="2.275"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="forearm_sensor"><inertial><origin xyz="0 0.01 0"/><mass value="0.4"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="wrist_1_link"><inertial><origin xyz="0 0.01 0"/><mass value="1.219"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="wrist_2_link"/>
  <link name="wrist_3_link"><inertial><origin xyz="0 0 -0.0229"/><mass value="0.1879"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="flange"/>
  <link name="tool0"/>
  <link name="finger_left"/>
  <link name="finger_right"/>

  <joint name="world_to_track" type="fixed">
    <parent link="world"/><child link="track"/><origin xyz="0.3 -0.2 0.1" rpy="0 0 0.4"/>
  </joint>
  <joint name="track_joint" type="prismatic">
    <parent link="track"/><child link="carriage"/><origin xyz="0 0 0.12"/>
    <axis xyz="1 0 0"/><limit lower="-0.5" upper="1.5" effort="500" velocity="1"/>
  </joint>
  <joint name="carriage_to_base" type="fixed">
    <parent link="carriage"/><child link="base_link"/><origin xyz="0 0 0.03" rpy="0 0 3.141592653589793"/>
  </joint>
  <joint name="shoulder_pan_joint" type="revolute">
    <parent link="base_link"/><child link="shoulder_link"/><origin xyz="0 0 0.1625" rpy="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-6.283" upper="6.283" effort="150" velocity="3.14"/>
  </joint>
  <joint name="shoulder_lift_joint" type="revolute">
    <parent link="shoulder_link"/><child link="upper_arm_link"/><origin xyz="0 0 0" rpy="1.570796327 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-3.14" upper="3.14" effort="150" velocity="3.14"/>
  </joint>
  <joint name="elbow_joint" type="revolute">
    <parent link="upper_arm_link"/><child link="forearm_link"/><origin xyz="-0.425 0 0" rpy="1e-7 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-3.14" upper="3.14" effort="150" velocity="3.14"/>
  </joint>
  <joint name="forearm_sensor_mount" type="fixed">
    <parent link="forearm_link"/><child link="forearm_sensor"/><origin xyz="-0.1 0.05 0" rpy="0 0.3 0"/>
  </joint>
  <joint name="wrist_1_joint" type="revolute">
    <parent link="forearm_link"/><child link="wrist_1_link"/><origin xyz="-0.3922 0 0.1333" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/><limit lower="-3.14" upper="3.14" effort="28" velocity="6.28"/>
  </joint>
  <joint name="wrist_2_joint" type="revolute">
    <parent link="wrist_1_link"/><child link="wrist_2_link"/><origin xyz="0 -0.0997 0" rpy="0.2 -0.1 0.05"/>
    <axis xyz="0.6 0 0.8"/><limit lower="-3.14" upper="3.14" effort="28" velocity="6.28"/>
  </joint>
  <joint name="wrist_3_joint" type="continuous">
    <parent link="wrist_2_link"/><child link="wrist_3_link"/>
    <origin xyz="0 0 0.0996" rpy="1.570796327 3.141592653589793 3.141592653589793"/>
    <axis xyz="1 0 0"/><limit effort="28" velocity="6.28"/>
  </joint>
  <joint name="wrist_3_flange" type="fixed">
    <parent link="wrist_3_link"/><child link="flange"/><origin xyz="0 0 0" rpy="0 -1.570796327 -1.570796327"/>
  </joint>
  <joint name="flange_tool0" type="fixed">
    <parent link="flange"/><child link="tool0"/><origin xyz="0.05 0.01 0.12" rpy="1.570796327 0 1.570796327"/>
  </joint>
  <joint name="finger_left_joint" type="prismatic">
    <parent link="tool0"/><child link="finger_left"/><origin xyz="0 0.02 0"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
  </joint>
  <joint name="finger_right_joint" type="prismatic">
    <parent link="tool0"/><child link="finger_right"/><origin xyz="0 -0.02 0"/>
    <axis xyz="0 -1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
    <mimic joint="finger_left_joint" multiplier="1" offset="0"/>
  </joint>
</robot>
"""


# --- an independent evaluator: the URDF's own 4x4 products (Rodrigues for the axis rotations) ------------

def _rpy(r, p, y):
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _hom(rpy, xyz) -> np.ndarray:
    """The 4x4 of a URDF origin (rpy rad, xyz m)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rpy(*rpy), xyz
    return T


def _joint_value(by_name: dict, name: str, q: dict[str, float], depth: int = 0) -> float:
    """A joint's value (m, rad): given in q, or its <mimic> (multiplier * source + offset), recursively."""
    if name in q:
        return q[name]
    mim = by_name[name].find("mimic")
    assert mim is not None and depth < 10, f"no value for joint {name!r}"
    return (float(mim.get("multiplier", "1")) * _joint_value(by_name, mim.get("joint"), q, depth + 1)
            + float(mim.get("offset", "0")))


def urdf_pose(text: str, link: str, q: dict[str, float], base: str | None = None) -> np.ndarray:
    """The 4x4 pose (m) of `link` in `base` (default: the root) from the URDF text alone; mimic joints follow."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    by_name = {j.get("name"): j for j in root.findall("joint")}
    chain, ln = [], link
    while ln in by_child and ln != base:
        j = by_child[ln]
        chain.append(j)
        ln = j.find("parent").get("link")
    T = np.eye(4)
    for j in reversed(chain):
        o = j.find("origin")
        xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
        rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        O = _hom(rpy, xyz)
        M = np.eye(4)
        if j.get("type") != "fixed":
            ax = j.find("axis")
            k = np.array([float(v) for v in (ax.get("xyz") if ax is not None else "1 0 0").split()])
            M = _motion(k, _joint_value(by_name, j.get("name"), q), j.get("type") == "prismatic")
        T = T @ O @ M
    return T


def _motion(k, v: float, prismatic: bool) -> np.ndarray:
    """Translation along / rotation about the axis k by v (Rodrigues)."""
    k = np.asarray(k, float) / np.linalg.norm(k)
    M = np.eye(4)
    if prismatic:
        M[:3, 3] = k * v
    else:
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        M[:3, :3] = np.eye(3) + math.sin(v) * Kx + (1 - math.cos(v)) * Kx @ Kx
    return M


def xyz_model_poses(doc: dict, q: dict[str, float]) -> dict[str, np.ndarray]:
    """Each target's 4x4 pose (m) in the base from a contract model of xyz/rpy/axis rows, read row by row here:
    origin Trans(xyz) Rz Ry Rx from the parent row's frame, then motion about / along `axis`; coupled rows
    follow their sources; q holds the actuated joints in the model's units."""
    ls = 1.0 if doc["units"]["length"] == "m" else 1e-3
    an = 1.0 if doc["units"]["angle"] == "rad" else math.pi / 180.0
    frames: dict[str, np.ndarray] = {}
    values: dict[str, float] = {}
    prev = None
    for row in doc["joints"]:
        name, kind = row["name"], row["type"]
        parent = row.get("parent", prev if prev is not None else "base")
        prev = name
        if kind != "fixed":
            if "coupled" in row:
                c = dict(row["coupled"])
                values[name] = c.pop("offset", 0.0) + sum(k * values[src] for src, k in c.items())
            else:
                values[name] = q[name]
        P = np.eye(4) if parent == "base" else frames[parent]
        O = _hom(np.array(row.get("rpy", [0, 0, 0])) * an, np.array(row.get("xyz", [0, 0, 0])) * ls)
        M = np.eye(4) if kind == "fixed" else _motion(row.get("axis", [0, 0, 1]), values[name] *
                                                      (ls if kind == "prismatic" else an), kind == "prismatic")
        frames[name] = P @ O @ M
    return {t["name"]: frames[t["parent"]] @ _hom([0, 0, 0], np.array(t["xyz"]) * ls) for t in doc["targets"]}


def actuated(doc: dict) -> list[str]:
    return [j["name"] for j in doc["joints"] if j["type"] != "fixed" and "coupled" not in j]


def random_actuated(doc: dict, n: int, seed: int = 0) -> list[dict[str, float]]:
    """n random values of the actuated joints within their limits (unlimited revolute joints: one turn)."""
    an = 1.0 if doc["units"]["angle"] == "rad" else math.pi / 180.0
    rows = {j["name"]: j for j in doc["joints"]}
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        out.append({k: float(rng.uniform(*rows[k].get("limits", (-math.pi / an, math.pi / an))))
                    for k in actuated(doc)})
    return out


def model_frames(doc: dict, q: np.ndarray) -> list[np.ndarray]:
    """MD-H joint frames (m) of a contract model in m / rad for one joint vector, 4x4 products of the rows."""
    T, out = np.eye(4), []
    for row, v in zip(doc["joints"], q):
        pri = row["type"] == "prismatic"
        T = T @ mdh_transform(row["a"], row["alpha"], row["d"] + (v if pri else 0.0),
                              row["theta"] + (0.0 if pri else v), row["beta"])
        out.append(T)
    return out


def target_pose(doc: dict, q: np.ndarray) -> np.ndarray:
    """The target link's pose in the URDF base link: base (extension) @ MD-H chain @ tool frame (extension)."""
    e = doc["urdf"]
    return _hom(e["base_rpy"], e["base_xyz"]) @ model_frames(doc, q)[-1] @ _hom(e["tool_rpy"], doc["tool"])


def random_q(doc: dict, n: int, seed: int = 0) -> np.ndarray:
    lim = np.array([j["limits"] for j in doc["joints"]], float)
    return lim[:, 0] + (lim[:, 1] - lim[:, 0]) * np.random.default_rng(seed).random((n, len(lim)))


def production_fk(doc: dict, q: np.ndarray) -> np.ndarray:
    """The tool point (model units) by calib_core.kinematics (internal mm), base pose zero."""
    m = parse_model(doc)
    ls = 1000.0 if doc["units"]["length"] == "m" else 1.0
    return K.forward(m, K.nominal_vector(m), q * m.joint_scale()) / ls


def check_round_trip(text: str, base: str | None, target: str, n_joints: int, seed: int = 0):
    m1 = parse_urdf(text, base, target)
    assert len(m1["joints"]) == n_joints and m1["units"] == {"length": "m", "angle": "rad"}
    u2 = to_urdf(m1)
    m2 = parse_urdf(u2)  # the exported URDF is a single chain: defaults find base and target
    assert m2["urdf"]["base_link"] == m1["urdf"]["base_link"] and m2["urdf"]["target_link"] == target
    u3 = to_urdf(m2)
    q = random_q(m1, 40, seed)
    names = [j["name"] for j in m1["joints"]]
    truth_pts = []
    for qi in q:
        qd = dict(zip(names, qi))
        truth = urdf_pose(text, target, qd, base)  # the original URDF's own products
        truth_pts.append(truth[:3, 3])
        for doc in (m1, m2):
            assert np.abs(target_pose(doc, qi) - truth).max() < 1e-9  # full frame
        for u in (u2, u3):  # the exported URDFs' own products: same target frame
            assert np.abs(urdf_pose(u, target, qd) - truth).max() < 1e-9
    # the production kinematics (mm internally) give the same point, in the MD-H base
    p1, p2 = production_fk(m1, q), production_fk(m2, q)
    assert np.abs(p1 - p2).max() < 1e-9
    B = _hom(m1["urdf"]["base_rpy"], m1["urdf"]["base_xyz"])
    truth_pts = np.array(truth_pts)
    assert np.abs((p1 @ B[:3, :3].T + B[:3, 3]) - truth_pts).max() < 1e-9
    return m1, m2


def test_ur_like_round_trip_keeps_point_and_frame():
    m1, m2 = check_round_trip(UR_LIKE, None, "tool0", 7)
    assert [j["name"] for j in m1["joints"]] == ["track_joint", "shoulder_pan_joint", "shoulder_lift_joint",
                                                 "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    types = [j["type"] for j in m1["joints"]]
    assert types[0] == "prismatic" and set(types[1:]) == {"revolute"}
    assert m1["joints"][0]["limits"] == [-0.5, 1.5]
    assert m1["joints"][6]["limits"] == [-CONTINUOUS_LIMIT_RAD, CONTINUOUS_LIMIT_RAD]
    assert m1["urdf"]["continuous"] == ["wrist_3_joint"] and "continuous" in to_urdf(m1)
    assert any(abs(j["beta"]) > 0 for j in m1["joints"])  # the tilted elbow: Hayati
    # gravity is -z of the URDF root, in the MD-H base
    B = _rpy(*m1["urdf"]["base_rpy"])
    assert np.allclose(B @ np.array(m1["gravity"]), [0, 0, -9.81], atol=1e-12)
    # the rows survive the round trip (same fold of the same axes)
    for a, b in zip(m1["joints"], m2["joints"]):
        for p in ("a", "alpha", "d", "theta", "beta", "mass"):
            assert abs(a[p] - b[p]) < 1e-9, (a["name"], p)


def test_masses_are_the_bodies_moved_by_each_joint():
    m = parse_urdf(UR_LIKE, target="tool0")
    masses = [j["mass"] for j in m["joints"]]
    # carriage (track joint); shoulder; upper arm; forearm + its fixed sensor; wrist 1; wrist 2 (none); wrist 3
    assert masses == pytest.approx([8.0, 3.7, 8.393, 2.275 + 0.4, 1.219, 0.0, 0.1879])
    names = [j["name"] for j in m["joints"]]
    child = {"track_joint": ["carriage"], "elbow_joint": ["forearm_link", "forearm_sensor"],
             "wrist_3_joint": ["wrist_3_link"]}
    coms = {"carriage": [0.01, 0, 0.02], "forearm_link": [-0.196, 0, 0.0165], "forearm_sensor": [0, 0.01, 0],
            "wrist_3_link": [0, 0, -0.0229]}
    mass = {"carriage": 8.0, "forearm_link": 2.275, "forearm_sensor": 0.4, "wrist_3_link": 0.1879}
    B = _hom(m["urdf"]["base_rpy"], m["urdf"]["base_xyz"])
    for qi in random_q(m, 5, 3):
        qd = dict(zip(names, qi))
        frames = model_frames(m, qi)
        for jn, body in child.items():
            k = names.index(jn)
            got = (B @ frames[k] @ np.r_[m["joints"][k]["com"], 1.0])[:3]
            want = sum(mass[ln] * (urdf_pose(UR_LIKE, ln, qd) @ np.r_[coms[ln], 1.0])[:3] for ln in body)
            want = want / sum(mass[ln] for ln in body)
            assert np.abs(got - want).max() < 1e-12, jn


def test_units_mm_deg_describe_the_same_robot():
    m = parse_urdf(UR_LIKE, target="tool0")
    mm = parse_urdf(UR_LIKE, target="tool0", length_unit="mm", angle_unit="deg")
    assert mm["units"] == {"length": "mm", "angle": "deg"}
    q = random_q(m, 10, 1)
    qmm = q * np.where([j["type"] == "prismatic" for j in m["joints"]], 1000.0, 180.0 / math.pi)
    assert np.abs(production_fk(m, q) * 1000.0 - production_fk(mm, qmm)).max() < 1e-9
    assert mm["joints"][0]["com"] == pytest.approx(np.array(m["joints"][0]["com"]) * 1000.0)
    u = parse_urdf(to_urdf(mm))  # back in m / rad: same robot
    assert np.abs(production_fk(u, q) - production_fk(m, q)).max() < 1e-12


def test_subchain_and_defaults():
    sub = parse_urdf(UR_LIKE, base="base_link", target="wrist_3_link")
    assert [j["name"] for j in sub["joints"]][0] == "shoulder_pan_joint" and len(sub["joints"]) == 6
    with pytest.raises(UrdfError, match="leaf links") as e:
        parse_urdf(UR_LIKE)
    assert {"finger_left", "finger_right", "forearm_sensor"} <= set(e.value.errors[0]["value"])
    with pytest.raises(UrdfError, match="finger_right_joint.*mimics.*finger_left_joint.*xyz form"):
        parse_urdf(UR_LIKE, target="finger_right", form="mdh")
    with pytest.raises(UrdfError, match="MD-H form takes one target"):
        parse_urdf(UR_LIKE, target="finger_left,finger_right", form="mdh")
    # a mimic joint on the way: the xyz form, the finger it mimics taken in as a branch (its CSV column)
    fr = parse_urdf(UR_LIKE, target="finger_right")
    rows = {j["name"]: j for j in fr["joints"]}
    assert rows["finger_right_joint"]["coupled"] == {"finger_left_joint": 1.0}
    assert rows["finger_right_joint"]["parent"] == "flange_tool0" and "finger_left_joint" in rows
    assert fr["targets"] == [{"name": "finger_right", "parent": "finger_right_joint", "xyz": [0.0, 0.0, 0.0]}]
    assert parse_model(fr).actuated_names[-1] == "finger_left_joint"
    with pytest.raises(UrdfError, match="not below the base link"):
        parse_urdf(UR_LIKE, base="forearm_link", target="shoulder_link")
    with pytest.raises(UrdfError, match="no link 'nowhere'"):
        parse_urdf(UR_LIKE, target="nowhere")


@pytest.mark.parametrize("old, new, field, words", [
    ('xyz="-0.425 0 0"', 'xyz="-0.425 0"', "joint[@name='elbow_joint']/origin/@xyz", "needs 3 numbers"),
    ('xyz="-0.425 0 0"', 'xyz="-0.425 abc 0"', "joint[@name='elbow_joint']/origin/@xyz", "'abc' is not a finite"),
    ('xyz="-0.425 0 0"', 'xyz="-0.425 nan 0"', "joint[@name='elbow_joint']/origin/@xyz", "not a finite"),
    ('xyz="-0.425 0 0"', 'xyz="-0.425 1_0 0"', "joint[@name='elbow_joint']/origin/@xyz", "not a finite"),
    ('<axis xyz="0 -1 0"/>', '<axis xyz="0 0 0"/>', "joint[@name='wrist_1_joint']/axis/@xyz", "zero vector"),
    ('name="elbow_joint" type="revolute"', 'name="elbow_joint" type="hinge"', "joint[@name='elbow_joint']/@type",
     "unknown joint type"),
    ('lower="-0.5" upper="1.5"', 'lower="1.5" upper="-0.5"', "joint[@name='track_joint']/limit", "below the upper"),
    ('<limit lower="-0.5" upper="1.5" effort="500" velocity="1"/>', "", "joint[@name='track_joint']/limit",
     "needs <limit"),
    ('<child link="forearm_link"/>', '<child link="forearm"/>', "joint[@name='elbow_joint']/child/@link",
     "no <link> of that name"),
    ('<mass value="2.275"/>', '<mass value="-2.275"/>', "link[@name='forearm_link']/inertial/mass/@value",
     "must not be negative"),
    ('name="track_joint" type="prismatic"', 'name="track_joint" type="floating"', "joint[@name='track_joint']/@type",
     "not supported"),
])
def test_bad_urdf_names_the_element(old, new, field, words):
    assert old in UR_LIKE
    with pytest.raises(UrdfError) as e:
        parse_urdf(UR_LIKE.replace(old, new, 1), target="tool0")
    assert isinstance(e.value, ValueError)
    assert any(err["field"] == field and words in err["message"] for err in e.value.errors), e.value.errors


def test_refuses_entities_and_garbage():
    bomb = ('<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;">]>'
            '<robot name="&lol2;"><link name="a"/></robot>')
    with pytest.raises(UrdfError, match="DOCTYPE"):
        parse_urdf(bomb)
    with pytest.raises(UrdfError, match="not well-formed") as e:
        parse_urdf("<robot><link name='a'></robot>")
    assert e.value.errors[0]["value"].startswith("line 1")
    with pytest.raises(UrdfError, match="<robot>"):
        parse_urdf("<html/>")
    with pytest.raises(UrdfError, match="UTF-8"):
        parse_urdf("<robot/>".encode("utf-16"))
    with pytest.raises(UrdfError, match="no revolute"):
        parse_urdf('<robot name="r"><link name="a"/><link name="b"/><joint name="f" type="fixed">'
                   '<parent link="a"/><child link="b"/></joint></robot>')
    assert parse_urdf(UR_LIKE.encode(), target="tool0")["name"] == "ur_like"


def test_calibrated_export_lists_effects():
    from calib_core.urdf_write import calibrated_model_dict

    m = parse_urdf(UR_LIKE, target="tool0")
    model = parse_model(m)
    x = K.nominal_vector(model)
    x[3] += 0.001  # a calibrated joint offset on the first row
    x[K.G * 2 + 4] += 0.005  # the elbow axis tilted by 5 mrad (beta) off its parallel neighbour: Hayati, no far normal
    x[K.G * 4 + 2] += 0.002  # and a length
    state = {"x": x.tolist(), "R0": np.eye(3).tolist(),
             "effects": [{"kind": "joint_compliance", "joints": [model.joint_names.index("shoulder_lift_joint")],
                          "values": [1e-6]}]}  # effect states store joint positions
    cal = calibrated_model_dict(model, state, m)
    assert cal["urdf"] == m["urdf"] and cal["calibration"]["effects"][0]["kind"] == "joint_compliance"
    text = to_urdf(cal)
    assert "joint_compliance on shoulder_lift_joint" in text
    back = parse_urdf(text)
    assert max(abs(j["d"]) for j in back["joints"]) < 1.0
    q = random_q(m, 10, 2)
    x_mm = parse_model(back)
    assert np.abs(K.forward(x_mm, K.nominal_vector(x_mm), q * x_mm.joint_scale())
                  - K.forward(model, x, q * model.joint_scale())).max() < 1e-9


# --- trees, fixed and mimic joints: the xyz form ---------------------------------------------------------------

# A torso on a lift with two arms and a head: a continuous wrist, skew and negative axes, fixed flanges, an IMU
# fixed to the torso (lumped into its body), a right elbow that mimics the left one (another branch), a head pan
# (revolute) that mimics a drive on a side branch that carries nothing measured (prismatic: rad per m), and a
# mimic of a mimic in the fingers (resolved to the first finger).
TREE = """<?xml version="1.0"?>
<robot name="tree">
  <link name="world"/>
  <link name="torso"><inertial><origin xyz="0 0 0.3"/><mass value="12"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="imu"><inertial><origin xyz="0.01 0 0"/><mass value="0.5"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="l_upper"><inertial><origin xyz="0.15 0 0" rpy="0.2 0 0"/><mass value="3"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="l_fore"/>
  <link name="l_hand"><inertial><origin xyz="0 0 0.02"/><mass value="1"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="l_tool"/>
  <link name="r_upper"/>
  <link name="r_fore"><inertial><origin xyz="0.1 0.01 0"/><mass value="2"/>
    <inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="r_tool"/>
  <link name="drive"/>
  <link name="head"/>
  <link name="camera"/>
  <link name="finger_a"/>
  <link name="finger_b"/>
  <link name="finger_c"/>
  <joint name="torso_lift" type="prismatic">
    <parent link="world"/><child link="torso"/><origin xyz="0.1 0 0.4" rpy="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="0" upper="0.5" effort="800" velocity="0.1"/>
  </joint>
  <joint name="imu_mount" type="fixed">
    <parent link="torso"/><child link="imu"/><origin xyz="0 0.1 0.2" rpy="0 0 1.5707963267948966"/>
  </joint>
  <joint name="l_shoulder" type="revolute">
    <parent link="torso"/><child link="l_upper"/><origin xyz="0 0.2 0.5" rpy="-1.2 0.1 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="100" velocity="2"/>
  </joint>
  <joint name="l_elbow" type="revolute">
    <parent link="l_upper"/><child link="l_fore"/><origin xyz="0.3 0 0" rpy="0 0 0.2"/>
    <axis xyz="0.6 0 -0.8"/><limit lower="-2.5" upper="2.5" effort="60" velocity="2"/>
  </joint>
  <joint name="l_wrist" type="continuous">
    <parent link="l_fore"/><child link="l_hand"/><origin xyz="0.25 0.01 0" rpy="0.3 -0.2 0.1"/>
    <axis xyz="1 0 0"/><limit effort="20" velocity="4"/>
  </joint>
  <joint name="l_flange" type="fixed">
    <parent link="l_hand"/><child link="l_tool"/><origin xyz="0.05 0 0.1" rpy="1.5707963267948966 0 0"/>
  </joint>
  <joint name="r_shoulder" type="revolute">
    <parent link="torso"/><child link="r_upper"/><origin xyz="0 -0.2 0.5" rpy="1.2 0.1 0"/>
    <axis xyz="0 -1 0"/><limit lower="-2" upper="2" effort="100" velocity="2"/>
  </joint>
  <joint name="r_elbow" type="revolute">
    <parent link="r_upper"/><child link="r_fore"/><origin xyz="0.3 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2.5" upper="2.5" effort="60" velocity="2"/>
    <mimic joint="l_elbow" multiplier="-1" offset="0.2"/>
  </joint>
  <joint name="r_flange" type="fixed">
    <parent link="r_fore"/><child link="r_tool"/><origin xyz="0.28 0 0.02" rpy="0 0.4 0"/>
  </joint>
  <joint name="drive_joint" type="prismatic">
    <parent link="torso"/><child link="drive"/><origin xyz="0 0 0.05"/>
    <axis xyz="1 0 0"/><limit lower="-0.05" upper="0.05" effort="10" velocity="0.1"/>
  </joint>
  <joint name="head_pan" type="revolute">
    <parent link="torso"/><child link="head"/><origin xyz="0 0 0.7"/>
    <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="5" velocity="1"/>
    <mimic joint="drive_joint" multiplier="10" offset="0.1"/>
  </joint>
  <joint name="camera_mount" type="fixed">
    <parent link="head"/><child link="camera"/><origin xyz="0.08 0 0.05" rpy="0 0.3 0"/>
  </joint>
  <joint name="finger_a_joint" type="prismatic">
    <parent link="l_tool"/><child link="finger_a"/><origin xyz="0 0.02 0"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
  </joint>
  <joint name="finger_b_joint" type="prismatic">
    <parent link="finger_a"/><child link="finger_b"/><origin xyz="0 0 0.01"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
    <mimic joint="finger_a_joint"/>
  </joint>
  <joint name="finger_c_joint" type="prismatic">
    <parent link="finger_b"/><child link="finger_c"/><origin xyz="0 0 0.01"/>
    <axis xyz="0 0 1"/><limit lower="0" upper="0.04" effort="10" velocity="0.1"/>
    <mimic joint="finger_b_joint" multiplier="0.5" offset="0.01"/>
  </joint>
</robot>
"""
TREE_TARGETS = "finger_c,r_tool,camera"


def production_points(doc: dict, qs: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """Each target's points (model units) by calib_core.kinematics for the actuated values qs, base pose zero."""
    m = parse_model(doc)
    ls = LENGTH_TO_MM[m.length_unit]
    q = m.expand_joints(np.array([[qi[k] for k in m.actuated_names] for qi in qs]) * m.joint_scale()[m.actuated])
    out = {}
    for t, name in enumerate(m.target_names):
        labels = K.Labels(np.full(len(qs), t), np.zeros(len(qs), int))
        out[name] = K.forward(m, K.nominal_vector(m), q, labels=labels) / ls
    return out


def check_tree_round_trip(text: str, base: str | None, targets: str, seed: int = 0, **kw):
    """URDF -> model (xyz form) -> URDF -> model -> URDF: every target's full frame equals the original URDF's
    products to 1e-9 (m) at random joint values, by the model's own rows, by the exported URDFs' products, and
    (point) by the production kinematics."""
    kw = {"form": "xyz", **kw}
    m1 = parse_urdf(text, base, targets, **kw)
    assert m1["urdf"]["form"] == "xyz"
    u2 = to_urdf(m1)
    m2 = parse_urdf(u2, base, targets, **kw)
    u3 = to_urdf(m2)
    assert [j["name"] for j in m2["joints"]] == [j["name"] for j in m1["joints"]]
    assert m2["urdf"]["links"] == m1["urdf"]["links"] and m2["urdf"]["base_link"] == m1["urdf"]["base_link"]
    base_link = m1["urdf"]["base_link"]
    ls = 1.0 if m1["units"]["length"] == "m" else 1e-3
    an = 1.0 if m1["units"]["angle"] == "rad" else math.pi / 180.0
    rows = {j["name"]: j for j in m1["joints"]}
    qs = random_actuated(m1, 30, seed)
    prod = {k: production_points(d, qs) for k, d in (("m1", m1), ("m2", m2))}
    for i, qm in enumerate(qs):
        qu = {k: v * (ls if rows[k]["type"] == "prismatic" else an) for k, v in qm.items()}  # URDF m / rad
        poses = [xyz_model_poses(m1, qm), xyz_model_poses(m2, qm)]
        for t in targets.split(","):
            truth = urdf_pose(text, t, qu, base_link)
            for P in poses:
                assert np.abs(P[t] - truth).max() < 1e-9, t
            for u in (u2, u3):
                assert np.abs(urdf_pose(u, t, qu, base_link) - truth).max() < 1e-9, t
            for p in prod.values():
                assert np.abs(p[t][i] * ls - truth[:3, 3]).max() < 1e-9, t
    return m1, m2, u2


def test_tree_with_mimic_joints_round_trips():
    m1, _, u2 = check_tree_round_trip(TREE, None, TREE_TARGETS)
    rows = {j["name"]: j for j in m1["joints"]}
    names = [j["name"] for j in m1["joints"]]
    # one row per joint on the ways to the targets, plus the drive the head follows; not the IMU mount
    assert set(names) == {"torso_lift", "l_shoulder", "l_elbow", "l_wrist", "l_flange", "finger_a_joint",
                          "finger_b_joint", "finger_c_joint", "r_shoulder", "r_elbow", "r_flange", "drive_joint",
                          "head_pan", "camera_mount"}
    assert all(names.index(rows[n].get("parent", names[names.index(n) - 1] if names.index(n) else "base"))
               < names.index(n) for n in names if rows[n].get("parent", "base") != "base")
    assert rows["r_shoulder"]["parent"] == "torso_lift" and rows["head_pan"]["parent"] == "torso_lift"
    assert rows["l_flange"]["type"] == "fixed" and "axis" not in rows["l_flange"]
    assert rows["l_wrist"]["type"] == "revolute" and "limits" not in rows["l_wrist"]  # continuous
    assert rows["l_elbow"]["axis"] == [0.6, 0.0, -0.8] and rows["torso_lift"]["limits"] == [0.0, 0.5]
    assert rows["r_elbow"]["coupled"] == {"l_elbow": -1.0, "offset": 0.2}
    assert rows["head_pan"]["coupled"] == {"drive_joint": 10.0, "offset": 0.1}
    assert rows["finger_b_joint"]["coupled"] == {"finger_a_joint": 1.0}
    assert rows["finger_c_joint"]["coupled"] == {"finger_a_joint": 0.5, "offset": 0.01}  # mimic of a mimic
    assert m1["targets"] == [{"name": t, "parent": p, "xyz": [0.0, 0.0, 0.0]} for t, p in
                             (("finger_c", "finger_c_joint"), ("r_tool", "r_flange"), ("camera", "camera_mount"))]
    assert parse_model(m1).actuated_names == ("torso_lift", "l_shoulder", "l_elbow", "l_wrist", "finger_a_joint",
                                              "r_shoulder", "drive_joint")
    assert m1["urdf"]["continuous"] == ["l_wrist"] and m1["urdf"]["target_links"] == ["finger_c", "r_tool", "camera"]
    # the exported URDF: the same joint and link names, mimic tags, continuous, fixed
    root = ET.fromstring(u2)
    j = {e.get("name"): e for e in root.findall("joint")}
    assert set(j) == set(names) and {e.get("name") for e in root.findall("link")} == {
        "world", *m1["urdf"]["links"].values()}
    assert j["l_wrist"].get("type") == "continuous" and j["l_flange"].get("type") == "fixed"
    mim = j["finger_c_joint"].find("mimic")
    assert (mim.get("joint"), float(mim.get("multiplier")), float(mim.get("offset"))) == ("finger_a_joint", 0.5, 0.01)
    assert float(j["head_pan"].find("mimic").get("multiplier")) == 10.0
    # masses: each row's child link plus links fixed to it that are no row's: the IMU rides on the torso
    assert rows["torso_lift"]["mass"] == pytest.approx(12.5)
    # (the IMU's frame is turned by 90 deg about z: its com offset 0.01 along its x is along the torso's y)
    assert rows["torso_lift"]["com"] == pytest.approx([0.0, 0.11 * 0.5 / 12.5, (12 * 0.3 + 0.5 * 0.2) / 12.5])
    assert rows["l_shoulder"]["com"] == pytest.approx([0.15, 0.0, 0.0]) and rows["l_flange"]["mass"] == 0.0


def test_tree_in_mm_deg_and_serial_chain_in_xyz_form():
    mm, _, _ = check_tree_round_trip(TREE, "world", TREE_TARGETS, seed=1, length_unit="mm", angle_unit="deg")
    rows = {j["name"]: j for j in mm["joints"]}
    # coupled coefficients in the model's joint units: deg per mm for the head on the drive
    assert rows["head_pan"]["coupled"]["drive_joint"] == pytest.approx(10.0 * 180.0 / math.pi / 1000.0)
    assert rows["head_pan"]["coupled"]["offset"] == pytest.approx(math.degrees(0.1))
    assert rows["finger_c_joint"]["coupled"] == pytest.approx({"finger_a_joint": 0.5, "offset": 10.0})
    assert rows["torso_lift"]["limits"] == pytest.approx([0.0, 500.0])
    # the UR-like chain with its fixed joints, forced into the xyz form: fixed rows, one target
    xyz, _, _ = check_tree_round_trip(UR_LIKE, None, "tool0", seed=2)
    assert [j["name"] for j in xyz["joints"] if j["type"] == "fixed"] == [
        "world_to_track", "carriage_to_base", "wrist_3_flange", "flange_tool0"]
    assert len(xyz["joints"]) == 11 and xyz["joints"][5]["name"] == "elbow_joint"
    assert xyz["joints"][5]["mass"] == pytest.approx(2.275 + 0.4)  # the forearm and the sensor fixed to it


def test_calibrated_tree_exports_its_identified_geometry():
    """A calibrated tree (every row's MD-H constants perturbed, beta included, fixed rows too, and the target
    points moved) written as URDF: re-imported, it predicts what the calibrated model predicts, to 1e-9 mm."""
    doc = parse_urdf(TREE, target=TREE_TARGETS)
    model = parse_model(doc)
    n = model.n_joints
    rng = np.random.default_rng(5)
    x = K.nominal_vector(model)
    x[: K.G * n] += rng.normal(0.0, 1.0, K.G * n) * np.tile([2.0, 0.01, 2.0, 0.01, 0.01, 0.01, 2.0], n)  # mm, rad
    x[K.G * n: K.G * n + 6] = [10.0, -20.0, 5.0, 0.01, 0.02, -0.03]  # a base pose: in a comment only
    x[K.G * n + 6:] += rng.normal(0.0, 3.0, 3 * model.n_targets)
    state = {"x": x.tolist(), "R0": np.eye(3).tolist(),
             "effects": [{"kind": "backlash", "joints": [model.joint_names.index("l_elbow")]}]}
    cal = calibrated_model_dict(model, state, doc)
    assert cal["urdf"] == doc["urdf"] and cal["calibration"]["effects"] == [{"kind": "backlash", "joints": ["l_elbow"]}]
    rows = {j["name"]: j for j in cal["joints"]}
    assert rows["l_elbow"]["axis"] != [0.6, 0.0, -0.8] and rows["l_elbow"]["axis"] == pytest.approx(
        [0.6, 0.0, -0.8], abs=0.05)  # the original axis, tilted by the identified geometry
    assert "axis" not in rows["l_flange"] and rows["r_elbow"]["coupled"] == {"l_elbow": -1.0, "offset": 0.2}
    text = to_urdf(cal)
    assert "backlash on l_elbow" in text and "identified base pose" in text
    back = parse_urdf(text, target=TREE_TARGETS)
    qs = random_actuated(doc, 20, 3)
    q = model.expand_joints(np.array([[qi[k] for k in model.actuated_names] for qi in qs])
                            * model.joint_scale()[model.actuated])
    R = K.base_rotation(x[K.G * n: K.G * n + 6], np.eye(3))  # the URDF is in the base link: put it where x puts it
    for t, name in enumerate(model.target_names):
        labels = K.Labels(np.full(len(qs), t), np.zeros(len(qs), int))
        want = K.forward(model, x, q, labels=labels)
        got_model = np.array([xyz_model_poses(cal, qi)[name] for qi in qs])  # the calibrated JSON's own rows
        got_urdf = np.array([urdf_pose(text, name, qi, "world") for qi in qs])  # the URDF's own products
        for got in (got_model, got_urdf):
            p = got[:, :3, 3] * 1000.0 @ R.T + x[K.G * n: K.G * n + 3]
            assert np.abs(p - want).max() < 1e-9, name
        assert np.abs(production_points(back, qs)[name] * 1000.0 @ R.T + x[K.G * n: K.G * n + 3] - want).max() < 1e-9
    # a target off its link origin: folded into the fixed row it hangs on (r_tool, camera) or a link of its own
    # below a movable row (finger_c): the re-import with the same target names finds the identified points
    links = {e.get("name") for e in ET.fromstring(text).iter("link")}
    assert "finger_c_parent" in links and {"r_tool", "camera", "finger_c"} <= links


@pytest.mark.parametrize("old, new, words", [
    ('<mimic joint="l_elbow" multiplier="-1" offset="0.2"/>', '<mimic joint="l_flange"/>', "is fixed"),
    ('<mimic joint="l_elbow" multiplier="-1" offset="0.2"/>', '<mimic joint="l_elbow" multiplier="x"/>',
     "not a finite number"),
    ('<mimic joint="finger_a_joint"/>', '<mimic joint="finger_c_joint"/>', "in a circle"),
    ('name="r_elbow" type="revolute"', 'name="r_elbow" type="floating"', "not supported"),
])
def test_bad_tree_names_the_problem(old, new, words):
    assert old in TREE
    with pytest.raises(UrdfError) as e:
        parse_urdf(TREE.replace(old, new, 1), target=TREE_TARGETS)
    assert any(words in err["message"] for err in e.value.errors), e.value.errors


def test_tree_targets_and_defaults():
    with pytest.raises(UrdfError, match="more than once"):
        parse_urdf(TREE, target="r_tool,r_tool")
    with pytest.raises(UrdfError, match="not the base link itself"):
        parse_urdf(TREE, base="torso", target="torso,r_tool")
    with pytest.raises(UrdfError, match="no link 'nowhere'"):
        parse_urdf(TREE, target="r_tool,nowhere")
    # a base below the joint a mimic follows: the joint cannot be taken in
    with pytest.raises(UrdfError, match="not below the base link.*r_elbow.*mimics.*l_elbow"):
        parse_urdf(TREE, base="r_upper", target="r_tool")
    # a list works like "a,b"; one target with a mimic on the way takes the xyz form by itself
    assert parse_urdf(TREE, target=["r_tool", "camera"]) == parse_urdf(TREE, target="r_tool, camera")
    one = parse_urdf(TREE, target="r_tool")
    assert one["urdf"]["form"] == "xyz" and {j["name"] for j in one["joints"]} == {
        "torso_lift", "r_shoulder", "r_elbow", "r_flange", "l_shoulder", "l_elbow"}
    # no mimic on the way and one target: the MD-H fold, as before
    mdh = parse_urdf(TREE, base="torso", target="l_tool,")
    assert "form" not in mdh["urdf"] and mdh["joints"][0].keys() >= {"a", "alpha", "d", "theta", "beta"}


# --- the one real URDF: Hilti Trailblazer (../shared/datasets) -------------------------------------------------

@pytest.mark.skipif(not HILTI.exists(), reason="../shared/datasets (Hilti trailblazer URDF) is absent")
def test_hilti_trailblazer_urdf():
    """The lifting column's stages mimic column_prismatic_joint, which moves only a pseudo link off the way to
    the prism: it is taken in as a branch row (its CSV column, as in the recordings' joint_names), the stages
    become coupled rows; the whole robot round-trips, and the Doosan arm alone still folds into MD-H rows."""
    text = HILTI.read_text()
    with pytest.raises(UrdfError, match="leaf links"):
        parse_urdf(text)
    with pytest.raises(UrdfError, match="column_middle_joint.*mimics.*column_prismatic_joint"):
        parse_urdf(text, target="prism", form="mdh")
    doc, _, _ = check_tree_round_trip(text, "base_link", "prism")
    rows = {j["name"]: j for j in doc["joints"]}
    assert parse_model(doc).actuated_names == ("column_prismatic_joint", *(f"dsr_joint{i}" for i in range(1, 7)))
    assert rows["column_middle_joint"]["coupled"] == {"column_prismatic_joint": 0.5, "offset": -0.706}
    assert rows["column_top_joint"]["coupled"] == {"column_prismatic_joint": 0.5, "offset": -0.736}
    assert rows["column_middle_joint"]["parent"] == "tracks_base_link_to_column_base"
    assert rows["prism_calib"]["type"] == "fixed" and rows["prism_calib"]["xyz"] == [0.00101828, -0.10091023,
                                                                                       0.33565636]
    assert doc["targets"] == [{"name": "prism", "parent": "prism_calib", "xyz": [0.0, 0.0, 0.0]}]
    assert rows["dsr_tool_to_tool"]["mass"] == 3.0 and rows["baselink_to_tracks"]["mass"] == pytest.approx(400.1)
    # FK sanity: the column at its lowest, the arm at zero: the arm hangs on the column's side
    # (column_tip_to_tool turns it by 90 deg), so it reaches out ahead along x at about the column top's height
    q0 = {"column_prismatic_joint": 1.48, **{f"dsr_joint{i}": 0.0 for i in range(1, 7)}}
    p = xyz_model_poses(doc, q0)["prism"][:3, 3]
    column_top = 0.14 + (0.5 * 1.48 - 0.706) + (0.5 * 1.48 - 0.736) + 1.442 + 0.076
    reach = 0.1525 + 0.62 + 0.559 + 0.121 + 0.34  # Doosan links and the prism offset
    assert 0.5 + reach - 0.5 < p[0] < 0.5 + 0.094 + reach + 0.1 and abs(p[1]) < 0.3, p
    assert abs(p[2] - column_top) < 0.3, (p, column_top)
    # raising the column lifts the prism by the stages' sum (2 x 0.5 x dq), whatever the arm does
    q1 = {**q0, "column_prismatic_joint": 3.0}
    dp = xyz_model_poses(doc, q1)["prism"][:3, 3] - p
    assert dp == pytest.approx([0.0, 0.0, 3.0 - 1.48], abs=1e-12)
    # several targets: the drill tip and the column-tip tilt sensor as well
    three = parse_urdf(text, "base_link", "prism,drill_tip,tilt_sensor_column_tip")
    assert [t["parent"] for t in three["targets"]] == ["prism_calib", "tool_to_tip", "tilt_sensor_column_tip_joint"]
    check_tree_round_trip(text, "base_link", "prism,drill_tip,tilt_sensor_column_tip", seed=4)
    # the arm alone (no mimic on the way) still folds into MD-H
    m1, _ = check_round_trip(text, "column_tool_mount", "prism", 6)
    assert [j["name"] for j in m1["joints"]] == [f"dsr_joint{i}" for i in range(1, 7)]
    assert m1["joints"][5]["mass"] == pytest.approx(1.16 + 3.0)  # link 6 and the tool fixed to it


@pytest.mark.skipif(not HILTI.exists(), reason="../shared/datasets (Hilti trailblazer URDF) is absent")
def test_hilti_nominal_fk_matches_the_total_station():
    """The imported model's nominal FK against the recorded prism positions (flat.yaml): one rigid transform
    per station (column height x IK branch, as the dataset's stationing does) leaves a few mm (6.81 mm; the
    notes: RMS 6.8 mm, deflection and backlash), not the metres a wrong frame, sign or mimic would."""
    yaml = pytest.importorskip("yaml")
    doc = parse_urdf(HILTI.read_text(), "base_link", "prism")
    data = yaml.load((HILTI.parent / "flat.yaml").read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    names = data["joint_names"]
    assert tuple(names) == parse_model(doc).actuated_names
    res = []
    for hv in data["column_heights"].values():
        for sv in hv["solution_spaces"].values():
            ms = (sv.get("stationing_measurements") or []) + (sv.get("evaluation_measurements") or [])
            qs = [dict(zip(names, m["joint_states"])) for m in ms]
            model_pts = np.array([xyz_model_poses(doc, q)["prism"][:3, 3] for q in qs])
            measured = np.array([m["prism_position"] for m in ms], float)
            R, t = K.rigid_fit(model_pts, measured)
            res.append(model_pts @ R.T + t - measured)
    res = np.concatenate(res) * 1000.0
    rms = float(np.sqrt((res ** 2).sum(1).mean()))
    assert 1.0 < rms < 12.0, rms


def test_mdh_tree_model_exports_as_urdf():
    """A tree given as MD-H rows (not from a URDF: no link names, axes z): a fixed row, a Hayati beta, a coupled
    row on another branch, a prismatic branch and three targets off their rows' origins. Its URDF names a link
    per target; read back with those targets it predicts what the model predicts (production kinematics)."""
    doc = {"name": "mdh_tree", "units": {"length": "mm", "angle": "deg"}, "joints": [
        {"name": "T1", "a": 0, "alpha": 0, "d": 400, "theta": 0, "limits": [-170, 170]},
        {"name": "F", "type": "fixed", "a": 50, "alpha": -90, "d": 0, "theta": 10},
        {"name": "L1", "a": 300, "alpha": 0, "d": 0, "theta": -90, "beta": 0.5, "limits": [-90, 90]},
        {"name": "R1", "parent": "F", "a": 300, "alpha": 90, "d": 20, "theta": 0, "limits": [-90, 90],
         "coupled": {"L1": -1.0, "offset": 5.0}},
        {"name": "P", "type": "prismatic", "parent": "T1", "a": 10, "alpha": 90, "d": 0, "theta": 0,
         "limits": [0, 200]}],
        "targets": [{"name": "left", "parent": "L1", "xyz": [100, 0, 0]},
                    {"name": "right", "parent": "R1", "xyz": [50, 10, 0]},
                    {"name": "slide", "parent": "P", "xyz": [0, 0, 30]}]}
    text = to_urdf(doc)
    root = ET.fromstring(text)
    assert root.find("joint[@name='F']").get("type") == "fixed"
    assert root.find("joint[@name='R1']/mimic").attrib == {"joint": "L1", "multiplier": "-1.0",
                                                            "offset": repr(math.radians(5.0))}
    back = parse_urdf(text, target="left,right,slide", length_unit="mm", angle_unit="deg")
    assert [t["name"] for t in back["targets"]] == ["left", "right", "slide"]
    qs = [{"T1": a, "L1": b, "P": c} for a, b, c in np.random.default_rng(7).uniform(
        [-170, -90, 0], [170, 90, 200], (20, 3))]
    want, got = production_points(doc, qs), production_points(back, qs)
    for t in ("left", "right", "slide"):
        assert np.abs(want[t] - got[t]).max() < 1e-9, t
        for i, qi in enumerate(qs):  # and the URDF's own products
            qu = {"T1": math.radians(qi["T1"]), "L1": math.radians(qi["L1"]), "P": qi["P"] / 1000.0}
            assert np.abs(urdf_pose(text, t, qu)[:3, 3] * 1000.0 - want[t][i]).max() < 1e-9, t


def test_calibrated_model_of_several_setups_and_targets():
    """The parameter vector of a calibration with several setups and targets (kinematics.layout): each target's
    identified point lands on its target, each setup's base pose is listed."""
    doc = parse_urdf(TREE, target=TREE_TARGETS)
    model = parse_model(doc)
    lay = K.layout(model, 2)
    x = np.zeros(lay.size)
    x[lay.geometry] = model.geometry.ravel()
    x[lay.base(0)] = [1.0, 2.0, 3.0, 0.0, 0.0, 0.1]
    x[lay.base(1)] = [-1.0, -2.0, -3.0, 0.0, 0.0, -0.1]
    x[lay.tools] = np.arange(3 * model.n_targets, dtype=float)  # mm, in the rows' joint frames
    cal = calibrated_model_dict(model, {"x": x.tolist(), "R0": np.stack([np.eye(3)] * 2).tolist(), "effects": []})
    assert [b["position"] for b in cal["calibration"]["base_poses"]] == [[0.001, 0.002, 0.003],
                                                                          [-0.001, -0.002, -0.003]]
    assert cal["calibration"]["base_pose"] == cal["calibration"]["base_poses"][0]
    back = parse_model(cal)
    assert np.abs(back.target_points - x[lay.tools].reshape(-1, 3)).max() < 1e-12  # the same joint-frame points
    assert "base pose of setup 2" in to_urdf(cal)
