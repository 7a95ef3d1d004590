"""URDF as XML (contract section 5): the text read safely (no DOCTYPE or entities, as defusedxml; a xacro file
refused with one clear error), and its joints and links parsed and checked (types, origins, axes, limits read
leniently where the URDF spec and pinocchio do, mimic), every problem named by element and attribute. The model
rows are made of them in :mod:`calib_core.urdf`."""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from .io import NUMBER
from .model import MAX_LENGTH_MM, MAX_REVOLUTE_DEG, ModelError

MAX_LENGTH_M = MAX_LENGTH_MM / 1000.0
"""|x|, |y|, |z| of a joint origin (m): the model's own plausibility bound."""
MAX_URDF_CHARS = 20_000_000
"""A URDF larger than this is refused (the largest real ones, with inline meshes, are a few MB)."""


MOVABLE = ("revolute", "continuous", "prismatic")
KNOWN_TYPES = (*MOVABLE, "fixed", "floating", "planar")


MAX_REVOLUTE_RAD = math.radians(MAX_REVOLUTE_DEG)
"""A revolute ``<limit>`` beyond this (100 turns; e.g. +-1e16) is read as no position limit (and noted)."""


XACRO_HINT = "this is a xacro file: expand it with `xacro FILE > robot.urdf` first"


_DOCTYPE = re.compile(r"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)
_XACRO_SUBST = re.compile(r"\$[({]")


class UrdfError(ModelError):
    """A URDF that cannot be read as a serial chain; `errors` lists {field, value, message}, the field naming
    the element and attribute (e.g. ``joint[@name='elbow']/origin/@xyz``)."""


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
    multiplier: float = 1.0
    offset: float = 0.0
    notes: list[str] = field(default_factory=list)
    """What was ignored or read the lenient way (plain sentences naming the joint)."""


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


MAX_RPY_RAD = math.radians(MAX_REVOLUTE_DEG)
"""|roll|, |pitch|, |yaw| of an <origin>: 100 turns (issue 33: rpy="1e300 0 0" was taken, an angle no sine can read)."""


def _rpy(errors, o, where):
    """An <origin>'s rpy: three finite numbers, each within MAX_RPY_RAD, or None (the error naming it added)."""
    rpy = _numbers(errors, o, "rpy", where, 3, (0.0, 0.0, 0.0))
    if rpy is not None and not np.abs(rpy).max() <= MAX_RPY_RAD:
        errors.append({"field": f"{where}/@rpy", "value": o.get("rpy")[:80],
                       "message": f"implausible: each angle must be at most {MAX_RPY_RAD:.1f} rad (100 turns)"})
        return None
    return rpy


def _one(errors, el, attr, where):
    v = _numbers(errors, el, attr, where, 1, None)
    return None if v is None else float(v[0])


def _decode(text) -> str:
    """The URDF as text (bytes: UTF-8, a BOM dropped), its size checked."""
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
    return text


def _xacro_error(field: str, value) -> UrdfError:
    return UrdfError([{"field": field, "value": value, "message": XACRO_HINT}])


def _is_xacro_name(name: str) -> bool:
    """An element or attribute name in a xacro namespace (``{http://www.ros.org/wiki/xacro}macro``)."""
    return name.startswith("{") and "xacro" in name[1:name.find("}")].lower()


def _check_xacro(root: ET.Element) -> None:
    """Refuses a xacro file with one clear error: an element or attribute in the xacro namespace anywhere
    (``<xacro:macro>``, ``<xacro:include>``, ``<xacro:property>``, ``xacro:if``), or a ``${...}`` / ``$(...)``
    substitution in an attribute this importer reads (the robot's, a link's name and inertial, a joint and its
    elements). A ``xmlns:xacro`` declaration alone is no sign: xacro keeps it in the URDFs it writes; nor is
    ``${...}`` in a comment, a visual or a collision (ignored here, as by urdfdom and pinocchio)."""
    for el in root.iter():
        if not isinstance(el.tag, str):
            continue
        if _is_xacro_name(el.tag):
            raise _xacro_error("urdf", f"<xacro:{el.tag.split('}', 1)[1]}>")
        for k in el.attrib:
            if _is_xacro_name(k):
                raise _xacro_error("urdf", f"<{el.tag} xacro:{k.split('}', 1)[1]}=...>")

    def scan(el: ET.Element, where: str) -> None:
        for k, v in el.attrib.items():
            if _XACRO_SUBST.search(v):
                raise _xacro_error(f"{where}/@{k}", v[:80])
        for c in el:
            if isinstance(c.tag, str):
                scan(c, f"{where}/{c.tag}")

    for k, v in root.attrib.items():
        if _XACRO_SUBST.search(v):
            raise _xacro_error(f"robot/@{k}", v[:80])
    for el in root:
        if el.tag == "joint":
            scan(el, _where("joint", el.get("name")))
        elif el.tag == "link":
            where = _where("link", el.get("name"))
            if _XACRO_SUBST.search(el.get("name") or ""):
                raise _xacro_error(f"{where}/@name", el.get("name")[:80])
            for inertial in el.findall("inertial"):
                scan(inertial, f"{where}/inertial")


def _read(text) -> ET.Element:
    text = _decode(text)
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
        if str(exc).startswith("unbound prefix") and re.search(r"<\s*xacro:|\sxacro:\w+\s*=", text):
            raise _xacro_error("urdf", f"line {line}, column {col + 1}: xacro: without xmlns:xacro") from None
        raise UrdfError([{"field": "urdf", "value": f"line {line}, column {col + 1}",
                          "message": f"not well-formed XML: {str(exc).split(':')[0]}"}]) from None
    if root.tag != "robot":
        raise UrdfError([{"field": root.tag, "value": root.tag,
                          "message": "the root element of a URDF must be <robot>"}])
    _check_xacro(root)
    return root


def _lenient_limits(jtype: str, name: str, lim: ET.Element, lower, upper, notes: list[str]):
    """(lower, upper) of a revolute or prismatic joint's <limit>, read the way the URDF spec and urdfdom do:
    a missing lower or upper is 0; lower = upper = 0 (e.g. a <limit> with only effort and velocity) is no
    position range, so (-inf, inf) for "no limits" (a prismatic joint: +-100 m, the model's bound); a revolute
    range beyond 100 turns (+-1e16 for "unlimited") likewise. Each such reading is noted."""
    if lower is None or upper is None:  # a bad number was already reported as an error
        gave_lower, gave_upper = lim.get("lower") is not None, lim.get("upper") is not None
        if (gave_lower and lower is None) or (gave_upper and upper is None):
            return lower, upper
        missing = [k for k, g in (("lower", gave_lower), ("upper", gave_upper)) if not g]
        lower, upper = (0.0 if lower is None else lower), (0.0 if upper is None else upper)
        if lower != 0.0 or upper != 0.0:
            notes.append(f"joint {name!r}: <limit> gives no {' and no '.join(missing)}: read as 0 (the URDF "
                         f"default), so the joint's range is [{lower:g}, {upper:g}]")
            return lower, upper
        what = f"<limit> gives no {' and no '.join(missing)} (the URDF default is 0)"
    elif lower == 0.0 and upper == 0.0:
        what = "<limit lower=\"0\" upper=\"0\"> gives no position range"
    elif jtype == "revolute" and max(abs(lower), abs(upper)) > MAX_REVOLUTE_RAD and lower < upper:
        what = f"<limit> [{lower:g}, {upper:g}] rad reaches beyond 100 turns"
    else:
        return lower, upper
    if jtype == "prismatic":
        notes.append(f"joint {name!r}: {what}: read as a travel of +-{MAX_LENGTH_M:g} m, the model's bound "
                     "(a prismatic row needs limits); give its real limits for planning")
        return -MAX_LENGTH_M, MAX_LENGTH_M
    notes.append(f"joint {name!r}: {what}: read as a revolute joint without position limits")
    return -math.inf, math.inf


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
        rpy = _rpy(errors, o, f"{where}/origin")
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
        notes: list[str] = []
        if lim is not None:
            lower, upper = _one(errors, lim, "lower", f"{where}/limit"), _one(errors, lim, "upper", f"{where}/limit")
            effort = _one(errors, lim, "effort", f"{where}/limit")
            velocity = _one(errors, lim, "velocity", f"{where}/limit")
            if jtype in ("revolute", "prismatic"):
                lower, upper = _lenient_limits(jtype, name, lim, lower, upper, notes)
        mimic = el.find("mimic")
        mult = off = None
        if mimic is not None:
            if not mimic.get("joint"):
                errors.append({"field": f"{where}/mimic/@joint", "value": None,
                               "message": "a <mimic> needs joint=... (the joint it follows)"})
            mult = _one(errors, mimic, "multiplier", f"{where}/mimic") if mimic.get("multiplier") else 1.0
            off = _one(errors, mimic, "offset", f"{where}/mimic") if mimic.get("offset") else 0.0
            if jtype == "fixed" and mimic.get("joint"):
                notes.append(f"joint {name!r} is fixed: its <mimic joint={mimic.get('joint')!r}> was ignored "
                             "(a fixed joint has no value to follow)")
                mimic = None
        joints[name] = _Joint(name, jtype, ends.get("parent"), ends.get("child"), xyz, rpy, axis, lower, upper,
                              effort, velocity, None if mimic is None else (mimic.get("joint") or "?"), where,
                              1.0 if mult is None else mult, 0.0 if off is None else off, notes)
    if errors:
        raise UrdfError(errors)
    for j in joints.values():
        if j.mimic is not None and j.mimic not in joints:
            j.notes.append(f"joint {j.name!r} mimics {j.mimic!r}, which is no joint of the URDF: the <mimic> was "
                           f"ignored and {j.name!r} read as an independent (actuated) joint")
            j.mimic, j.multiplier, j.offset = None, 1.0, 0.0
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
