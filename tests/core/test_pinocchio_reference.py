"""Pinocchio as the reference kinematics on real URDFs (issue 30), with example-robot-data's robots.

1. FK equality: the target points of the model parse_urdf + parse_model make of a real URDF (MD-H or xyz form,
   m or mm) equal pinocchio's frame placements times the same point, at random configurations within the
   limits; joints matched by NAME, mimic joints set from the URDF's <mimic> tags (not from our coupled rows).
2. Completeness (noise-free): a "true" robot is the URDF with every joint origin moved by up to 0.5 mm and
   1 mrad (fixed joints too; the axis stays as written, so it turns with the origin), an SMR 30/20/50 mm off
   each target link, seen in a random tracker frame; its points come from PINOCCHIO on the perturbed URDF text,
   never from our kinematics. The NOMINAL model (imported from the unperturbed URDF, the SMR's nominal offset
   given as the target point) fitted to them without a prior must leave <= 1e-6 mm: a complete
   parameterisation absorbs any rigid error of any joint origin, base and target.

Skips when pinocchio or example-robot-data is absent (both are test extras in pyproject.toml).
benchmarks/urdf_completeness.py prints the same checks as a table.
"""
from __future__ import annotations

import importlib.metadata
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

from calib_core import kinematics as K  # noqa: E402
from calib_core.identify import identify  # noqa: E402
from calib_core.io import Measurements  # noqa: E402
from calib_core.model import parse_model  # noqa: E402
from calib_core.twin import sample_uniform  # noqa: E402
from calib_core.urdf import parse_urdf  # noqa: E402

SMR_MM = np.array([30.0, 20.0, 50.0])  # the SMR's offset in each target link's frame
FK_TOL_MM = 1e-9  # the xyz form: one row per URDF joint
FK_TOL_MDH_MM = 1e-8  # the MD-H fold rounds through nearly parallel axes (test_frames: 1.5e-9 mm seen; TIAGo 1.8e-9)
COMPLETE_TOL_MM = 1e-6  # issue 30's "done when"
SECOND_ORDER_MM = {"talos_arms_mimic": 1e-3}
"""Cases the 1e-6 mm bar does not hold for, and why: Talos's two arms to the fingertips leave up to 3.5e-4 mm RMS
(1.1e-3 max held out) over 31 seeds (seeds 0-29 and CI's 2064201877, c465453), all of it from the fingertip rows: gripper_*_inner_single_joint and gripper_*_fingertip_*_joint
turn about parallel axes, both coupled to one gripper joint (mimic -1). Perturbing only the fingertip row's origin
leaves 4e-5 mm against pinocchio and 3e-7 to 6e-7 mm against our own kinematics as the truth; the remainder falls with
the square of the error's size (0.05 mm / 0.1 mrad leaves at most 0.011 of it, 31 seeds). Freeing every parameter the pose set
tells at 1e-6 instead of 1e-3 at the estimate (78 -> 88) leaves 8e-6 mm; freeing all 194 that move a point (no
pruning, LM through the null space) reaches 1.6e-9 mm. So the rows are complete, and the minimal set chosen at
nominal, where the pair is exactly parallel, is not at a finite distance from it (as the coupled torso of
tests/core/test_completeness.py): 1000 times below a laser tracker's noise, and left so."""


# --- example-robot-data's URDFs ---------------------------------------------------------------------------

def erd_files(suffixes: tuple[str, ...] = (".urdf",)) -> dict[str, Path]:
    """File name -> path of every file with these suffixes that example-robot-data installs (cmeel prefix), {} when
    it is absent."""
    try:
        files = importlib.metadata.files("example-robot-data") or []
    except importlib.metadata.PackageNotFoundError:
        return {}
    out = {}
    for f in files:
        if str(f).endswith(suffixes):
            out.setdefault(Path(str(f)).name, Path(f.locate()))
    return out


ERD = erd_files()


def urdf_text(name: str) -> str:
    if name in LOCAL_URDFS:
        return LOCAL_URDFS[name]
    if name not in ERD:
        pytest.skip(f"example-robot-data has no {name} (installed: {len(ERD)} URDFs)")
    return ERD[name].read_text()


# --- two small robots written here (xyz/rpy/axis rows) -------------------------------------------------------

GANTRY = """<?xml version="1.0"?>
<robot name="gantry_xyz">
  <link name="world"/><link name="x_carriage"/><link name="y_carriage"/><link name="z_quill"/><link name="tool"/>
  <joint name="X" type="prismatic"><parent link="world"/><child link="x_carriage"/>
    <origin xyz="0.1 0.2 0.8" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="0" upper="1.2" effort="1" velocity="1"/>
  </joint>
  <joint name="Y" type="prismatic"><parent link="x_carriage"/><child link="y_carriage"/>
    <origin xyz="0 0.05 0.1" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="0" upper="0.9" effort="1" velocity="1"/>
  </joint>
  <joint name="Z" type="prismatic"><parent link="y_carriage"/><child link="z_quill"/>
    <origin xyz="0.04 0 -0.05" rpy="0 0 0"/><axis xyz="0 0 -1"/><limit lower="0" upper="0.5" effort="1" velocity="1"/>
  </joint>
  <joint name="tool_mount" type="fixed"><parent link="z_quill"/><child link="tool"/>
    <origin xyz="0 0 -0.15" rpy="0 0 0"/></joint>
</robot>
"""

# A UR-like 6R arm on a rail; shoulder_lift and elbow are parallel (the upper arm, 0.425 m, between them).
RAIL = """<?xml version="1.0"?>
<robot name="rail_6r">
  <link name="world"/><link name="carriage"/><link name="base_link"/><link name="shoulder_link"/>
  <link name="upper_arm_link"/><link name="forearm_link"/><link name="wrist_1_link"/><link name="wrist_2_link"/>
  <link name="wrist_3_link"/><link name="tool0"/>
  <joint name="rail" type="prismatic"><parent link="world"/><child link="carriage"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="0" upper="3.0" effort="1" velocity="1"/></joint>
  <joint name="carriage_mount" type="fixed"><parent link="carriage"/><child link="base_link"/>
    <origin xyz="0 0 0.05" rpy="0 0 1.5707963267948966"/></joint>
  <joint name="shoulder_pan_joint" type="revolute"><parent link="base_link"/><child link="shoulder_link"/>
    <origin xyz="0 0 0.089159" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="shoulder_lift_joint" type="revolute"><parent link="shoulder_link"/><child link="upper_arm_link"/>
    <origin xyz="0 0.13585 0" rpy="0 1.5707963267948966 0"/><axis xyz="0 1 0"/>
    <limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="elbow_joint" type="revolute"><parent link="upper_arm_link"/><child link="forearm_link"/>
    <origin xyz="0 -0.1197 0.425" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="wrist_1_joint" type="revolute"><parent link="forearm_link"/><child link="wrist_1_link"/>
    <origin xyz="0 0 0.39225" rpy="0 1.5707963267948966 0"/><axis xyz="0 1 0"/>
    <limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="wrist_2_joint" type="revolute"><parent link="wrist_1_link"/><child link="wrist_2_link"/>
    <origin xyz="0 0.093 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="wrist_3_joint" type="revolute"><parent link="wrist_2_link"/><child link="wrist_3_link"/>
    <origin xyz="0 0 0.09465" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-3.1" upper="3.1" effort="1" velocity="1"/></joint>
  <joint name="ee_fixed_joint" type="fixed"><parent link="wrist_3_link"/><child link="tool0"/>
    <origin xyz="0 0.0823 0" rpy="0 0 1.5707963267948966"/></joint>
</robot>
"""

LOCAL_URDFS = {"gantry.urdf": GANTRY, "rail_6r.urdf": RAIL}


# --- the cases -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    id: str
    file: str
    base: str | None
    targets: tuple[str, ...]
    form: str = "auto"
    length_unit: str = "mm"
    angle_unit: str = "rad"
    # for the completeness check: a named error of the truth on top of the random one, (joint, dxyz m, drpy rad)
    error: tuple = ()
    # the nominal target point: the SMR's offset (the user names it at import), or the target link's origin
    smr_known: bool = True
    note: str = ""


FK_CASES = [
    Case("ur5_tool0_mdh", "ur5_robot.urdf", None, ("tool0",), "auto", "mm"),
    Case("ur10_tool0_xyz_m_deg", "ur10_robot.urdf", None, ("tool0",), "xyz", "m", "deg"),
    Case("panda_fingers_mimic", "panda.urdf", None, ("panda_leftfinger", "panda_rightfinger"), "auto", "m",
         note="a tree of two fingers, finger_joint2 mimics finger_joint1"),
    Case("panda_tcp_mdh_m", "panda.urdf", None, ("panda_hand_tcp",), "mdh", "m"),
    Case("kinova_j2s6s200", "kinova.urdf", None, ("j2s6s200_end_effector",), "auto", "mm",
         note="continuous joints"),
    Case("xarm7", "xarm7.urdf", None, ("link_eef",), "auto", "mm"),
    Case("tiago_arm", "tiago.urdf", "base_footprint", ("arm_tool_link",), "auto", "mm",
         note="a prismatic torso lift"),
    Case("talos_left_mdh", "talos_full_v2.urdf", "base_link", ("gripper_left_base_link",), "mdh", "mm"),
    Case("talos_arms_fingertips", "talos_full_v2.urdf", "base_link",
         ("gripper_left_fingertip_1_link", "gripper_right_fingertip_3_link"), "xyz", "mm",
         note="a tree, two targets, mimic joints whose source is off the targets' paths"),
    Case("baxter_arms", "baxter.urdf", "base", ("left_gripper", "right_gripper"), "auto", "mm"),
    Case("baxter_right_finger_mimic", "baxter.urdf", "base", ("r_gripper_r_finger_tip",), "auto", "m",
         note="a chain ending in a prismatic mimic joint"),
    Case("pr2_left_finger_mimic", "pr2.urdf", "base_footprint", ("l_gripper_r_finger_tip_link",), "auto", "mm",
         note="prismatic torso, continuous joints, two revolute mimic joints on the chain"),
    Case("romeo_left_finger_mimic", "romeo.urdf", "base_link", ("LFinger13Link",), "auto", "mm"),
    Case("icub_arms", "icub.urdf", "base_link", ("l_gripper", "r_gripper"), "auto", "m", "deg"),
]

COMPLETE_CASES = [
    Case("talos_left_xyz", "talos_full_v2.urdf", "base_link", ("gripper_left_base_link",), "xyz"),
    Case("talos_left_mdh", "talos_full_v2.urdf", "base_link", ("gripper_left_base_link",), "mdh"),
    Case("talos_arms", "talos_full_v2.urdf", "base_link", ("gripper_left_base_link", "gripper_right_base_link"),
         "xyz", note="a tree: the torso shared by two arms, two targets"),
    Case("talos_arms_mimic", "talos_full_v2.urdf", "base_link",
         ("gripper_left_fingertip_1_link", "gripper_right_fingertip_3_link"), "xyz"),
    Case("baxter_arms", "baxter.urdf", "base", ("left_gripper", "right_gripper"), "auto"),
    Case("tiago_arm", "tiago.urdf", "base_footprint", ("arm_tool_link",), "auto"),
    Case("ur5_tool0_mdh", "ur5_robot.urdf", None, ("tool0",), "mdh"),
    Case("ur5_tool0_xyz", "ur5_robot.urdf", None, ("tool0",), "xyz"),
    Case("ur5_tool0_mdh_target_at_origin", "ur5_robot.urdf", None, ("tool0",), "mdh", smr_known=False,
         note="the nominal target at tool0's origin, on the last joint axis; the real SMR 30/20/50 mm off it"),
    Case("gantry_xyz_squareness", "gantry.urdf", None, ("tool",), "xyz", error=(("Y", (0, 0, 0), (0, 0, 0.8e-3)),),
         note="X, Y, Z linear axes, Y 0.8 mrad out of square with X"),
    Case("rail_6r_xyz_upper_arm", "rail_6r.urdf", None, ("tool0",), "xyz",
         error=(("elbow_joint", (0, 0, 0.6e-3), (0, 0, 0)),),
         note="a 6R arm on a rail, the upper arm 0.6 mm longer between its parallel axes"),
]


# --- our side ---------------------------------------------------------------------------------------------

def _rpy_matrix(rpy) -> np.ndarray:
    return np.asarray(pin.rpy.rpyToMatrix(*map(float, rpy)))


def model_doc(case: Case, text: str, smr_mm=SMR_MM) -> dict:
    """parse_urdf's contract model of the case with the SMR (mm, in each target link's frame) as target point."""
    doc = parse_urdf(text, case.base, list(case.targets) if len(case.targets) > 1 else case.targets[0],
                     length_unit=case.length_unit, angle_unit=case.angle_unit, form=case.form)
    to_unit = 1.0 if case.length_unit == "mm" else 1e-3
    an = 1.0 if case.angle_unit == "rad" else math.pi / 180.0
    p = np.asarray(smr_mm, float) * to_unit
    if "tool" in doc:  # MD-H: the tool point in the last MD-H frame; the target link turned by tool_rpy in it
        C = _rpy_matrix(np.array(doc["urdf"]["tool_rpy"]) * an)
        doc["tool"] = [float(v) for v in np.asarray(doc["tool"], float) + C @ p]
    else:
        for t in doc["targets"]:
            t["xyz"] = [float(v) for v in np.asarray(t["xyz"], float) + p]
    return doc


def model_base_in_urdf_base(doc: dict) -> np.ndarray:
    """4x4 (mm) of the model's base frame in the URDF base link: the MD-H form's base_xyz / base_rpy, else I."""
    ext = doc.get("urdf", {})
    T = np.eye(4)
    if "base_xyz" in ext:
        mm = 1.0 if doc["units"]["length"] == "mm" else 1000.0
        an = 1.0 if doc["units"]["angle"] == "rad" else math.pi / 180.0
        T[:3, :3] = _rpy_matrix(np.array(ext["base_rpy"]) * an)
        T[:3, 3] = np.array(ext["base_xyz"]) * mm
    return T


def our_points(model, doc: dict, rows: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
    """(T, N, 3) mm: each target's point in the URDF base link at row values `rows` (internal units)."""
    x = K.nominal_vector(model) if x is None else x
    Tb = model_base_in_urdf_base(doc)
    out = []
    for t in range(model.n_targets):
        lab = K.Labels(np.full(len(rows), t), np.zeros(len(rows), int)) if model.n_targets > 1 else None
        p = K.forward(model, x, rows, None, lab)
        out.append(p @ Tb[:3, :3].T + Tb[:3, 3])
    return np.array(out)


def urdf_values(model, rows: np.ndarray) -> list[dict[str, float]]:
    """Per configuration the ACTUATED joints' values in URDF units (rad, m), by name; coupled rows left out."""
    names = model.actuated_names
    act = model.actuated
    scale = np.where(model.prismatic[act], 1e-3, 1.0)
    return [dict(zip(names, r[act] * scale)) for r in rows]


# --- pinocchio's side -------------------------------------------------------------------------------------

def urdf_mimics(text: str) -> dict[str, tuple[str, float, float]]:
    """joint -> (source joint, multiplier, offset) from the URDF's <mimic> tags."""
    out = {}
    for j in ET.fromstring(text).findall("joint"):
        m = j.find("mimic")
        if m is not None and j.get("type") != "fixed":
            out[j.get("name")] = (m.get("joint"), float(m.get("multiplier", "1")), float(m.get("offset", "0")))
    return out


class PinRobot:
    """Pinocchio's model of a URDF text (mimic joints as ordinary joints, set here from their <mimic> tags)."""

    def __init__(self, text: str):
        self.model = pin.buildModelFromXML(text)
        self.data = self.model.createData()
        self.mimic = urdf_mimics(text)

    def _value(self, name: str, values: dict, depth: int = 0) -> float | None:
        if name in values:
            return values[name]
        if name in self.mimic and depth < 20:
            src, k, off = self.mimic[name]
            v = self._value(src, values, depth + 1)
            return None if v is None else k * v + off
        return None

    def config(self, values: dict[str, float]) -> np.ndarray:
        """pinocchio's q for joint values (rad, m) by NAME; joints not given (nor mimicking one given) neutral."""
        m = self.model
        q = pin.neutral(m)
        for jid in range(1, m.njoints):
            v = self._value(m.names[jid], values)
            if v is None:
                continue
            jm = m.joints[jid]
            if jm.nq == 2:  # continuous: cos, sin
                q[jm.idx_q], q[jm.idx_q + 1] = math.cos(v), math.sin(v)
            elif jm.nq == 1:
                q[jm.idx_q] = v
            else:
                raise AssertionError(f"joint {m.names[jid]} has nq={jm.nq}")
        return q

    def link_points(self, values: list[dict], base: str, links, point_mm) -> np.ndarray:
        """(T, N, 3) mm: point_mm in each link's frame, in the base link's frame."""
        m, d = self.model, self.data
        fb = m.getFrameId(base, pin.FrameType.BODY)
        fl = [m.getFrameId(ln, pin.FrameType.BODY) for ln in links]
        assert fb < m.nframes and all(f < m.nframes for f in fl), (base, links)
        p = np.asarray(point_mm, float) * 1e-3
        out = np.empty((len(links), len(values), 3))
        for i, v in enumerate(values):
            pin.framesForwardKinematics(m, d, self.config(v))
            inv_b = d.oMf[fb].inverse()
            for t, f in enumerate(fl):
                out[t, i] = (inv_b * d.oMf[f]).act(p) * 1e3
        return out


def base_link_of(text: str, case: Case) -> str:
    if case.base is not None:
        return case.base
    root = ET.fromstring(text)
    children = {j.find("child").get("link") for j in root.findall("joint")}
    roots = [ln.get("name") for ln in root.findall("link") if ln.get("name") not in children]
    assert len(roots) == 1, roots
    return roots[0]


# --- FK equality ------------------------------------------------------------------------------------------

def fk_error(case: Case, n: int = 300, seed: int = 0) -> tuple[float, str, int]:
    """Largest distance (mm) between our target points and pinocchio's over n random configurations, the form
    the import chose ("mdh" / "xyz") and the number of model rows."""
    text = urdf_text(case.file)
    doc = model_doc(case, text)
    model = parse_model(doc)
    rows = sample_uniform(model, n, np.random.default_rng(seed))
    ours = our_points(model, doc, rows)
    ref = PinRobot(text).link_points(urdf_values(model, rows), base_link_of(text, case), case.targets, SMR_MM)
    return float(np.linalg.norm(ours - ref, axis=-1).max()), form_of(doc), model.n_joints


def form_of(doc: dict) -> str:
    return "mdh" if "tool" in doc else "xyz"


@pytest.mark.parametrize("case", FK_CASES, ids=[c.id for c in FK_CASES])
def test_forward_kinematics_equal_pinocchio(case, seed):
    err, form, _ = fk_error(case, seed=seed)
    assert err <= (FK_TOL_MDH_MM if form == "mdh" else FK_TOL_MM), (err, form, f"seed {seed}")


@pytest.mark.parametrize("case", FK_CASES, ids=[c.id for c in FK_CASES])
def test_the_reference_is_not_pinocchio_alone(case):
    """yourdfpy (its own URDF reader, its own mimic handling: only the actuated joints are given to it) places
    the same points as pinocchio: the reference is two independent implementations."""
    yourdfpy = pytest.importorskip("yourdfpy")
    import io
    text = urdf_text(case.file)
    model = parse_model(model_doc(case, text))
    rows = sample_uniform(model, 10, np.random.default_rng(3))
    vals, base = urdf_values(model, rows), base_link_of(text, case)
    ref = PinRobot(text).link_points(vals, base, case.targets, SMR_MM)
    u = yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=True, load_meshes=False,
                           load_collision_meshes=False)
    for i, v in enumerate(vals):
        u.update_cfg({k: x for k, x in v.items() if k in u.actuated_joint_names})
        for t, link in enumerate(case.targets):
            T = u.get_transform(link, base)
            assert np.abs((T[:3, :3] @ SMR_MM + T[:3, 3] * 1e3) - ref[t, i]).max() < FK_TOL_MM


def test_fk_cases_cover_the_issue():
    """At least 10 real URDFs, a tree with two targets and a chain with a mimic joint among them."""
    assert len({c.file for c in FK_CASES}) >= 10
    assert any(len(c.targets) > 1 for c in FK_CASES)
    assert any("mimic" in c.id and len(c.targets) == 1 for c in FK_CASES)


# --- completeness -----------------------------------------------------------------------------------------

def _small_rotation(rng: np.random.Generator, max_rad: float) -> np.ndarray:
    w = rng.normal(size=3)
    return np.asarray(pin.exp3(w / np.linalg.norm(w) * rng.uniform(0, max_rad)))


def perturbed_urdf(text: str, seed: int, max_mm: float = 0.5, max_mrad: float = 1.0, error=()) -> str:
    """The URDF with every joint's origin moved by up to max_mm (a random direction) and turned by up to max_mrad
    (a random axis, after the written rpy); the axis stays as written (it turns with the origin). `error`:
    (joint, dxyz m, drpy rad) added to the named joints' written xyz / rpy first."""
    root = ET.fromstring(text)
    rng = np.random.default_rng(seed)
    named = {j: (np.array(dx, float), np.array(dr, float)) for j, dx, dr in error}
    seen = set()
    for j in root.findall("joint"):  # not the <joint>s of a <transmission>
        o = j.find("origin")
        if o is None:
            o = ET.SubElement(j, "origin")
        xyz = np.array([float(v) for v in o.get("xyz", "0 0 0").split()])
        rpy = np.array([float(v) for v in o.get("rpy", "0 0 0").split()])
        if j.get("name") in named:
            dx, dr = named[j.get("name")]
            xyz, rpy = xyz + dx, rpy + dr
            seen.add(j.get("name"))
        d = rng.normal(size=3)
        xyz = xyz + d / np.linalg.norm(d) * rng.uniform(0, max_mm * 1e-3)
        R = _rpy_matrix(rpy) @ _small_rotation(rng, max_mrad * 1e-3)
        o.set("xyz", " ".join(repr(float(v)) for v in xyz))
        o.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(R)))
    assert seen == set(named), f"no joint {set(named) - seen}"
    return ET.tostring(root, encoding="unicode")


@dataclass
class Completeness:
    case: str
    n_params: int
    rms_mm: float
    max_mm: float
    holdout_max_mm: float
    n_rows: int
    form: str = ""


def completeness(case: Case, n: int = 300, n_test: int = 100, seed: int = 0, max_mm: float = 0.5,
                 max_mrad: float = 1.0) -> Completeness:
    """Fit the nominal model to noise-free points of the perturbed URDF (pinocchio's), tracker frame random."""
    text = urdf_text(case.file)
    doc = model_doc(case, text, SMR_MM if case.smr_known else np.zeros(3))
    model = parse_model(doc)
    truth = PinRobot(perturbed_urdf(text, seed, max_mm, max_mrad, error=case.error))
    base = base_link_of(text, case)
    rng = np.random.default_rng(seed + 1)
    Rt = np.asarray(pin.exp3(rng.normal(size=3)))
    tt = rng.uniform(-3000, 3000, 3)

    def measure(rows):
        pts = truth.link_points(urdf_values(model, rows), base, case.targets, SMR_MM) @ Rt.T + tt  # (T, N, 3)
        T, N = pts.shape[:2]
        return Measurements(joints=np.tile(rows, (T, 1)), points=pts.reshape(-1, 3), sigma=np.full(T * N, 1e-3),
                            target=np.repeat(np.arange(T), N), setup=np.zeros(T * N, int))

    meas = measure(sample_uniform(model, n, rng))
    cal = identify(model, meas, regularize=False, folds=0)
    r = np.linalg.norm(cal.predict(meas.joints, meas) - meas.points, axis=1)
    fresh = measure(sample_uniform(model, n_test, rng))
    h = np.linalg.norm(cal.predict(fresh.joints, fresh) - fresh.points, axis=1)
    return Completeness(case.id, len(cal.free), float(np.sqrt(np.mean(r ** 2))), float(r.max()), float(h.max()),
                        meas.n_poses, form_of(doc))


def test_the_truth_is_pinocchios_and_differs_from_nominal():
    """The perturbed URDF moves the points by a fraction of a mm to a few mm (the check has something to find),
    and an unperturbed "truth" equals our nominal model (the harness's frames and units agree)."""
    case = COMPLETE_CASES[0]
    text = urdf_text(case.file)
    doc = model_doc(case, text)
    model = parse_model(doc)
    rows = sample_uniform(model, 50, np.random.default_rng(5))
    vals, base = urdf_values(model, rows), base_link_of(text, case)
    nominal = PinRobot(text).link_points(vals, base, case.targets, SMR_MM)
    assert np.abs(our_points(model, doc, rows) - nominal).max() < FK_TOL_MM
    moved = PinRobot(perturbed_urdf(text, 0)).link_points(vals, base, case.targets, SMR_MM)
    d = np.linalg.norm(moved - nominal, axis=-1)
    assert 0.2 < d.max() < 20.0
    same = PinRobot(perturbed_urdf(text, 0, 0.0, 0.0)).link_points(vals, base, case.targets, SMR_MM)
    assert np.abs(same - nominal).max() < 1e-9


@pytest.mark.parametrize("case", COMPLETE_CASES, ids=[c.id for c in COMPLETE_CASES])
def test_noise_free_fit_of_a_perturbed_urdf_is_exact(case, seed):
    """Issue 30's "done when": <= 1e-6 mm RMS left; the fit also predicts 100 new configurations to 1e-5 mm."""
    res = completeness(case, seed=seed)
    tol = SECOND_ORDER_MM.get(case.id, COMPLETE_TOL_MM)
    assert res.rms_mm <= tol, (res, f"seed {seed}")
    assert res.holdout_max_mm <= 10 * tol, (res, f"seed {seed}")
    if case.id in SECOND_ORDER_MM:  # what is left is second order: a tenth of the error leaves a hundredth
        small = completeness(case, seed=seed, max_mm=0.05, max_mrad=0.1)
        assert small.rms_mm <= 0.03 * max(res.rms_mm, 1e-9) + 1e-9, (res, small, f"seed {seed}")
