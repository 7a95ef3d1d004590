"""URDF in (contract section 5): serial chains, trees, fixed and mimic joints. Out: :mod:`calib_core.urdf_write`
(a URDF of the model's rows) and :mod:`calib_core.urdf_patch` (the original file patched).

:func:`parse_urdf` reads a URDF, picks the joints from a base link to one or more target links and writes
contract model JSON in one of two forms; :func:`calib_core.urdf_write.to_urdf` writes a model (or a calibrated model) back as a URDF.

* MD-H form (``form="mdh"``; the default for one target whose chain has no mimic joint): every joint (origin
  xyz/rpy, any axis, fixed joints in between) folded exactly into contract MD-H rows with
  :func:`calib_core.frames.fold_links`, one row per movable joint.
* xyz form (``form="xyz"``; the default for several targets or a mimic joint on the way): one row per URDF
  joint, given the URDF way (``xyz``/``rpy`` of the joint origin in the parent joint's child-link frame,
  ``axis``), ``parent`` where a row does not follow the one before it (trees), URDF ``fixed`` joints as
  ``type: fixed`` rows, ``mimic`` joints as ``coupled`` rows, one target per target link (at its SMR offset).
  A mimic joint's source joint is taken in too when it is off the paths to the targets (the Hilti column: the
  measured stages mimic a stage that carries nothing), so its value is the CSV column.

SMR offsets: each target is put at its target link's origin unless the user names the nominal SMR offset
(``smr_m``: metres, in the target link's frame; ``"x,y,z;x,y,z"`` one triple per target in the order of the
targets, as the REST ``smr`` parameter and ``calib import-urdf --smr`` take it, or a list of triples, or a mapping
link -> triple). ``tool0`` or ``hand_tool_link`` lies on the last joint axis; a real SMR does not. MD-H form: the
offset is turned from the target link frame into the last MD-H frame and added to the ``tool`` point; xyz form:
it is each target's ``xyz`` (the target link frame is its row's link frame). Model units in both; the
extension's ``smr_m`` keeps the offsets as given (m, link frame). |x|, |y|, |z| above ``MAX_SMR_OFFSET_M``
(10 m: most likely mm) is refused, naming ``smr`` and the value.

Read the way the URDF spec and urdfdom (so pinocchio) read them, each noted in the extension's ``notes`` (a
list of plain sentences naming the joint; only for the joints taken in):

* a ``fixed`` joint with a ``<mimic>``: the mimic is ignored (Talos's grippers);
* a revolute ``<limit>`` without ``lower`` and ``upper`` (only effort / velocity; the spec's default is 0 for
  both), with ``lower = upper = 0``, or with a range beyond 100 turns (``+-1e16``): a joint without position
  limits (no ``limits`` in the model, as an unlimited revolute joint; written back as ``continuous``), never
  [0, 0]; the same on a prismatic joint: +-100 m, the model's bound (a prismatic row needs limits); only one of
  ``lower`` / ``upper`` given: the other is 0;
* a ``<mimic>`` naming no joint of the URDF: ignored, the joint read as an independent (actuated) joint.

What urdfdom refuses stays refused: a revolute or prismatic joint without ``<limit>``, lower above upper.

Xacro: a xacro file (an element or attribute in the xacro namespace, ``xacro:`` without its declaration, or a
``${...}`` / ``$(...)`` substitution in an attribute the importer reads: the robot's, a link's name and
inertial, a joint and its elements) gets one error, :data:`XACRO_HINT` (expand it with ``xacro`` first). A
``xmlns:xacro`` declaration alone is no sign (xacro keeps it in the URDFs it writes), nor is ``${...}`` in a
comment, a visual or a collision (not read here, nor by pinocchio).

Conventions

* URDF is always m and rad. The model is written in ``length_unit`` / ``angle_unit`` (default m / rad).
* A joint's child frame is ``parent @ origin(xyz, rpy) @ motion(axis, q)`` with ``R(rpy) = Rz(y) Ry(p) Rx(r)``
  (fixed axes). In the MD-H form the frame is turned so that the axis is its z (:func:`align_z`), and the turn
  is undone in front of the next joint.
* ``continuous`` joints: MD-H form, revolute with limits of +-``CONTINUOUS_LIMIT_RAD`` (one turn each way
  covers every orientation); xyz form, revolute without limits.
* Mimic: URDF ``q = multiplier * q_source + offset`` (m / rad) is ``"coupled": {source: c, "offset": o}`` in
  the model's joint units; a mimic of a mimic joint is resolved to the joint at the end of the chain.
* MD-H form: nearly parallel consecutive axes (within ``PARALLEL_SIN``) are folded in Hayati's form (``beta``).
* Gravity is -z of the URDF base link (9.81 m/s^2), in the MD-H base frame (MD-H form) or the base link
  (xyz form).
* Masses: the body moved by a row is its child link plus every link fixed to it that is not a row's child
  link itself (through ``fixed`` joints, side branches included: a tilt sensor, a drill tip); its mass is the
  sum and its centre of mass is written in the row's frame (the MD-H joint frame, or the child link frame in
  the xyz form). Links behind a movable joint that is not taken in are not counted. Inertia tensors are not
  kept (the model has none).
* What the rows cannot say about the URDF goes into the model's ``"urdf"`` object (an extension; the
  contract's parsers ignore it): the URDF base and target link names, which joints were ``continuous`` and
  their effort / velocity limits; MD-H form: the pose of the MD-H base frame in the URDF base link
  (``base_xyz``, ``base_rpy``) and the orientation of the target link in the last MD-H frame (``tool_rpy``),
  both in model units; xyz form: ``links``, each row's child link name. :func:`calib_core.urdf_write.to_urdf` uses it, so URDF ->
  model -> URDF keeps the link names and the base and target link frames, not only the points. Both forms:
  ``notes`` (what was ignored or read leniently, see above; often empty), ``smr_m`` (when SMR offsets were
  given) and ``source``, the original URDF text (for an exporter that patches it; a stored model is thereby
  about the URDF's size: Talos, 110 kB of URDF, makes a 127 kB model document).
* Export of a calibrated model: the identified MD-H constants of each row (and the identified target points)
  are moved into the URDF joint origins, in the original link frames and about the original axes
  (:func:`calib_core.urdf_write.general_rows`); coupled rows get ``<mimic>``; effects a URDF cannot hold (and a coupling on several
  joints, the identified base poses) are listed in comments.

Not supported: ``floating`` and ``planar`` joints among the rows taken in (a clear error names the joint), xacro
(expand it first).

Security: the text is refused when it carries a DOCTYPE (so no entity declarations, no entity expansion,
no external entities), the way defusedxml does.
"""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from .frames import Link, fold_links, rot_x, rot_y, rot_z
from .io import NUMBER
from .model import ANGLE_TO_RAD, LENGTH_TO_MM, ModelError, parse_model
from .urdf_xml import MOVABLE, XACRO_HINT, UrdfError, _decode, _Joint, _numbers, _one, _parse_joints, _read, _rpy, _where

CONTINUOUS_LIMIT_RAD = 2.0 * math.pi
"""Limits written for a URDF ``continuous`` joint: one turn each way."""
GRAVITY = (0.0, 0.0, -9.81)
PARALLEL_SIN = 0.05
"""Consecutive axes closer than this to parallel (|sin| < 0.05, about 3 deg) take Hayati's form (d = 0, beta)
rather than the common normal, which would lie up to 1/|sin| link lengths away (d of hundreds of metres for a
calibrated model whose parallel axes are tilted by a milliradian). Both forms are exact."""
EXTENSION = "urdf"
"""The model-JSON key of the URDF extension object."""
MAX_SMR_OFFSET_M = 10.0
"""|x|, |y|, |z| of a nominal SMR offset (m, in its target link's frame): a larger one is refused (most likely
given in mm)."""


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

def _children(joints: dict[str, _Joint]) -> dict[str, list[_Joint]]:
    """Each link's child joints, in document order."""
    out: dict[str, list[_Joint]] = {}
    for j in joints.values():
        out.setdefault(j.parent, []).append(j)
    return out


def _base_link(links, by_child, base) -> str:
    if base is None:
        roots = [ln for ln in links if ln not in by_child]
        if not links:
            raise UrdfError([{"field": "link", "value": None, "message": "the URDF has no <link>"}])
        if len(roots) != 1:
            raise UrdfError([{"field": "link", "value": roots, "message":
                              f"the URDF has {len(roots)} root links ({', '.join(roots) or 'none: a cycle'}); "
                              "name the chain's base link"}])
        return roots[0]
    if base not in links:
        raise UrdfError([{"field": "base", "value": base, "message": f"no link {base!r} in the URDF"}])
    return base


def _default_target(children, base) -> str:
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
    if not leaves:
        raise UrdfError([{"field": "joint", "value": None, "message": f"the URDF has no joint below the base link "
                          f"{base!r}: there is nothing to calibrate (a model needs at least one joint)"}])
    if len(leaves) != 1:
        raise UrdfError([{"field": "target", "value": sorted(leaves), "message":
                          f"the URDF has {len(leaves)} leaf links below {base!r} ({', '.join(sorted(leaves))}); "
                          "name the target link (the measured point's link)"}])
    return leaves[0]


def _chain(links, joints, by_child, base, link, field: str = "target", why: str = "") -> list[_Joint]:
    """The joints from the base link down to `link`, base first."""
    if link not in links:
        raise UrdfError([{"field": field, "value": link, "message": f"no link {link!r} in the URDF{why}"}])
    path, ln = [], link
    while ln != base:
        j = by_child.get(ln)
        if j is None or len(path) > len(joints):
            raise UrdfError([{"field": field, "value": link, "message":
                              f"link {link!r} is not below the base link {base!r} (the chain must go from the base "
                              f"down to the target){why}"}])
        path.append(j)
        ln = j.parent
    return path[::-1]


def _path(links, joints, by_child, base, target):
    children = _children(joints)
    base = _base_link(links, by_child, base)
    if target is None:
        target = _default_target(children, base)
    return base, target, _chain(links, joints, by_child, base, target), children


def _target_names(target) -> list[str | None]:
    """`target` as a list: None (the default leaf), one link, 'a,b' or a sequence of links."""
    if target is None:
        return [None]
    if isinstance(target, str):
        names = [t.strip() for t in target.split(",")] if "," in target else [target]
    else:
        names = [str(t).strip() for t in target]
    names = [t for t in names if t]
    if not names:
        return [None]
    dup = sorted({t for t in names if names.count(t) > 1})
    if dup:
        raise UrdfError([{"field": "target", "value": dup, "message": "a target link is named more than once"}])
    return names


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
    rpy = _rpy(errors, o, f"{where}/origin")  # checked; the COM needs no turn
    if xyz is None or rpy is None:
        return None
    return m, xyz * scale


def _smr_list(smr_m):
    """The nominal SMR offsets as given (None, ``"x,y,z;x,y,z"``, a sequence of triples or a mapping target
    link -> triple), each checked: a list of (target link or None, 3 floats m), or None."""
    if smr_m is None or (isinstance(smr_m, str) and not smr_m.strip()):
        return None
    errors: list[dict] = []
    if isinstance(smr_m, str):
        items = [(None, part) for part in smr_m.split(";")]
    elif isinstance(smr_m, dict):
        items = [(str(k), v) for k, v in smr_m.items()]
    else:
        try:
            items = [(None, v) for v in smr_m]
        except TypeError:
            raise UrdfError([{"field": "smr", "value": repr(smr_m)[:80], "message": "the SMR offsets must be "
                              "'x,y,z;x,y,z' (m), a list of (x, y, z) or a mapping target link -> (x, y, z)"}]
                            ) from None
    out = []
    for k, v in items:
        field = "smr" if k is None else f"smr[{k!r}]"
        shown = v.strip()[:80] if isinstance(v, str) else repr(v)[:80]
        parts = [c.strip() for c in v.split(",")] if isinstance(v, str) else v
        try:
            parts = list(parts)
        except TypeError:
            parts = [parts]
        if len(parts) != 3:
            errors.append({"field": field, "value": shown, "message": "an SMR offset is three numbers x,y,z (m, in "
                           "its target link's frame); the offsets of several targets are separated by ';'"})
            continue
        xyz = []
        for c in parts:
            if isinstance(c, str):
                c = float(c) if NUMBER.fullmatch(c) else math.nan
            elif isinstance(c, bool) or not isinstance(c, (int, float, np.integer, np.floating)):
                c = math.nan
            xyz.append(float(c))
        if not all(math.isfinite(c) for c in xyz):
            errors.append({"field": field, "value": shown, "message": "an SMR offset is three finite numbers x,y,z "
                           "(m, in its target link's frame)"})
        elif max(abs(c) for c in xyz) > MAX_SMR_OFFSET_M:
            errors.append({"field": field, "value": shown, "message": "implausible: each component must be at most "
                           f"{MAX_SMR_OFFSET_M:g} m (the offset is in metres, not millimetres)"})
        else:
            out.append((k, np.array(xyz, float)))
    if errors:
        raise UrdfError(errors)
    return out


def _smr_of(offsets, targets: list[str]) -> dict[str, np.ndarray] | None:
    """Each target link's nominal SMR offset (m, link frame) from :func:`_smr_list`, matched to the targets."""
    if offsets is None:
        return None
    if all(k is None for k, _ in offsets):
        if len(offsets) != len(targets):
            raise UrdfError([{"field": "smr", "value": ";".join(",".join(f"{c:g}" for c in v) for _, v in offsets),
                              "message": f"{len(offsets)} SMR offset{'s' * (len(offsets) != 1)} for {len(targets)} "
                                         f"target link{'s' * (len(targets) != 1)} ({', '.join(targets)}): give one "
                                         "x,y,z per target, in the order of the targets, separated by ';'"}])
        return {t: v for t, (_, v) in zip(targets, offsets)}
    unknown = [k for k, _ in offsets if k not in targets]
    if unknown:
        raise UrdfError([{"field": f"smr[{k!r}]", "value": k, "message":
                          f"{k!r} is not one of the target links ({', '.join(targets)})"} for k in unknown])
    given = dict(offsets)
    return {t: given.get(t, np.zeros(3)) for t in targets}


def _finish(doc: dict, ext: dict, joints_taken, smr: dict[str, np.ndarray] | None, source: str) -> dict:
    """The extension's notes (what was ignored or read leniently, of the joints taken in), SMR offsets and
    the original URDF text, then the contract check."""
    if smr is not None:
        ext["smr_m"] = {t: [float(v) + 0.0 for v in off] for t, off in smr.items()}
    ext["notes"] = [n for j in joints_taken for n in j.notes]
    ext["source"] = source
    doc[EXTENSION] = ext
    return _validated(doc)


def parse_urdf(text: str | bytes, base: str | None = None, target=None, *,
               length_unit: str = "m", angle_unit: str = "rad", name: str | None = None, form: str = "auto",
               smr_m=None) -> dict:
    """Contract model JSON (``length_unit`` / ``angle_unit``) of the URDF joints from `base` (default: the root
    link) to the `target` links (one link, ``"a,b"`` or a list; default: the only leaf below the base).

    `form`: ``"mdh"`` folds one serial chain into MD-H rows, ``"xyz"`` writes one xyz/rpy/axis row per URDF
    joint (trees, fixed rows, coupled rows), ``"auto"`` (default) the MD-H form for one target whose chain has
    no mimic joint, else the xyz form.

    `smr_m`: the nominal SMR (measured point) offset of each target, metres, in the target link's frame
    (default: each target at its link's origin): ``"x,y,z;x,y,z"`` (one triple per target, in the order of the
    targets: the REST ``smr`` parameter and the CLI ``--smr``), a list of (x, y, z) in that order, or a mapping
    target link -> (x, y, z) (targets left out: at their origin).

    Raises :class:`UrdfError` (a ValueError) naming the element, attribute (or parameter) and value of every
    problem found."""
    if length_unit not in LENGTH_TO_MM or angle_unit not in ANGLE_TO_RAD:
        raise ValueError("length_unit must be 'm' or 'mm' and angle_unit 'rad' or 'deg'")
    if form not in ("auto", "mdh", "xyz"):
        raise ValueError("form must be 'auto', 'mdh' or 'xyz'")
    scale = 1000.0 / LENGTH_TO_MM[length_unit]  # URDF m -> model length unit
    offsets = _smr_list(smr_m)
    text = _decode(text)
    root = _read(text)
    links, joints, by_child = _parse_joints(root)
    targets = _target_names(target)
    if form == "auto":
        form = "xyz" if len(targets) > 1 else "mdh"
        if form == "mdh":
            _, _, path, _ = _path(links, joints, by_child, base, targets[0])
            if any(j.mimic is not None for j in path):
                form = "xyz"
    if form == "xyz":
        return _parse_xyz(root, links, joints, by_child, base, targets, scale, length_unit, angle_unit, name,
                          offsets, text)
    if len(targets) > 1:
        raise UrdfError([{"field": "target", "value": targets, "message":
                          "the MD-H form takes one target link (one serial chain); the xyz form takes several"}])
    return _parse_mdh(root, links, joints, by_child, base, targets[0], scale, length_unit, angle_unit, name,
                      offsets, text)


def _parse_mdh(root, links, joints, by_child, base, target, scale, length_unit, angle_unit, name,
               offsets=None, source: str = "") -> dict:
    """The MD-H form: one serial chain folded into MD-H rows; the SMR offset in the tool point."""
    ang = math.degrees if angle_unit == "deg" else float
    base, target, path, children = _path(links, joints, by_child, base, target)
    smr = _smr_of(offsets, [target])

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
                           f"joint {j.name!r} mimics {j.mimic!r}: a mimic (coupled) joint needs the xyz form "
                           "(form 'xyz' or 'auto'), the MD-H form folds one chain of independent joints"})
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
            if not (math.isfinite(j.lower) and math.isfinite(j.upper)):
                lim = None  # a revolute joint without position limits (noted)
        extra_limits[j.name] = {k: v for k, v in (("effort", j.effort), ("velocity", j.velocity)) if v is not None}
        R = align_z(j.axis)
        chain_links.append(Link(pending @ T @ R, "prismatic" if j.type == "prismatic" else "revolute", j.name, lim))
        pending = R.T.copy()
    if errors:
        raise UrdfError(errors)
    if not chain_links:
        raise UrdfError([{"field": "joint", "value": [j.name for j in path], "message":
                          f"the chain {base} -> {target} has no revolute, continuous or prismatic joint"}])
    tool_T = pending  # the target link frame in the last joint's (aligned) frame
    tool_point = tool_T[:3, 3] if smr is None else (tool_T @ np.r_[smr[target] * scale, 1.0])[:3]
    try:
        folded = fold_links(chain_links, tool_point, gravity=GRAVITY, parallel_tol=PARALLEL_SIN)
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
    return _finish(doc, ext, path, smr, source)


def _validated(doc: dict) -> dict:
    """The converted model document, checked by the contract parser; its errors named by URDF element."""
    try:
        parse_model(doc)
    except ModelError as exc:
        raise UrdfError([{**e, "field": f"{_model_field_to_urdf(e['field'], doc)} (model {e['field']})"}
                         for e in exc.errors]) from None
    return doc


def _wrap(a: float) -> float:
    """An angle in (-pi, pi] (the same rotation: each URDF angle enters only through cos and sin)."""
    return math.remainder(float(a), 2.0 * math.pi) + 0.0


def _mimic_source(joints: dict[str, _Joint], j: _Joint, errors: list):
    """(source joint, multiplier, offset) of a mimic joint in URDF units, a mimic of a mimic resolved to the
    joint at the end of the chain; None (with an error) when the chain is broken."""
    mult, off, seen, cur = 1.0, 0.0, {j.name}, j
    while cur.mimic is not None:
        src = joints.get(cur.mimic)
        mult, off = mult * cur.multiplier, off + mult * cur.offset
        if src is None:
            errors.append({"field": f"{cur.where}/mimic/@joint", "value": cur.mimic,
                           "message": "no <joint> of that name"})
            return None
        if src.type not in MOVABLE:
            errors.append({"field": f"{cur.where}/mimic/@joint", "value": cur.mimic,
                           "message": f"joint {src.name!r} is {src.type}: a mimic joint follows a revolute, "
                                      "continuous or prismatic joint"})
            return None
        if src.name in seen:
            errors.append({"field": f"{j.where}/mimic/@joint", "value": j.mimic,
                           "message": f"the mimic joints {', '.join(sorted(seen))} follow each other in a circle"})
            return None
        seen.add(src.name)
        cur = src
    return cur, mult, off


def _parse_xyz(root, links, joints, by_child, base, targets, scale, length_unit, angle_unit, name,
               offsets=None, source: str = "") -> dict:
    """The xyz form: one xyz/rpy/axis row per URDF joint on the way from the base to the targets (and to the
    joints their mimic joints follow), fixed rows, coupled rows, one target per target link (at its SMR
    offset)."""
    an = ANGLE_TO_RAD[angle_unit]
    children = _children(joints)
    base = _base_link(links, by_child, base)
    if targets == [None]:
        targets = [_default_target(children, base)]
    if base in targets:
        raise UrdfError([{"field": "target", "value": base, "message": "a target link must be below the base "
                          "link, not the base link itself"}])
    smr = _smr_of(offsets, targets)
    need: set[str] = set()
    for t in targets:
        need.update(j.name for j in _chain(links, joints, by_child, base, t))
    errors: list[dict] = []
    mimic: dict[str, tuple] = {}  # row -> (source joint, multiplier, offset), URDF units
    todo = sorted(need)
    while todo:
        j = joints[todo.pop()]
        if j.mimic is None or j.name in mimic:
            continue
        src = _mimic_source(joints, j, errors)
        if src is None:
            continue
        mimic[j.name] = src
        if src[0].name not in need:
            try:
                extra = _chain(links, joints, by_child, base, src[0].child, f"{j.where}/mimic/@joint",
                               f" (joint {j.name!r} mimics {src[0].name!r}, whose child link it is)")
            except UrdfError as exc:
                errors.extend(exc.errors)
                continue
            new = [k.name for k in extra if k.name not in need]
            need.update(new)
            todo.extend(new)
    if errors:
        raise UrdfError(errors)

    # rows: the joints taken in, parents before children (depth first from the base, document order)
    order: list[_Joint] = []
    stack = [base]
    while stack:
        ln = stack.pop()
        if ln != base:
            order.append(by_child[ln])
        stack.extend(j.child for j in reversed(children.get(ln, [])) if j.name in need)
    row_of_link = {j.child: j.name for j in order}
    scale_of = {}  # URDF -> model joint units
    for j in order:
        scale_of[j.name] = scale if j.type == "prismatic" else 1.0 / an
    rows: list[dict] = []
    continuous, extra_limits = [], {}
    prev = None
    for j in order:
        if j.type in ("floating", "planar"):
            errors.append({"field": f"{j.where}/@type", "value": j.type, "message":
                           f"a {j.type} joint on the way {base} -> {', '.join(targets)} is not supported "
                           "(revolute, continuous, prismatic, fixed and mimic joints are)"})
            continue
        row: dict[str, Any] = {"name": j.name, "type": "fixed" if j.type == "fixed" else
                               "prismatic" if j.type == "prismatic" else "revolute"}
        par = "base" if j.parent == base else row_of_link[j.parent]
        if par != (prev if prev is not None else "base"):
            row["parent"] = par
        prev = j.name
        row["xyz"] = [float(v * scale) + 0.0 for v in j.xyz]
        row["rpy"] = [_wrap(v) / an + 0.0 for v in j.rpy]
        if j.type != "fixed":
            row["axis"] = [float(v) + 0.0 for v in j.axis]
        if j.name in mimic:
            src, mult, off = mimic[j.name]
            f_row, f_src = scale_of[j.name], (scale if src.type == "prismatic" else 1.0 / an)
            row["coupled"] = {src.name: float(mult * f_row / f_src)}
            if off:
                row["coupled"]["offset"] = float(off * f_row)
        if j.type == "continuous":
            continuous.append(j.name)
        elif j.type in ("revolute", "prismatic"):
            if j.lower is None or j.upper is None:
                if j.name not in mimic:
                    errors.append({"field": f"{j.where}/limit", "value": None, "message":
                                   f"a {j.type} joint needs <limit lower=... upper=...> (use type continuous for an "
                                   "unlimited revolute joint)"})
            elif not j.lower < j.upper:
                errors.append({"field": f"{j.where}/limit", "value": [j.lower, j.upper],
                               "message": "the lower limit must be below the upper limit"})
            elif math.isfinite(j.lower) and math.isfinite(j.upper):  # else: no position limits (noted)
                row["limits"] = [float(j.lower * scale_of[j.name]), float(j.upper * scale_of[j.name])]
        if j.type != "fixed":
            info = {k: v for k, v in (("effort", j.effort), ("velocity", j.velocity)) if v is not None}
            if info:
                extra_limits[j.name] = info
        rows.append(row)
    if errors:
        raise UrdfError(errors)
    if all(r["type"] == "fixed" or "coupled" in r for r in rows):
        raise UrdfError([{"field": "joint", "value": [j.name for j in order], "message":
                          f"the way {base} -> {', '.join(targets)} has no revolute, continuous or prismatic joint"}])

    # masses: each row's child link and every link fixed to it that is no row's child link, in the child link
    any_inertial = False
    for j, row in zip(order, rows):
        m_tot, moment = 0.0, np.zeros(3)
        stack = [(j.child, np.eye(4))]
        while stack:
            ln, T = stack.pop()
            mc = _link_mass(links[ln], ln, scale, errors)
            if mc is not None:
                any_inertial = True
                m_tot += mc[0]
                moment += mc[0] * (T @ np.r_[mc[1], 1.0])[:3]
            for k in children.get(ln, []):
                if k.type == "fixed" and k.name not in need and k.xyz is not None and k.rpy is not None:
                    stack.append((k.child, T @ origin_matrix(k.xyz * scale, k.rpy)))
        row["mass"] = float(m_tot)
        row["com"] = [float(v) + 0.0 for v in (moment / m_tot if m_tot > 0 else np.zeros(3))]
    if errors:
        raise UrdfError(errors)
    if not any_inertial:
        for row in rows:
            del row["mass"], row["com"]
    doc = {"name": name or root.get("name") or "robot", "convention": "mdh",
           "units": {"length": length_unit, "angle": angle_unit}, "joints": rows,
           "targets": [{"name": t, "parent": by_child[t].name,
                        "xyz": [0.0, 0.0, 0.0] if smr is None else [float(v * scale) + 0.0 for v in smr[t]]}
                       for t in targets],
           "gravity": list(GRAVITY)}
    ext = {
        "robot": root.get("name"), "base_link": base, "target_link": ",".join(targets), "target_links": targets,
        "form": "xyz", "links": {j.name: j.child for j in order}, "continuous": continuous, "limits": extra_limits,
    }
    return _finish(doc, ext, order, smr, source)


def _model_field_to_urdf(field: str, doc: dict) -> str:
    m = re.match(r"joints\[(\d+)\]", field)
    if m and int(m.group(1)) < len(doc["joints"]):
        return _where("joint", doc["joints"][int(m.group(1))]["name"])
    return "robot" if field in ("name", "") else field


__all__ = ["CONTINUOUS_LIMIT_RAD", "XACRO_HINT", "UrdfError", "align_z", "matrix_rpy", "origin_matrix", "parse_urdf",
           "rpy_matrix"]
