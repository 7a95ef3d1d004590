"""URDF import (issue 30): valid URDFs that were refused now import, with a note of what was ignored (a fixed
joint's <mimic>, a <limit> without a range, a <mimic> of no joint); a xacro file gets one clear error; the user
names each target's nominal SMR offset (m, target link frame); the model keeps the URDF text.

The kinematics are checked two independent ways: against the URDF's own 4x4 products (tests/core/test_urdf.py's
evaluator, no calib_core involved) and, on example-robot-data's real URDFs, against pinocchio's placement of the
target link times the SMR offset; both to 1e-9 mm at random configurations. The pinocchio checks skip when
pinocchio or example-robot-data is absent."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calib_core.model import parse_model
from calib_core.urdf import MAX_SMR_OFFSET_M, XACRO_HINT, UrdfError, parse_urdf

from .test_urdf import UR_LIKE, _hom, production_points, random_actuated, urdf_pose

SMR_M = np.array([0.03, 0.02, 0.05])
FK_TOL_MM = 1e-9


# --- helpers ---------------------------------------------------------------------------------------------

def base_in_urdf_base(doc: dict) -> np.ndarray:
    """4x4 (model units) of the model's base frame in the URDF base link: MD-H base_xyz / base_rpy, else I."""
    e = doc["urdf"]
    if "base_xyz" not in e:
        return np.eye(4)
    an = 1.0 if doc["units"]["angle"] == "rad" else math.pi / 180.0
    return _hom(np.array(e["base_rpy"]) * an, np.array(e["base_xyz"]))


def model_points_mm(doc: dict, qs: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """Each target's points (mm) in the URDF base link by calib_core.kinematics at actuated values qs."""
    mm = 1000.0 if doc["units"]["length"] == "m" else 1.0
    B = base_in_urdf_base(doc)
    pts = {t: (p @ B[:3, :3].T + B[:3, 3]) * mm for t, p in production_points(doc, qs).items()}
    if "tool" in doc:  # the MD-H form: one target, the tool, at the target link
        (p,) = pts.values()
        return {doc["urdf"]["target_link"]: p}
    return pts


def urdf_values(doc: dict, qm: dict[str, float]) -> dict[str, float]:
    """Actuated values from model units to URDF m / rad."""
    ls = 1.0 if doc["units"]["length"] == "m" else 1e-3
    an = 1.0 if doc["units"]["angle"] == "rad" else math.pi / 180.0
    rows = {j["name"]: j for j in doc["joints"]}
    return {k: v * (ls if rows[k]["type"] == "prismatic" else an) for k, v in qm.items()}


def own_products_mm(text: str, base: str, link: str, q: dict[str, float], smr_m) -> np.ndarray:
    """The URDF's own 4x4 products (test_urdf.urdf_pose) times the SMR offset, mm."""
    return (urdf_pose(text, link, q, base) @ np.r_[smr_m, 1.0])[:3] * 1000.0


def arm(joint2: str, extra: str = "") -> str:
    """A three-joint arm whose second joint's XML is `joint2` (named j2, a -> b -> c -> tool)."""
    return f"""<robot name="arm">
  <link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="tool"/>{extra}
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  {joint2}
  <joint name="j3" type="revolute"><parent link="c"/><child link="d"/><origin xyz="0.4 0 0" rpy="0.3 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="flange" type="fixed"><parent link="d"/><child link="tool"/><origin xyz="0.1 0 0.02" rpy="0 1.2 0.4"/>
  </joint>
</robot>"""


J2 = """<joint name="j2" type="{type}"><parent link="b"/><child link="c"/><origin xyz="0 0.1 0" rpy="0 0.2 0"/>
    <axis xyz="0 1 0"/>{limit}{mimic}</joint>"""


def j2(type: str = "revolute", limit: str = '<limit lower="-1" upper="1" effort="1" velocity="1"/>',
       mimic: str = "") -> str:
    return J2.format(type=type, limit=limit, mimic=mimic)


def check_own_products(text: str, base: str, targets: list[str], smr, seed: int = 0, **kw) -> dict:
    """parse_urdf with SMR offsets; every target point equals the URDF's own products times the offset."""
    doc = parse_urdf(text, base, targets if len(targets) > 1 else targets[0], smr_m=smr, **kw)
    offs = dict(zip(targets, np.atleast_2d(np.asarray(
        [list(map(float, s.split(","))) for s in smr.split(";")] if isinstance(smr, str) else smr, float))))
    qs = random_actuated(doc, 25, seed)
    pts = model_points_mm(doc, qs)
    for i, qm in enumerate(qs):
        for t in targets:
            want = own_products_mm(text, base, t, urdf_values(doc, qm), offs[t])
            assert np.abs(pts[t][i] - want).max() < FK_TOL_MM, (t, pts[t][i] - want)
    return doc


# --- 1. valid URDFs that were refused ----------------------------------------------------------------------

def test_fixed_joint_with_mimic_is_ignored_and_noted():
    text = arm(j2(), extra="").replace(
        '<joint name="flange" type="fixed"><parent link="d"/>',
        '<joint name="flange" type="fixed"><mimic joint="j3" multiplier="2"/><parent link="d"/>')
    for form in ("mdh", "xyz"):
        doc = parse_urdf(text, target="tool", form=form)
        assert doc["urdf"]["notes"] == ["joint 'flange' is fixed: its <mimic joint='j3'> was ignored (a fixed "
                                        "joint has no value to follow)"]
        assert not any("coupled" in row for row in doc["joints"])
        assert parse_model(doc).actuated_names == ("j1", "j2", "j3")
    assert "tool" in parse_urdf(text, target="tool")  # the auto form: no mimic left on the chain, MD-H
    # a note only for the joints taken in: the chain a -> c does not pass the flange
    assert parse_urdf(text, target="c", form="xyz")["urdf"]["notes"] == []


@pytest.mark.parametrize("limit, what", [
    ('<limit effort="1" velocity="1"/>', "gives no lower and no upper (the URDF default is 0)"),
    ('<limit lower="0" upper="0" effort="1" velocity="1"/>', 'gives no position range'),
    ('<limit lower="-1e16" upper="1e16" effort="1" velocity="1"/>', "reaches beyond 100 turns"),
])
def test_revolute_limit_without_range_is_unlimited(limit, what):
    text = arm(j2(limit=limit))
    for form in ("mdh", "xyz"):
        doc = parse_urdf(text, target="tool", form=form, angle_unit="deg")
        rows = {r["name"]: r for r in doc["joints"]}
        assert "limits" not in rows["j2"] and rows["j1"]["limits"] == pytest.approx([-3 * 180 / math.pi,
                                                                                     3 * 180 / math.pi])
        assert len(doc["urdf"]["notes"]) == 1
        note = doc["urdf"]["notes"][0]
        assert note.startswith("joint 'j2': ") and what in note and note.endswith(
            "read as a revolute joint without position limits"), note
        model = parse_model(doc)
        assert not np.isfinite(model.limits[1]).all() and np.isfinite(model.limits[0]).all()
        assert "j2" not in doc["urdf"]["continuous"]  # a revolute joint, written back with its effort/velocity
        assert doc["urdf"]["limits"]["j2"] == {"effort": 1.0, "velocity": 1.0}


def test_limit_defaults_of_the_urdf_spec():
    # one bound given: the other is the URDF default 0, noted
    doc = parse_urdf(arm(j2(limit='<limit upper="1.5" effort="1" velocity="1"/>')), target="tool", form="xyz")
    assert {r["name"]: r for r in doc["joints"]}["j2"]["limits"] == [0.0, 1.5]
    assert doc["urdf"]["notes"] == ["joint 'j2': <limit> gives no lower: read as 0 (the URDF default), so the "
                                    "joint's range is [0, 1.5]"]
    # a prismatic joint without range: the model needs limits, so +-100 m, noted
    doc = parse_urdf(arm(j2("prismatic", '<limit effort="1" velocity="1"/>')), target="tool", length_unit="mm")
    assert {r["name"]: r for r in doc["joints"]}["j2"]["limits"] == [-1e5, 1e5]
    assert "read as a travel of +-100 m" in doc["urdf"]["notes"][0]
    # what urdfdom (so pinocchio) refuses stays refused: a revolute joint without <limit>, lower above upper
    with pytest.raises(UrdfError, match="needs <limit lower=... upper=...>") as e:
        parse_urdf(arm(j2(limit="")), target="tool")
    assert e.value.errors[0]["field"] == "joint[@name='j2']/limit"
    with pytest.raises(UrdfError, match="lower limit must be below"):
        parse_urdf(arm(j2(limit='<limit lower="1" upper="-1" effort="1" velocity="1"/>')), target="tool")
    with pytest.raises(UrdfError, match="not a finite number") as e:
        parse_urdf(arm(j2(limit='<limit upper="x" effort="1" velocity="1"/>')), target="tool")
    assert e.value.errors[0]["field"] == "joint[@name='j2']/limit/@upper"


def test_mimic_of_no_joint_is_an_independent_joint():
    text = arm(j2(mimic='<mimic joint="j_missing" multiplier="2" offset="0.1"/>'))
    doc = parse_urdf(text, target="tool")  # no mimic left on the chain: the auto form folds it into MD-H rows
    assert "tool" in doc and doc["urdf"]["notes"] == [
        "joint 'j2' mimics 'j_missing', which is no joint of the URDF: the <mimic> was ignored and 'j2' read as an "
        "independent (actuated) joint"]
    xyz = parse_urdf(text, target="tool", form="xyz")
    assert parse_model(xyz).actuated_names == ("j1", "j2", "j3") and not any("coupled" in r for r in xyz["joints"])
    check_own_products(text.replace('<mimic joint="j_missing" multiplier="2" offset="0.1"/>', ""), "a", ["tool"],
                       "0.03,0.02,0.05")
    # a mimic of that joint still follows it
    text2 = text.replace('<joint name="j3" type="revolute">', '<joint name="j3" type="revolute"><mimic joint="j2"/>')
    doc2 = parse_urdf(text2, target="tool")
    assert {r["name"]: r for r in doc2["joints"]}["j3"]["coupled"] == {"j2": 1.0}
    # the errors that remain: a mimic of a fixed joint, a mimic without joint=
    with pytest.raises(UrdfError, match="is fixed"):
        parse_urdf(text.replace('"j_missing"', '"flange"'), target="tool")
    with pytest.raises(UrdfError, match="needs joint="):
        parse_urdf(text.replace('joint="j_missing" ', ""), target="tool")


# --- 2. xacro ----------------------------------------------------------------------------------------------

SMALL_XACRO = """<?xml version="1.0"?>
<robot name="arm" xmlns:xacro="http://www.ros.org/wiki/xacro">
  <xacro:property name="l1" value="0.3"/>
  <link name="a"/><link name="b"/>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 ${l1}"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>"""


@pytest.mark.parametrize("text, value", [
    (SMALL_XACRO, "<xacro:property>"),
    # no xacro element, but a substitution in an attribute the importer reads
    (SMALL_XACRO.replace('<xacro:property name="l1" value="0.3"/>', ""), "0 0 ${l1}"),
    (SMALL_XACRO.replace('<xacro:property name="l1" value="0.3"/>', "").replace(
        ' xmlns:xacro="http://www.ros.org/wiki/xacro"', "").replace("${l1}", "$(arg l1)"), "0 0 $(arg l1)"),
    # xacro: used without declaring it: not even well-formed XML
    (SMALL_XACRO.replace(' xmlns:xacro="http://www.ros.org/wiki/xacro"', ""), None),
    # a xacro attribute, a macro call wrapping everything
    (SMALL_XACRO.replace('<link name="a"/>', '<link name="a" xacro:if="${l1 > 0}"/>').replace(
        '<xacro:property name="l1" value="0.3"/>', ""), None),
    ('<robot name="r" xmlns:xacro="http://wiki.ros.org/xacro"><xacro:include filename="arm.xacro"/>'
     '<xacro:arm prefix="left_"/></robot>', "<xacro:include>"),
])
def test_xacro_gets_one_clear_error(text, value):
    with pytest.raises(UrdfError) as e:
        parse_urdf(text)
    assert len(e.value.errors) == 1 and e.value.errors[0]["message"] == XACRO_HINT, e.value.errors
    assert XACRO_HINT == "this is a xacro file: expand it with `xacro FILE > robot.urdf` first"
    if value is not None:
        assert e.value.errors[0]["value"] == value


def test_xacro_output_is_no_xacro_file():
    """xacro keeps xmlns:xacro in the URDF it writes, and ${...} may stay in comments and visuals."""
    text = UR_LIKE.replace('<robot name="ur_like">', '<robot name="ur_like" xmlns:xacro="http://wiki.ros.org/xacro">'
                           '<!-- <xacro:arm l="${l1}"/> -->').replace(
        '<link name="tool0"/>', '<link name="tool0"><visual><geometry><box size="${w} 0.1 0.1"/></geometry></visual>'
        '</link>')
    assert parse_urdf(text, target="tool0")["joints"] == parse_urdf(UR_LIKE, target="tool0")["joints"]
    with pytest.raises(UrdfError, match="the URDF has no <link>"):  # xacro's output of a file with macros only
        parse_urdf('<robot xmlns:xacro="http://wiki.ros.org/xacro"><!-- autogenerated --></robot>')


# --- 3. SMR offsets ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("form", ["mdh", "xyz"])
@pytest.mark.parametrize("units", [("m", "rad"), ("mm", "deg")])
def test_smr_offset_in_the_target_link_frame(form, units):
    doc = check_own_products(UR_LIKE, "world", ["tool0"], "0.03,0.02,0.05", form=form, length_unit=units[0],
                             angle_unit=units[1])
    assert doc["urdf"]["smr_m"] == {"tool0": [0.03, 0.02, 0.05]}
    plain = parse_urdf(UR_LIKE, "world", "tool0", form=form, length_unit=units[0], angle_unit=units[1])
    assert plain["joints"] == doc["joints"] and "smr_m" not in plain["urdf"]
    if form == "mdh":  # the offset turned into the last MD-H frame: not simply added
        k = 1.0 if units[0] == "m" else 1000.0
        assert np.abs(np.subtract(doc["tool"], plain["tool"])).max() > 1e-3 * k
        assert not np.allclose(np.subtract(doc["tool"], plain["tool"]), SMR_M * k)
        assert doc["urdf"]["tool_rpy"] == plain["urdf"]["tool_rpy"]  # the link frame's orientation stays
    else:
        k = 1.0 if units[0] == "m" else 1000.0
        assert doc["targets"][0]["xyz"] == pytest.approx(list(SMR_M * k))


def test_smr_offsets_of_several_targets():
    from .test_urdf import TREE, TREE_TARGETS

    targets = TREE_TARGETS.split(",")
    smr = "0.03,0.02,0.05;-0.01,0,0.2;0,0,0"
    doc = check_own_products(TREE, "world", targets, smr)
    assert [t["xyz"] for t in doc["targets"]] == [[0.03, 0.02, 0.05], [-0.01, 0.0, 0.2], [0.0, 0.0, 0.0]]
    # the same as a list and as a mapping (targets left out: at the link origin)
    assert parse_urdf(TREE, "world", targets, smr_m=[(0.03, 0.02, 0.05), (-0.01, 0, 0.2), (0, 0, 0)]) == doc
    by_name = parse_urdf(TREE, "world", targets, smr_m={"r_tool": (-0.01, 0, 0.2), "finger_c": (0.03, 0.02, 0.05)})
    assert by_name["targets"] == doc["targets"]


@pytest.mark.parametrize("smr, field, words", [
    ("0.03,0.02", "smr", "three numbers x,y,z"),
    ("0.03,0.02,abc", "smr", "three finite numbers"),
    ("0.03,0.02,nan", "smr", "three finite numbers"),
    ("30,20,50", "smr", f"at most {MAX_SMR_OFFSET_M:g} m (the offset is in metres, not millimetres)"),
    ("0,0,0.1;0,0,0.2", "smr", "2 SMR offsets for 1 target link (tool0): give one x,y,z per target"),
    ({"tool1": (0, 0, 0.1)}, "smr['tool1']", "'tool1' is not one of the target links (tool0)"),
    ([(0, 0, "x")], "smr", "three finite numbers"),
    (5, "smr", "'x,y,z;x,y,z' (m)"),
])
def test_bad_smr_names_the_parameter_and_value(smr, field, words):
    with pytest.raises(UrdfError) as e:
        parse_urdf(UR_LIKE, "world", "tool0", smr_m=smr)
    err = e.value.errors[0]
    assert err["field"] == field and words in err["message"], err
    if isinstance(smr, str) and ";" not in smr:
        assert err["value"] == smr


# --- 4. the URDF text is kept --------------------------------------------------------------------------------

def test_source_is_the_original_text():
    doc = parse_urdf(UR_LIKE, "world", "tool0")
    assert doc["urdf"]["source"] == UR_LIKE and doc["urdf"]["notes"] == []
    assert parse_urdf(b"\xef\xbb\xbf" + UR_LIKE.encode(), "world", "tool0")["urdf"]["source"] == UR_LIKE
    tree = parse_urdf(UR_LIKE, "world", "tool0,finger_left")
    assert tree["urdf"]["form"] == "xyz" and tree["urdf"]["source"] == UR_LIKE


# --- real URDFs against pinocchio ----------------------------------------------------------------------------

def _erd() -> dict[str, Path]:
    """File name -> path of example-robot-data's URDFs and xacro files ({} when it is not installed)."""
    from .test_pinocchio_reference import erd_files

    return erd_files((".urdf", ".xacro"))


ERD = _erd()


def erd_text(name: str) -> str:
    if name not in ERD or not ERD[name].exists():
        pytest.skip(f"example-robot-data has no {name}")
    return ERD[name].read_text()


# (file, base link or None, target links, a joint the note names, what the note says): each refused before
REFUSED = [
    ("talos_left_arm.urdf", None, "gripper_left_fingertip_1_link", "gripper_left_fingertip_1_joint",
     "is fixed: its <mimic joint='gripper_left_joint'> was ignored"),
    ("talos_reduced.urdf", "base_link", "gripper_left_fingertip_1_link,gripper_right_fingertip_3_link",
     "gripper_right_fingertip_3_joint", "is fixed: its <mimic joint='gripper_right_joint'> was ignored"),
    ("centauro.urdf", None, "wheel_1", "j_wheel_1", "gives no lower and no upper"),
    ("quadruped.urdf", None, "FL_shank", "FL_KFE", "gives no lower and no upper"),
    ("double_pendulum.urdf", None, None, "joint2", 'gives no position range'),
    ("iris.urdf", None, "iris__rotor_0", "iris__rotor_0_joint", "reaches beyond 100 turns"),
    ("alex_psyonic_hands.urdf", None, "Right_ring_L2", "Right_ring_q2",
     "mimics 'ring_q1', which is no joint of the URDF"),
]


@pytest.mark.parametrize("file, base, targets, joint, words", REFUSED, ids=[r[0] + ":" + r[3] for r in REFUSED])
@pytest.mark.parametrize("form", ["auto", "xyz"])
def test_refused_urdfs_import_like_pinocchio(file, base, targets, joint, words, form):
    pytest.importorskip("pinocchio")
    from .test_pinocchio_reference import PinRobot

    text = erd_text(file)
    tl = targets.split(",") if targets else None
    smr = None if tl is None else ";".join(["0.03,0.02,0.05"] * len(tl))
    doc = parse_urdf(text, base, targets, form=form, smr_m=smr, length_unit="mm")
    notes = [n for n in doc["urdf"]["notes"] if f"joint {joint!r}" in n]
    assert len(notes) == 1 and words in notes[0], doc["urdf"]["notes"]
    assert doc["urdf"]["source"] == text
    base_link, tl = doc["urdf"]["base_link"], doc["urdf"].get("target_links") or [doc["urdf"]["target_link"]]
    ref = PinRobot(text)  # pinocchio loads it
    qs = random_actuated(doc, 30, seed=7)
    pts = model_points_mm(doc, qs)
    offset = SMR_M if smr else np.zeros(3)
    for i, qm in enumerate(qs):
        qu = urdf_values(doc, qm)
        for t in tl:
            want = ref.link_points([qu], base_link, [t], np.asarray(offset, float) * 1000.0)[0, 0]
            assert np.abs(pts[t][i] - want).max() < FK_TOL_MM, (t, pts[t][i] - want)
            assert np.abs(own_products_mm(text, base_link, t, qu, offset) - want).max() < FK_TOL_MM


@pytest.mark.parametrize("file, target, form", [("ur5_robot.urdf", "tool0", "mdh"), ("ur5_robot.urdf", "tool0", "xyz"),
                                                ("panda.urdf", "panda_hand_tcp", "mdh"),
                                                ("baxter.urdf", "left_gripper,right_gripper", "auto")])
def test_smr_offset_matches_pinocchio(file, target, form):
    pytest.importorskip("pinocchio")
    from .test_pinocchio_reference import PinRobot

    text = erd_text(file)
    base = "base" if file == "baxter.urdf" else None
    tl = target.split(",")
    smr = [(0.03, 0.02, 0.05), (-0.04, 0.01, 0.12)][:len(tl)]
    doc = parse_urdf(text, base, target, form=form, smr_m=smr, angle_unit="deg")
    ref = PinRobot(text)
    qs = random_actuated(doc, 40, seed=3)
    pts = model_points_mm(doc, qs)
    for i, qm in enumerate(qs):
        qu = urdf_values(doc, qm)
        for t, off in zip(tl, smr):
            want = ref.link_points([qu], doc["urdf"]["base_link"], [t], np.asarray(off, float) * 1000.0)[0, 0]
            assert np.abs(pts[t][i] - want).max() < FK_TOL_MM, (t, pts[t][i] - want)


@pytest.mark.parametrize("file", ["quadrotor_base.xacro", "quadrotor_base.urdf.xacro"])
def test_real_xacro_files(file):
    with pytest.raises(UrdfError) as e:
        parse_urdf(erd_text(file))
    assert [err["message"] for err in e.value.errors] == [XACRO_HINT]
