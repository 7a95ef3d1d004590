"""URDF in and out (contract section 5) for serial chains.

:func:`parse_urdf` reads a URDF, picks the chain from a base link to a target link, folds every joint
(origin xyz/rpy, any axis, fixed joints in between) exactly into contract MD-H rows with
:func:`calib_core.frames.fold_links` and writes contract model JSON; :func:`to_urdf` writes a model (or a
calibrated model) back as a URDF whose joint origins carry the MD-H rows.

Conventions

* URDF is always m and rad. The model is written in ``length_unit`` / ``angle_unit`` (default m / rad).
* A joint's child frame is ``parent @ origin(xyz, rpy) @ motion(axis, q)`` with ``R(rpy) = Rz(y) Ry(p) Rx(r)``
  (fixed axes). The axis need not be z: the frame is turned so that the axis is its z (:func:`align_z`),
  and the turn is undone in front of the next joint.
* ``continuous`` joints are revolute with limits of +-``CONTINUOUS_LIMIT_RAD`` (the model wants limits for
  sampling and compensation; one turn each way covers every orientation).
* Nearly parallel consecutive axes (within ``PARALLEL_SIN``) are folded in Hayati's form (``beta``).
* Gravity is -z of the URDF base link (9.81 m/s^2), rotated into the MD-H base frame.
* Masses: the body moved by joint i is its child link plus every link fixed to it (through ``fixed``
  joints, side branches included); its mass is the sum and its centre of mass is written in the joint's
  MD-H frame. Links behind a movable joint that is not on the chain are not counted (trees: later).
* What MD-H cannot say about the URDF frames goes into the model's ``"urdf"`` object (an extension; the
  contract's parsers ignore it): the URDF base and target link names, the pose of the MD-H base frame in the
  URDF base link (``base_xyz``, ``base_rpy``) and the orientation of the target link in the last MD-H frame
  (``tool_rpy``), both in model units, which joints were ``continuous`` and their effort / velocity limits.
  :func:`to_urdf` uses it, so URDF -> model -> URDF keeps the base and target link frames, not only the
  point.

Not yet: mimic joints on the chain (a clear error names the joint; the contract's ``coupled`` joints will
take them), several targets / trees, ``floating`` and ``planar`` joints on the chain.

Security: the text is refused when it carries a DOCTYPE (so no entity declarations, no entity expansion,
no external entities), the way defusedxml does.
"""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from .frames import Link, fold_links, mdh_transform, rot_x, rot_y, rot_z
from .io import NUMBER
from .model import ANGLE_TO_RAD, LENGTH_TO_MM, MAX_LENGTH_MM, ModelError, RobotModel, parse_model

CONTINUOUS_LIMIT_RAD = 2.0 * math.pi
"""Limits written for a URDF ``continuous`` joint: one turn each way."""
MAX_URDF_CHARS = 20_000_000
"""A URDF larger than this is refused (the largest real ones, with inline meshes, are a few MB)."""
MAX_LENGTH_M = MAX_LENGTH_MM / 1000.0
"""|x|, |y|, |z| of a joint origin (m): the model's own plausibility bound."""
MOVABLE = ("revolute", "continuous", "prismatic")
KNOWN_TYPES = (*MOVABLE, "fixed", "floating", "planar")
GRAVITY = (0.0, 0.0, -9.81)
PARALLEL_SIN = 0.05
"""Consecutive axes closer than this to parallel (|sin| < 0.05, about 3 deg) take Hayati's form (d = 0, beta)
rather than the common normal, which would lie up to 1/|sin| link lengths away (d of hundreds of metres for a
calibrated model whose parallel axes are tilted by a milliradian). Both forms are exact."""
EXTENSION = "urdf"
"""The model-JSON key of the URDF extension object."""

_DOCTYPE = re.compile(r"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)


class UrdfError(ModelError):
    """A URDF that cannot be read as a serial chain; `errors` lists {field, value, message}, the field naming
    the element and attribute (e.g. ``joint[@name='elbow']/origin/@xyz``)."""


# --- small geometry -------------------------------------------------------------------

def rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF rotation (4x4): Rz(y) Ry(p) Rx(r)."""
    return rot_z(y) @ rot_y(p) @ rot_x(r)


def origin_matrix(xyz, rpy) -> np.ndarray:
    T = rpy_matrix(*rpy)
    T[:3, 3] = xyz
    return T


def matrix_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw of a rotation; exact to rounding also at and near pitch = +-90 deg (the yaw is
    taken first and removed before roll and pitch are read, so an ill-defined yaw costs nothing)."""
    R = np.asarray(R, float)[:3, :3]
    y = math.atan2(R[1, 0], R[0, 0])
    Rp = rot_z(-y)[:3, :3] @ R  # = Ry(p) Rx(r)
    p = math.atan2(-Rp[2, 0], Rp[0, 0])
    r = math.atan2(-Rp[1, 2], Rp[1, 1])
    return r, p, y


def align_z(axis: np.ndarray) -> np.ndarray:
    """A rotation (4x4) whose z column is the unit vector `axis` (the smallest turn from z)."""
    u = np.asarray(axis, float)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    T = np.eye(4)
    if c > 1.0 - 1e-15:
        return T
    if c < -1.0 + 1e-15:
        return rot_x(math.pi)
    k = np.cross(z, u)
    s = float(np.linalg.norm(k))
    k = k / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    T[:3, :3] = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    return T


# --- reading -------------------------------------------------------------------------

@dataclass
class _Joint:
    name: str
    type: str
    parent: str
    child: str
    xyz: np.ndarray
    rpy: np.ndarray
    axis: np.ndarray
    lower: float | None
    upper: float | None
    effort: float | None
    velocity: float | None
    mimic: str | None
    where: str


def _where(kind: str, name) -> str:
    return f"{kind}[@name={name!r}]" if name is not None else kind


def _numbers(errors, el, attr, where, n, default):
    """Whitespace-separated finite numbers of an attribute."""
    if el is None or el.get(attr) is None:
        return None if default is None else np.array(default, float)
    text = el.get(attr)
    parts = text.split()
    out = []
    for p in parts:
        v = float(p) if NUMBER.fullmatch(p) else math.nan
        if not math.isfinite(v):
            errors.append({"field": f"{where}/@{attr}", "value": text[:80],
                           "message": f"{p[:40]!r} is not a finite number"})
            return None
        out.append(v)
    if len(out) != n:
        errors.append({"field": f"{where}/@{attr}", "value": text[:80],
                       "message": f"needs {n} number{'s' * (n != 1)} separated by spaces, got {len(out)}"})
        return None
    return np.array(out, float)


def _one(errors, el, attr, where):
    v = _numbers(errors, el, attr, where, 1, None)
    return None if v is None else float(v[0])


def _read(text) -> ET.Element:
    if isinstance(text, (bytes, bytearray)):
        try:
            text = bytes(text).decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise UrdfError([{"field": "urdf", "value": f"byte {exc.start}",
                              "message": "the URDF is not UTF-8 text"}]) from None
    if not isinstance(text, str):
        raise UrdfError([{"field": "urdf", "value": type(text).__name__, "message": "the URDF must be text"}])
    if len(text) > MAX_URDF_CHARS:
        raise UrdfError([{"field": "urdf", "value": len(text),
                          "message": f"the URDF is larger than {MAX_URDF_CHARS} characters"}])
    m = _DOCTYPE.search(text)
    if m:
        line = text.count("\n", 0, m.start()) + 1
        raise UrdfError([{"field": "urdf", "value": f"line {line}: {m.group()}",
                          "message": "a DOCTYPE or ENTITY declaration is refused (entity expansion); "
                                     "a URDF needs neither"}])
    if "\x00" in text:
        raise UrdfError([{"field": "urdf", "value": None, "message": "the URDF must not contain a NUL character"}])
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        line, col = exc.position
        raise UrdfError([{"field": "urdf", "value": f"line {line}, column {col + 1}",
                          "message": f"not well-formed XML: {str(exc).split(':')[0]}"}]) from None
    if root.tag != "robot":
        raise UrdfError([{"field": root.tag, "value": root.tag,
                          "message": "the root element of a URDF must be <robot>"}])
    return root


def _parse_joints(root: ET.Element):
    errors: list[dict] = []
    links: dict[str, ET.Element] = {}
    for el in root.findall("link"):
        name = el.get("name")
        if not name:
            errors.append({"field": "link/@name", "value": name, "message": "every <link> needs a name"})
        elif name in links:
            errors.append({"field": _where("link", name), "value": name, "message": "duplicate link name"})
        else:
            links[name] = el
    joints: dict[str, _Joint] = {}
    for el in root.findall("joint"):
        name = el.get("name")
        where = _where("joint", name)
        if not name:
            errors.append({"field": "joint/@name", "value": name, "message": "every <joint> needs a name"})
            continue
        if name in joints:
            errors.append({"field": where, "value": name, "message": "duplicate joint name"})
            continue
        jtype = el.get("type")
        if jtype not in KNOWN_TYPES:
            errors.append({"field": f"{where}/@type", "value": jtype,
                           "message": f"unknown joint type; a URDF joint is one of {', '.join(KNOWN_TYPES)}"})
            continue
        ends = {}
        for tag in ("parent", "child"):
            e = el.find(tag)
            ln = None if e is None else e.get("link")
            if not ln:
                errors.append({"field": f"{where}/{tag}/@link", "value": ln,
                               "message": f"the joint needs a <{tag} link=...>"})
            elif ln not in links:
                errors.append({"field": f"{where}/{tag}/@link", "value": ln, "message": "no <link> of that name"})
            ends[tag] = ln
        o = el.find("origin")
        xyz = _numbers(errors, o, "xyz", f"{where}/origin", 3, (0.0, 0.0, 0.0))
        if xyz is not None and not np.abs(xyz).max() <= MAX_LENGTH_M:
            errors.append({"field": f"{where}/origin/@xyz", "value": o.get("xyz")[:80],
                           "message": f"implausible: each component must be at most {MAX_LENGTH_M:g} m"})
            xyz = None
        rpy = _numbers(errors, o, "rpy", f"{where}/origin", 3, (0.0, 0.0, 0.0))
        axis = _numbers(errors, el.find("axis"), "xyz", f"{where}/axis", 3, (1.0, 0.0, 0.0))  # URDF default: x
        if axis is not None and jtype in MOVABLE:
            nrm = float(np.linalg.norm(axis))
            if not nrm > 1e-9:
                errors.append({"field": f"{where}/axis/@xyz", "value": el.find("axis").get("xyz"),
                               "message": "the joint axis must not be the zero vector"})
                axis = None
            else:
                axis = axis / nrm
        lim = el.find("limit")
        lower = upper = effort = velocity = None
        if lim is not None:
            lower, upper = _one(errors, lim, "lower", f"{where}/limit"), _one(errors, lim, "upper", f"{where}/limit")
            effort = _one(errors, lim, "effort", f"{where}/limit")
            velocity = _one(errors, lim, "velocity", f"{where}/limit")
        mimic = el.find("mimic")
        joints[name] = _Joint(name, jtype, ends.get("parent"), ends.get("child"), xyz, rpy, axis, lower, upper,
                              effort, velocity, None if mimic is None else (mimic.get("joint") or "?"), where)
    if errors:
        raise UrdfError(errors)
    by_child: dict[str, _Joint] = {}
    for j in joints.values():
        if j.child in by_child:
            errors.append({"field": f"{j.where}/child/@link", "value": j.child,
                           "message": f"link {j.child!r} is already the child of joint {by_child[j.child].name!r}; "
                                      "a URDF is a tree (one parent joint per link)"})
        else:
            by_child[j.child] = j
    if errors:
        raise UrdfError(errors)
    return links, joints, by_child


def _path(links, joints, by_child, base, target) -> list[_Joint]:
    children: dict[str, list[_Joint]] = {}
    for j in joints.values():
        children.setdefault(j.parent, []).append(j)
    if base is None:
        roots = [ln for ln in links if ln not in by_child]
        if len(roots) != 1:
            raise UrdfError([{"field": "link", "value": roots, "message":
                              f"the URDF has {len(roots)} root links ({', '.join(roots) or 'none: a cycle'}); "
                              "name the chain's base link"}])
        base = roots[0]
    elif base not in links:
        raise UrdfError([{"field": "base", "value": base, "message": f"no link {base!r} in the URDF"}])
    if target is None:
        leaves, stack, seen = [], [base], set()
        while stack:
            ln = stack.pop()
            if ln in seen:
                continue
            seen.add(ln)
            kids = children.get(ln, [])
            if not kids and ln != base:
                leaves.append(ln)
            stack.extend(j.child for j in kids)
        if len(leaves) != 1:
            raise UrdfError([{"field": "target", "value": sorted(leaves), "message":
                              f"the URDF has {len(leaves)} leaf links below {base!r} ({', '.join(sorted(leaves))}); "
                              "name the target link (the measured point's link)"}])
        target = leaves[0]
    elif target not in links:
        raise UrdfError([{"field": "target", "value": target, "message": f"no link {target!r} in the URDF"}])
    path, ln = [], target
    while ln != base:
        j = by_child.get(ln)
        if j is None or len(path) > len(joints):
            raise UrdfError([{"field": "target", "value": target, "message":
                              f"link {target!r} is not below the base link {base!r} (the chain must go from the base "
                              "down to the target)"}])
        path.append(j)
        ln = j.parent
    return base, target, path[::-1], children


def _link_mass(el: ET.Element, name: str, scale: float, errors: list):
    """(mass kg, com in the link frame, model length unit) of a <link>'s <inertial>, or None."""
    inertial = el.find("inertial")
    if inertial is None:
        return None
    where = f"{_where('link', name)}/inertial"
    m_el = inertial.find("mass")
    m = _one(errors, m_el, "value", f"{where}/mass") if m_el is not None else None
    if m is None:
        if m_el is None or m_el.get("value") is None:
            errors.append({"field": f"{where}/mass/@value", "value": None,
                           "message": "an <inertial> needs <mass value=...>"})
        return None
    if m < 0:
        errors.append({"field": f"{where}/mass/@value", "value": m, "message": "a mass must not be negative"})
        return None
    o = inertial.find("origin")
    xyz = _numbers(errors, o, "xyz", f"{where}/origin", 3, (0.0, 0.0, 0.0))
    rpy = _numbers(errors, o, "rpy", f"{where}/origin", 3, (0.0, 0.0, 0.0))  # checked; the COM needs no turn
    if xyz is None or rpy is None:
        return None
    return m, xyz * scale


def parse_urdf(text: str | bytes, base: str | None = None, target: str | None = None, *,
               length_unit: str = "m", angle_unit: str = "rad", name: str | None = None) -> dict:
    """Contract model JSON (MD-H, ``length_unit`` / ``angle_unit``) of the URDF chain from `base` (default: the
    root link) to `target` (default: the only leaf below the base). Raises :class:`UrdfError` (a ValueError)
    naming the element, attribute and value of every problem found."""
    if length_unit not in LENGTH_TO_MM or angle_unit not in ANGLE_TO_RAD:
        raise ValueError("length_unit must be 'm' or 'mm' and angle_unit 'rad' or 'deg'")
    scale = 1000.0 / LENGTH_TO_MM[length_unit]  # URDF m -> model length unit
    ang = math.degrees if angle_unit == "deg" else float
    root = _read(text)
    links, joints, by_child = _parse_joints(root)
    base, target, path, children = _path(links, joints, by_child, base, target)

    errors: list[dict] = []
    chain_links: list[Link] = []
    extra_limits: dict[str, dict] = {}
    continuous: list[str] = []
    pending = np.eye(4)
    for j in path:
        T = origin_matrix(j.xyz * scale, j.rpy)
        if j.type == "fixed":
            pending = pending @ T
            continue
        if j.type in ("floating", "planar"):
            errors.append({"field": f"{j.where}/@type", "value": j.type, "message":
                           f"a {j.type} joint on the chain {base} -> {target} is not supported (a serial chain of "
                           "revolute, continuous, prismatic and fixed joints is)"})
            continue
        if j.mimic is not None:
            errors.append({"field": f"{j.where}/mimic", "value": j.mimic, "message":
                           f"joint {j.name!r} mimics {j.mimic!r}: mimic (coupled) joints are not yet supported by the "
                           "URDF import; choose a chain without it (?base=LINK below it)"})
            continue
        if j.type == "continuous":
            lim = (-CONTINUOUS_LIMIT_RAD, CONTINUOUS_LIMIT_RAD)
            continuous.append(j.name)
        else:
            if j.lower is None or j.upper is None:
                errors.append({"field": f"{j.where}/limit", "value": None, "message":
                               f"a {j.type} joint needs <limit lower=... upper=...> (use type continuous for an "
                               "unlimited revolute joint)"})
                continue
            if not j.lower < j.upper:
                errors.append({"field": f"{j.where}/limit", "value": [j.lower, j.upper],
                               "message": "the lower limit must be below the upper limit"})
                continue
            lim = (j.lower * scale, j.upper * scale) if j.type == "prismatic" else (j.lower, j.upper)
        extra_limits[j.name] = {k: v for k, v in (("effort", j.effort), ("velocity", j.velocity)) if v is not None}
        R = align_z(j.axis)
        chain_links.append(Link(pending @ T @ R, "prismatic" if j.type == "prismatic" else "revolute", j.name, lim))
        pending = R.T.copy()
    if errors:
        raise UrdfError(errors)
    if not chain_links:
        raise UrdfError([{"field": "joint", "value": [j.name for j in path], "message":
                          f"the chain {base} -> {target} has no revolute, continuous or prismatic joint"}])
    tool_T = pending
    try:
        folded = fold_links(chain_links, tool_T[:3, 3], gravity=GRAVITY, parallel_tol=PARALLEL_SIN)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        raise UrdfError([{"field": "joint", "value": [lk.name for lk in chain_links],
                          "message": f"the chain {base} -> {target} cannot be folded into MD-H rows: {exc}"}]) from None
    robot_name = name or root.get("name") or "robot"
    doc = folded.model_dict(robot_name, length_unit=length_unit, angle_unit=angle_unit)

    # frames at q = 0 in the URDF base: the last joint's (aligned) frame, every MD-H frame
    n = folded.n_joints
    T_last = np.eye(4)
    for lk in chain_links:
        T_last = T_last @ lk.transform
    mdh0 = [folded.base @ F for F in folded.frames(np.zeros(n))]
    C = np.linalg.inv(mdh0[-1]) @ T_last @ tool_T  # target link frame in the last MD-H frame
    ext: dict[str, Any] = {
        "robot": root.get("name"), "base_link": base, "target_link": target,
        "base_xyz": [float(v) for v in folded.base[:3, 3]],
        "base_rpy": [ang(v) + 0.0 for v in matrix_rpy(folded.base)],
        "tool_rpy": [ang(v) + 0.0 for v in matrix_rpy(C)],
        "continuous": continuous,
        "limits": {k: v for k, v in extra_limits.items() if v},
    }

    # masses: each movable joint's child link and everything fixed to it, at q = 0 in the URDF base
    pose = {base: np.eye(4)}
    stack = [base]
    while stack:
        ln = stack.pop()
        for j in children.get(ln, []):
            if j.child not in pose and j.xyz is not None and j.rpy is not None:
                pose[j.child] = pose[ln] @ origin_matrix(j.xyz * scale, j.rpy)
                stack.append(j.child)
    movable = [j for j in path if j.type in MOVABLE]
    masses, coms, any_inertial = [], [], False
    for i, j in enumerate(movable):
        body, stack = [], [j.child]
        while stack:
            ln = stack.pop()
            body.append(ln)
            stack.extend(k.child for k in children.get(ln, []) if k.type == "fixed")
        m_tot, moment = 0.0, np.zeros(3)
        for ln in body:
            mc = _link_mass(links[ln], ln, scale, errors)
            if mc is None:
                continue
            any_inertial = True
            m, c = mc
            m_tot += m
            moment += m * (pose[ln] @ np.r_[c, 1.0])[:3]
        com_base = moment / m_tot if m_tot > 0 else mdh0[i][:3, 3]
        masses.append(m_tot)
        coms.append((np.linalg.inv(mdh0[i]) @ np.r_[com_base, 1.0])[:3])
    if errors:
        raise UrdfError(errors)
    if any_inertial:
        for row, m, c in zip(doc["joints"], masses, coms):
            row["mass"] = float(m)
            row["com"] = [float(0.0 if abs(v) < 1e-15 * max(1.0, scale) else v) for v in c]
    doc[EXTENSION] = ext
    try:
        parse_model(doc)
    except ModelError as exc:
        raise UrdfError([{**e, "field": f"{_model_field_to_urdf(e['field'], doc)} (model {e['field']})"}
                         for e in exc.errors]) from None
    return doc


def _model_field_to_urdf(field: str, doc: dict) -> str:
    m = re.match(r"joints\[(\d+)\]", field)
    if m and int(m.group(1)) < len(doc["joints"]):
        return _where("joint", doc["joints"][int(m.group(1))]["name"])
    return "robot" if field in ("name", "") else field


# --- writing -------------------------------------------------------------------------

def calibrated_model_dict(model: RobotModel, state: dict, source: dict | None = None) -> dict:
    """The calibrated model as contract JSON: the model with the identified geometry and tool point, the URDF
    extension of the source model document (if any) kept, and a ``"calibration"`` object listing the
    identified effects (which the model rows cannot hold) and the identified base pose (model units, in the
    measurement frame). `state`: a CalibratedRobot state (``to_state()``) or the robot itself."""
    if not isinstance(state, dict):
        state = state.to_state()
    n = model.n_joints
    x = np.asarray(state["x"], float)
    doc = model.to_dict(x[: 5 * n].reshape(n, 5), x[5 * n + 6: 5 * n + 9])
    if source and isinstance(source.get(EXTENSION), dict):
        doc[EXTENSION] = source[EXTENSION]
    from .kinematics import base_rotation

    ls = LENGTH_TO_MM[model.length_unit]
    Rb = base_rotation(x[5 * n: 5 * n + 6], np.asarray(state.get("R0", np.eye(3)), float))
    doc["calibration"] = {
        "base_pose": {"position": [float(v / ls) for v in x[5 * n: 5 * n + 3]], "rotation_matrix": Rb.tolist(),
                      "frame": "the robot's MD-H base frame in the measurement frame"},
        "effects": [{"kind": e.get("kind"), "joints": [_joint_name(model, j) for j in e.get("joints", [])]}
                    for e in state.get("effects", [])],
    }
    return doc


def _joint_name(model: RobotModel, j) -> str:
    """An effect's joint as the model names it (effect states store positions)."""
    return model.joint_names[j] if isinstance(j, (int, np.integer)) else str(j)


def _f(v: float) -> str:
    v = float(v)
    return "0" if v == 0.0 else repr(v)


def _vec(v) -> str:
    return " ".join(_f(x) for x in v)


def _comment(text: str) -> str:
    return "<!-- " + text.replace("--", "- -").rstrip("-") + " -->"


def to_urdf(model, name: str | None = None) -> str:
    """A URDF of a model: a contract model dict (any convention and units; its ``"urdf"`` extension and
    ``"calibration"`` object are used when present), a :class:`RobotModel`, or a calibrated robot (an object
    with ``model`` and ``x``, e.g. :class:`calib_core.identify.CalibratedRobot`).

    Each MD-H row becomes a joint whose origin is ``Rx(alpha) Tx(a) Rz(theta) Tz(d)`` with axis ``0 0 1``
    (revolute or prismatic); a row with ``beta`` adds a fixed joint ``<joint>_beta`` (``Ry(beta)``), and the
    tool point a fixed joint to the target link. The links between are the MD-H joint frames
    (``<joint>_link``), carrying the model's masses and centres of mass as inertials (no inertia tensor: the
    model has none). Effects a URDF cannot hold are listed in a comment."""
    ext: dict = {}
    calib: dict | None = None
    if isinstance(model, dict):
        ext = model.get(EXTENSION) if isinstance(model.get(EXTENSION), dict) else {}
        calib = model.get("calibration") if isinstance(model.get("calibration"), dict) else None
        m = parse_model(model)
        geometry, tool = m.geometry, m.tool
    elif isinstance(model, RobotModel):
        m, geometry, tool = model, model.geometry, model.tool
    elif hasattr(model, "model") and hasattr(model, "x"):
        m = model.model
        n = m.n_joints
        geometry, tool = np.asarray(model.x[: 5 * n]).reshape(n, 5), np.asarray(model.x[5 * n + 6: 5 * n + 9])
        calib = {"effects": [{"kind": e.kind, "joints": list(e.joints)} for e in getattr(model, "effects", ())]}
    else:
        raise TypeError("to_urdf takes a model dict, a RobotModel or a calibrated robot")
    au = ANGLE_TO_RAD[m.angle_unit]
    ls = LENGTH_TO_MM[m.length_unit]
    rname = name or ext.get("robot") or m.name
    base_link = str(ext.get("base_link") or "base_link")
    target_link = str(ext.get("target_link") or "tool")
    continuous = set(ext.get("continuous") or ())
    extra = ext.get("limits") if isinstance(ext.get("limits"), dict) else {}

    used: set[str] = set()

    def uniq(s: str) -> str:
        out, k = s, 2
        while out in used:
            out, k = f"{s}_{k}", k + 1
        used.add(out)
        return out

    used.add(base_link)
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(str(rname))}>",
             _comment(f"written by calib from the contract model {m.name!r}: each MD-H row "
                      "(Rx(alpha) Tx(a) Rz(theta) Tz(d) Ry(beta)) is a joint origin with axis 0 0 1; the links "
                      "between are the MD-H joint frames; lengths m, angles rad")]
    effects = (calib or {}).get("effects") or []
    if effects:
        lines.append(_comment("identified effects this URDF cannot hold (the calibration's predict and compensate "
                              "include them): " + "; ".join(
                                  f"{e.get('kind')}" + (f" on {', '.join(map(str, e.get('joints') or []))}"
                                                        if e.get("joints") else "") for e in effects)))
    bp = (calib or {}).get("base_pose")
    if bp:
        lines.append(_comment(f"identified base pose in the measurement frame ({m.length_unit}): position "
                              f"{_vec(bp['position'])}, rotation matrix rows {bp['rotation_matrix']}"))

    def link(name_: str, mass=None, com=None):
        if mass is None:
            lines.append(f"  <link name={quoteattr(name_)}/>")
            return
        lines.extend([f"  <link name={quoteattr(name_)}>", "    <inertial>",
                      f'      <origin xyz="{_vec(com)}" rpy="0 0 0"/>', f'      <mass value="{_f(mass)}"/>',
                      '      <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>', "    </inertial>",
                      "  </link>"])

    def joint(name_: str, jtype: str, parent: str, child: str, T: np.ndarray, limit: str | None = None):
        lines.append(f"  <joint name={quoteattr(name_)} type={quoteattr(jtype)}>")
        lines.append(f"    <parent link={quoteattr(parent)}/>")
        lines.append(f"    <child link={quoteattr(child)}/>")
        lines.append(f'    <origin xyz="{_vec(T[:3, 3] / 1000.0)}" rpy="{_vec(matrix_rpy(T))}"/>')
        if jtype != "fixed":
            lines.append('    <axis xyz="0 0 1"/>')
        if limit:
            lines.append(f"    {limit}")
        lines.append("  </joint>")

    link(base_link)
    parent = base_link
    bxyz, brpy = ext.get("base_xyz"), ext.get("base_rpy")
    if bxyz is not None and brpy is not None and (any(bxyz) or any(brpy)):
        B = origin_matrix(np.asarray(bxyz, float) * ls, np.asarray(brpy, float) * au)
        child = uniq("mdh_base")
        link(child)
        jb = f"{base_link}_to_mdh_base"
        while jb in m.joint_names:
            jb += "_"
        joint(jb, "fixed", parent, child, B)
        parent = child
    joint_names: set[str] = set()
    for j, jn in enumerate(m.joint_names):
        a, alpha, d, theta, beta = (float(v) for v in geometry[j])
        T = mdh_transform(a, alpha, d, theta)  # Ry(beta) follows as a fixed joint of its own
        lo, hi = (float(v) for v in m.limits[j])
        info = extra.get(jn) if isinstance(extra.get(jn), dict) else {}
        eff = f' effort="{_f(info.get("effort", 0.0))}" velocity="{_f(info.get("velocity", 0.0))}"'
        if m.prismatic[j]:
            jtype, limit = "prismatic", f'<limit lower="{_f(lo / 1000.0)}" upper="{_f(hi / 1000.0)}"{eff}/>'
        elif jn in continuous or not (math.isfinite(lo) and math.isfinite(hi)):
            jtype, limit = "continuous", (f"<limit{eff}/>" if info else None)
        else:
            jtype, limit = "revolute", f'<limit lower="{_f(lo)}" upper="{_f(hi)}"{eff}/>'
        has_mass = m.mass is not None
        child = uniq(f"{jn}_link")
        if beta != 0.0:
            link(child)
        else:
            link(child, m.mass[j] if has_mass else None, m.com[j] / 1000.0 if has_mass else None)
        joint(jn, jtype, parent, child, T, limit)
        joint_names.add(jn)
        parent = child
        if beta != 0.0:
            child = uniq(f"{jn}_frame")
            link(child, m.mass[j] if has_mass else None, m.com[j] / 1000.0 if has_mass else None)
            jb = f"{jn}_beta"
            while jb in joint_names or jb in m.joint_names:
                jb += "_"
            joint_names.add(jb)
            joint(jb, "fixed", parent, child, rot_y(beta))
            parent = child
    trpy = ext.get("tool_rpy")
    Tt = rpy_matrix(*(np.asarray(trpy, float) * au)) if trpy is not None else np.eye(4)
    Tt[:3, 3] = tool
    tlink = uniq(target_link) if target_link not in used else uniq(f"{target_link}_tool")
    link(tlink)
    jt = f"{tlink}_fixed"
    while jt in joint_names or jt in m.joint_names:
        jt += "_"
    joint(jt, "fixed", parent, tlink, Tt)
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


__all__ = ["CONTINUOUS_LIMIT_RAD", "UrdfError", "align_z", "calibrated_model_dict", "matrix_rpy", "origin_matrix",
           "parse_urdf", "rpy_matrix", "to_urdf"]
