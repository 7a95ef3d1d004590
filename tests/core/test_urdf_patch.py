"""The calibrated URDF as the original file patched (calib_core.urdf_patch, issue 30), on real URDFs of the
example-robot-data package: a UR5 to tool0 in the MD-H form, the Talos left arm in the xyz form (and as MD-H
rows), Baxter's two arms (a tree with two targets), the Panda to a finger with a mimic joint and the Talos gripper
(a mimic joint). For each, a calibrated parameter vector with every geometric parameter, the base and the targets
changed at random:

(i) the export is the original with only joint origins changed: both parsed with xml.etree, every element and
    attribute equal except the ``xyz`` / ``rpy`` of joint ``<origin>`` elements (meshes, collisions, inertials,
    transmissions, gazebo tags, link and joint names, element counts), and a unified diff shows only origin
    lines and the one comment;
(ii) it loads in pinocchio and yourdfpy;
(iii) pinocchio's FK of the export at 200 random configurations, times the side file's SMR point, equals
    calib_core.kinematics.forward with the base block zeroed (in the URDF base link) to 1e-6 mm, and with the
    base joint, the measurement-frame prediction.
"""
from __future__ import annotations

import difflib
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.identify import CalibratedRobot
from calib_core.model import GEOMETRIC, ANGULAR, parse_model
from calib_core.urdf import parse_urdf
from calib_core.urdf_patch import _base_matrix, export_calibration, patch_urdf

pin = pytest.importorskip("pinocchio")

ROBOTS = Path(pin.__file__).resolve().parents[4] / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
if not ROBOTS.exists():  # pragma: no cover - another layout of the package
    import glob

    hits = glob.glob(str(Path(pin.__file__).resolve().parents[5] / "**" / "example-robot-data" / "robots"),
                     recursive=True)
    ROBOTS = Path(hits[0]) if hits else ROBOTS

CASES = {  # name: (file, base link, target link(s), form)
    "ur5_mdh": ("ur_description/urdf/ur5_robot.urdf", "base_link", "tool0", "auto"),
    "talos_left_arm_xyz": ("talos_data/robots/talos_reduced.urdf", "base_link", "gripper_left_base_link", "xyz"),
    "talos_left_arm_mdh": ("talos_data/robots/talos_reduced.urdf", "base_link", "gripper_left_base_link", "mdh"),
    "baxter_two_arms": ("baxter_description/urdf/baxter.urdf", "base", "left_gripper,right_gripper", "auto"),
    "panda_mimic_finger": ("panda_description/urdf/panda.urdf", None, "panda_rightfinger", "auto"),
    "talos_gripper_mimic": ("talos_data/robots/talos_full_v2.urdf", "base_link", "gripper_left_inner_single_link",
                            "auto"),
}
N_FK = 200
TOL_MM = 1e-6


def _source(name: str) -> str:
    path = ROBOTS / CASES[name][0]
    if not path.exists():
        pytest.skip(f"{path} is absent")
    return path.read_text()


def imported(name: str) -> tuple[str, dict]:
    """(URDF text, model document with the source kept as the import keeps it)."""
    f, base, targets, form = CASES[name]
    text = _source(name)
    doc = parse_urdf(text, base, targets, form=form)
    doc["urdf"]["source"] = text
    return text, doc


def perturbed(model, seed: int = 0, n_setups: int = 1) -> np.ndarray:
    """The nominal vector with every geometric parameter moved (0.5 mm, 1 mrad), a base pose and the targets
    moved by tens of mm (an SMR off the link origin)."""
    rng = np.random.default_rng(seed)
    x = K.nominal_vector(model, n_setups=n_setups)
    lay = K.layout(model, x)
    scale = np.array([1e-3 if p in ANGULAR else 0.5 for p in GEOMETRIC])
    x[lay.geometry] += rng.normal(0.0, 1.0, lay.geometry.stop) * np.tile(scale, model.n_joints)
    for s in range(n_setups):
        x[lay.base(s)] = [1500.0 - 300 * s, -800.0, 200.0, 0.01, -0.02, 0.7 + 0.1 * s]
    x[lay.tools] += rng.normal(0.0, 30.0, 3 * model.n_targets)
    return x


def state_of(model, x, R0=None, effects=()) -> dict:
    """A calibration's stored state (CalibratedRobot.to_state) with these effect states."""
    st = CalibratedRobot(model, np.asarray(x, float), np.eye(3) if R0 is None else np.asarray(R0, float)).to_state()
    st["effects"] = list(effects)
    return st


def joint_origins_only(orig: str, new: str, extra_links=(), extra_joints=()) -> set[str]:
    """Assert that `new` is `orig` up to joint origins (and the named added link / joint); the joints whose
    origins differ."""
    a, b = ET.fromstring(orig), ET.fromstring(new)
    drop = [e for e in list(b) if (e.tag == "link" and e.get("name") in extra_links)
            or (e.tag == "joint" and e.get("name") in extra_joints)]
    assert len(drop) == len(extra_links) + len(extra_joints)
    for e in drop:
        b.remove(e)
    ea, eb = list(a.iter()), list(b.iter())
    assert len(ea) == len(eb)
    parent_a = {c: p for p in a.iter() for c in p}
    changed = set()
    for x, y in zip(ea, eb):
        assert x.tag == y.tag and (x.text or "").strip() == (y.text or "").strip()
        p = parent_a.get(x)
        if x.tag == "origin" and p is not None and p.tag == "joint":
            if x.attrib != y.attrib:
                changed.add(p.get("name"))
            assert set(y.attrib) <= set(x.attrib) | {"xyz", "rpy"}
            assert {k: v for k, v in x.attrib.items() if k not in ("xyz", "rpy")} == \
                   {k: v for k, v in y.attrib.items() if k not in ("xyz", "rpy")}
        else:
            assert x.attrib == y.attrib, (x.tag, x.attrib, y.attrib)
    for tag in ("link", "joint", "visual", "collision", "inertial", "mesh", "transmission", "gazebo", "mimic"):
        assert len(a.findall(f".//{tag}")) == len(b.findall(f".//{tag}")), tag
    return changed


def diff_lines(orig: str, new: str) -> tuple[list[str], list[str]]:
    d = [ln for ln in difflib.unified_diff(orig.splitlines(), new.splitlines(), lineterm="", n=0)
         if not ln.startswith(("---", "+++", "@@"))]
    return [ln[1:] for ln in d if ln.startswith("-")], [ln[1:] for ln in d if ln.startswith("+")]


def pin_q(pm, values: dict[str, float]) -> np.ndarray:
    q = pin.neutral(pm)
    for jid in range(1, pm.njoints):
        jm, v = pm.joints[jid], values.get(pm.names[jid], 0.0)
        if jm.nq == 1:
            q[jm.idx_q] = v
        elif jm.nq == 2:  # continuous: cos, sin
            q[jm.idx_q: jm.idx_q + 2] = [np.cos(v), np.sin(v)]
    return q


def sample(model, n: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    lim = model.limits[model.actuated].copy()
    lim[~np.isfinite(lim)] = np.sign(lim[~np.isfinite(lim)]) * np.pi
    q = model.expand_joints(lim[:, 0] + (lim[:, 1] - lim[:, 0]) * rng.random((n, len(lim))))
    return q, K.Labels(np.arange(n) % model.n_targets, np.zeros(n, int))


def pin_points(urdf_text: str, model, side: dict, q: np.ndarray, labels, relative_to: str | None) -> np.ndarray:
    """mm: the side file's SMR point through pinocchio's FK of the URDF, in `relative_to`'s frame (None: the
    URDF's root frame)."""
    pm = pin.buildModelFromXML(urdf_text)
    data = pm.createData()
    out = []
    for qi, t in zip(q, labels.target):
        vals = {nm: qi[k] / (1000.0 if model.prismatic[k] else 1.0) for k, nm in enumerate(model.joint_names)}
        pin.framesForwardKinematics(pm, data, pin_q(pm, vals))
        tg = side["targets"][t]
        M = data.oMf[pm.getFrameId(tg["link"], pin.BODY)]
        if relative_to is not None:
            M = data.oMf[pm.getFrameId(relative_to, pin.BODY)].inverse() * M
        out.append(M.act(np.array(tg["xyz"])) * 1000.0)
    return np.array(out)


def yourdfpy_load(text: str, tmp_path: Path):
    yourdfpy = pytest.importorskip("yourdfpy")
    f = tmp_path / "export.urdf"
    f.write_text(text)
    return yourdfpy.URDF.load(str(f), build_scene_graph=True, load_meshes=False, build_collision_scene_graph=False,
                              load_collision_meshes=False)


@pytest.mark.parametrize("name", list(CASES))
def test_patched_export_is_the_original_with_calibrated_origins(name, tmp_path):
    text, doc = imported(name)
    model = parse_model(doc)
    x = perturbed(model, seed=len(name))
    state = state_of(model, x, effects=[
        {"kind": "joint_compliance", "class": "JointCompliance", "joints": [1], "values": [1e-6]}])
    out = export_calibration(doc, state, calibration_id="cal-1")

    # (i) only joint origins (and the comment) differ
    changed = joint_origins_only(text, out.urdf)
    assert changed == set(out.changed) and changed
    removed, added = diff_lines(text, out.urdf)
    assert all("<origin" in ln for ln in removed), removed
    comments = [ln for ln in added if "<!--" in ln]
    assert len(comments) == 1 and "calibration.json" in comments[0] and "cal-1" in comments[0]
    assert all("<origin" in ln for ln in added if ln not in comments)
    assert len(removed) == len(added) - 1 <= len(changed) * 2  # an origin spread over two lines at most
    # every movable row's joint moved; nothing off the rows' joints did
    rows = set(model.joint_names)
    assert changed <= rows
    assert {model.joint_names[j] for j in np.flatnonzero(model.moving)} <= changed

    # (ii) it loads in pinocchio and yourdfpy, with every joint and link the original has
    pm, pm0 = pin.buildModelFromXML(out.urdf), pin.buildModelFromXML(text)
    assert list(pm.names) == list(pm0.names) and pm.nq == pm0.nq and pm.nframes == pm0.nframes
    ydf = yourdfpy_load(out.urdf, tmp_path)
    assert set(ydf.joint_map) == {j.get("name") for j in ET.fromstring(text).findall("joint")}

    # (iii) pinocchio FK x the side file's SMR point = forward() in the URDF base link
    q, labels = sample(model, N_FK)
    x0 = x.copy()
    x0[K.layout(model, x).bases] = 0.0
    B = _base_matrix(doc["urdf"], model)
    ref = K.forward(model, x0, q, labels=labels) @ B[:3, :3].T + B[:3, 3]
    got = pin_points(out.urdf, model, out.side, q, labels, doc["urdf"]["base_link"])
    err = np.abs(got - ref).max()
    assert err < TOL_MM, err
    # and the nominal URDF is far from it (the test would see a missed change)
    nominal = pin_points(text, model, out.side, q, labels, doc["urdf"]["base_link"])
    assert np.abs(nominal - ref).max() > 0.1

    # yourdfpy's own FK agrees with pinocchio's on a few configurations (it follows mimic joints itself)
    for i in range(5):
        cfg = {nm: q[i, k] / (1000.0 if model.prismatic[k] else 1.0) for k, nm in enumerate(model.joint_names)
               if nm in ydf.actuated_joint_names}
        ydf.update_cfg(cfg)
        tg = out.side["targets"][labels.target[i]]
        T = ydf.get_transform(tg["link"], doc["urdf"]["base_link"])
        assert np.abs((T[:3, :3] @ tg["xyz"] + T[:3, 3]) * 1000.0 - ref[i]).max() < TOL_MM

    side = json.loads(out.side_json())
    assert side["changed_joints"] == out.changed and side["calibration_id"] == "cal-1"
    assert [t["name"] for t in side["targets"]] == list(model.target_names)
    assert side["effects"][0]["joints"] == [model.joint_names[1]]
    assert all(not m["changed"] for m in side["mimic"])
    assert len(side["mimic"]) == len(model.coupling)


@pytest.mark.parametrize("name", ["ur5_mdh", "baxter_two_arms", "panda_mimic_finger"])
def test_base_joint_carries_the_measurement_frame(name, tmp_path):
    text, doc = imported(name)
    model = parse_model(doc)
    x = perturbed(model, seed=3)
    R0 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # a pre-alignment
    state = state_of(model, x, R0)
    out = export_calibration(doc, state, base_joint=True)
    root = [ln.get("name") for ln in ET.fromstring(text).findall("link")
            if ln.get("name") not in {j.find("child").get("link") for j in ET.fromstring(text).findall("joint")}]
    joint_origins_only(text, out.urdf, ["measurement_frame"], ["measurement_frame_joint"])
    assert out.side["base_joint"]["link"] == "measurement_frame" and out.side["base_joint"]["parent_of"] == root[0]
    pm = pin.buildModelFromXML(out.urdf)
    assert pm.frames[pm.getFrameId(root[0], pin.BODY)].parentJoint == 0
    yourdfpy_load(out.urdf, tmp_path)
    q, labels = sample(model, N_FK, seed=5)
    ref = K.forward(model, x, q, R0, labels=labels)  # the measurement frame: what predict answers
    got = pin_points(out.urdf, model, out.side, q, labels, None)
    err = np.abs(got - ref).max()
    assert err < TOL_MM, err
    # the side file's base pose is the same frame
    bp = out.side["base_poses"][0]
    P = np.eye(4)
    P[:3, :3], P[:3, 3] = np.array(bp["rotation_matrix"]), np.array(bp["xyz"]) * 1000.0
    rel = pin_points(out.urdf, model, out.side, q[:5], labels[:5], doc["urdf"]["base_link"])
    assert np.abs(rel @ P[:3, :3].T + P[:3, 3] - ref[:5]).max() < TOL_MM
    # a name of one's own; a name the URDF has is refused
    named = export_calibration(doc, state, base_joint="tracker")
    assert '<link name="tracker"/>' in named.urdf and 'name="tracker_joint"' in named.urdf
    with pytest.raises(ValueError, match="already has a link"):
        export_calibration(doc, state, base_joint=root[0])


def test_uncalibrated_export_is_the_original_plus_one_comment():
    text, doc = imported("talos_left_arm_xyz")
    model = parse_model(doc)
    out = export_calibration(doc, state_of(model, K.nominal_vector(model)))
    removed, added = diff_lines(text, out.urdf)
    assert removed == [] and len(added) == 1 and "<!--" in added[0] and out.changed == []


def test_one_row_moved_changes_its_joint_and_its_children_only():
    """theta of one row (a joint offset) changes that joint's origin; a shift `a` of the next row changes that
    one; every other joint keeps its text."""
    text, doc = imported("ur5_mdh")
    model = parse_model(doc)
    x = K.nominal_vector(model)
    G = len(GEOMETRIC)
    x[2 * G + GEOMETRIC.index("theta")] += 1e-3
    out = export_calibration(doc, state_of(model, x))
    assert out.changed == ["elbow_joint"]
    removed, added = diff_lines(text, out.urdf)
    assert len(removed) == 1 and "<origin" in removed[0]
    x[3 * G + GEOMETRIC.index("a")] += 0.2
    out = export_calibration(doc, state_of(model, x))
    assert out.changed == ["elbow_joint", "wrist_1_joint"]


def test_formatting_is_kept_byte_for_byte():
    """Comments, attribute order, single quotes, an origin without rpy, a joint without origin, CRLF line ends."""
    text = ("<?xml version='1.0'?>\r\n<!-- top -->\r\n<robot name='r'>\r\n  <!-- a comment -->\r\n"
            "  <link name='base'><visual><origin xyz='1 2 3'/><geometry><mesh filename='package://m.dae'/>"
            "</geometry></visual></link>\r\n  <link name='l1'/>\r\n  <link name='l2'/>\r\n"
            "  <joint type='revolute' name='j1'>\r\n    <parent link='base'/>\r\n    <child link='l1'/>\r\n"
            "    <axis xyz='0 0 1'/>\r\n    <limit lower='-1' upper='1' effort='1' velocity='1'/>\r\n  </joint>\r\n"
            "  <joint name='j2' type='revolute'>\r\n    <origin  xyz = '0.1 0 0.2'   />\r\n"
            "    <parent link='l1'/>\r\n    <child link='l2'/>\r\n    <axis xyz='0 1 0'/>\r\n"
            "    <limit lower='-1' upper='1' effort='1' velocity='1'/>\r\n  </joint>\r\n</robot>\r\n")
    doc = parse_urdf(text, form="xyz")
    doc["urdf"]["source"] = text
    model = parse_model(doc)
    x = perturbed(model, seed=9)
    out = export_calibration(doc, state_of(model, x))
    assert out.changed == ["j1", "j2"]
    removed, added = diff_lines(text, out.urdf)
    assert removed == ["    <origin  xyz = '0.1 0 0.2'   />"]
    assert added[1].startswith("    <origin xyz=") and len(added) == 3  # j1 had none: one inserted
    assert added[2].startswith("    <origin  xyz = '") and " rpy='" in added[2] and added[2].endswith("'   />")
    assert out.urdf.count("\n") == out.urdf.count("\r\n") == text.count("\r\n") + 2  # CRLF kept, and used
    assert "<!-- a comment -->" in out.urdf and "<!-- top -->" in out.urdf
    q, labels = sample(model, 20)
    x0 = x.copy()
    x0[K.layout(model, x).bases] = 0.0
    got = pin_points(out.urdf, model, out.side, q, labels, "base")
    assert np.abs(got - K.forward(model, x0, q, labels=labels)).max() < TOL_MM


def test_refuses_a_urdf_that_is_not_the_models():
    text, doc = imported("ur5_mdh")
    model = parse_model(doc)
    other = text.replace('<axis xyz="0 1 0"/>', '<axis xyz="1 0 0"/>', 1)
    with pytest.raises(ValueError, match="not the one the model was imported from"):
        patch_urdf(other, doc["urdf"], model, perturbed(model))
    no_source = {k: v for k, v in doc.items()}
    no_source["urdf"] = {k: v for k, v in doc["urdf"].items() if k != "source"}
    with pytest.raises(ValueError, match="no URDF source"):
        export_calibration(no_source, state_of(model, K.nominal_vector(model)))
