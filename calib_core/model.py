"""The robot model of the contract (section 1): MD-H or standard DH joints, units, validation.

Internally every length is in mm and every angle in rad; `units` only says how the
user wrote the model and how answers are given back.  Standard DH is converted
exactly to MD-H (Craig / Hayati) so that one kinematics and one Jacobian serve both.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0}
ANGLE_TO_RAD = {"deg": math.pi / 180.0, "rad": 1.0}
GEOMETRIC = ("a", "alpha", "d", "theta", "beta")
"""Per-joint MD-H parameters in the order of the parameter vector."""
ANGULAR = {"alpha", "theta", "beta"}

# Plausibility ranges at the input, in one place, internal units in the names.  Generous for any real cell
# (a 100 m hall, a 10 t payload, a tracker to an interferometer), and a wall in front of the numerics: a finite
# but absurd value (a coordinate of 1e305, sigma 1e-300, a payload of 1e308 kg) is a 422 naming the field,
# never a job that spins or a raw ZeroDivisionError.  Messages state the range in the model's own units.
MAX_LENGTH_MM = 1e5
"""|a|, |d|, tool, centre of mass, prismatic travel and limits: 100 m."""
MAX_POINT_MM = 1e5
"""|x|, |y|, |z| of a measured point or a compensate target in the measurement frame: 100 m."""
MAX_MODEL_ANGLE_DEG = 720.0
"""|alpha|, |theta|, |beta| of a model row: two turns."""
MAX_REVOLUTE_DEG = 36000.0
"""|value| of a revolute joint (limits, CSV, predict): 100 turns."""
MAX_MASS_KG = 1e5
"""mass of one body: 100 t."""
MAX_PAYLOAD_KG = 1e4
"""payload at the tool: 10 t."""
MAX_GRAVITY_MS2 = 20.0
"""|gravity| in m/s^2: about twice the Earth's (9.81); a vector in mm/s^2 is caught."""
SIGMA_RANGE_MM = (1e-4, 100.0)
"""1-sigma measurement uncertainty of a point: 0.1 um (an interferometer) to 100 mm."""
TEMPERATURE_RANGE_C = (-60.0, 200.0)
TIMESTAMP_RANGE_UTC = ("1970-01-01T00:00:00+00:00", "2200-01-01T00:00:00+00:00")
TIMESTAMP_RANGE_S = (0.0, 7258118400.0)
"""The same range in seconds since the epoch."""
JOINT_MARGIN_FRACTION = 0.1
"""predict / compensate: a joint value beyond its limits by more than this share of the joint's range is refused."""
MAX_NAME_CHARS = 200
"""robot name (the database column holds 200)."""
MAX_JOINT_NAME_CHARS = 100
MAX_JSON_DEPTH = 20
"""nesting depth of a model document (the contract's own is 4)."""
RESERVED_COLUMNS = ("point", "x", "y", "z", "timestamp", "temperature", "payload", "payload_kg", "sigma",
                    "target", "setup", "qw", "qx", "qy", "qz")
"""The measurement CSV's own columns (contract sections 2 and 5): no joint may be named like one."""
RESERVED_PREFIXES = ("tau_",)
"""`tau_<joint>` columns carry measured joint torques (contract section 5)."""
_UNSAFE_NAME = re.compile(r'[\x00-\x1f\x7f-\x9f,"\u2028\u2029]')
"""Characters a CSV header cannot carry as written: comma, quote, control characters, line breaks."""


def length_text(mm: float, unit: str) -> str:
    """A length given in mm, written in the model's length unit: '100000 mm' or '100 m'."""
    return f"{mm / LENGTH_TO_MM.get(unit, 1.0):g} {unit if unit in LENGTH_TO_MM else 'mm'}"


def revolute_bound(angle_unit: str) -> float:
    """MAX_REVOLUTE_DEG (100 turns) in `angle_unit`: the largest |value| of a revolute joint."""
    return MAX_REVOLUTE_DEG * ANGLE_TO_RAD["deg"] / ANGLE_TO_RAD[angle_unit]


def angle_text(deg: float, unit: str) -> str:
    return f"{deg:g} deg" if unit != "rad" else f"{math.radians(deg):.6g} rad"


def name_problem(name, *, what: str = "joint name", max_chars: int = MAX_JOINT_NAME_CHARS,
                 csv_column: bool = True) -> str | None:
    """Why `name` cannot be used (plain words), or None when it can."""
    if not isinstance(name, str):
        return f"the {what} must be a text string"
    if not name.strip():
        return f"the {what} must not be empty"
    if len(name) > max_chars:
        return f"the {what} is {len(name)} characters long; at most {max_chars} are allowed"
    if "\x00" in name:
        return f"the {what} must not contain a NUL character"
    if not csv_column:
        if any(c < " " or c == "\x7f" for c in name):
            return f"the {what} must not contain control characters or line breaks"
        return None
    if name != name.strip():
        return f"the {what} must not start or end with spaces (it is a CSV column header)"
    m = _UNSAFE_NAME.search(name)
    if m:
        return (f"the {what} cannot be a CSV column header: it contains {m.group()!r}; "
                "use letters, digits, spaces, '_', '-' or '.'")
    if name.startswith(("#", "//")):
        return f"the {what} must not start with '#' or '//' (a CSV line starting so is a comment)"
    if name in RESERVED_COLUMNS:
        return (f"{name!r} is a column of the measurement CSV ({', '.join(RESERVED_COLUMNS)}); "
                f"name the joint differently, e.g. 'J_{name}'")
    if name.startswith(RESERVED_PREFIXES):
        return "joint names must not start with 'tau_' (the CSV's measured-torque columns are named tau_<joint>)"
    return None


def _json_problems(doc, max_errors: int = 50) -> list[dict]:
    """NaN/Infinity literals, NUL characters and too deep nesting anywhere in a JSON document, with the
    field path of each; walked without recursion so any depth is safe."""
    errors: list[dict] = []
    stack = [("", doc, 1)]
    while stack and len(errors) < max_errors:
        path, v, depth = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            errors.append({"field": path, "value": str(v),
                           "message": "must be a finite number (NaN and Infinity are not JSON numbers)"})
        elif isinstance(v, str) and "\x00" in v:
            errors.append({"field": path, "value": v[:80], "message": "must not contain a NUL character"})
        elif isinstance(v, (dict, list)):
            if depth > MAX_JSON_DEPTH:
                errors.append({"field": path, "value": None, "message": f"nested deeper than {MAX_JSON_DEPTH} "
                               "levels; a model document is at most a few levels deep"})
                continue
            items = v.items() if isinstance(v, dict) else enumerate(v)
            kids = []
            for k, x in items:
                if isinstance(k, str) and "\x00" in k:
                    errors.append({"field": path, "value": k[:80], "message": "a key must not contain a NUL character"})
                    continue
                kp = (f"{path}.{k}" if path else str(k)) if isinstance(v, dict) else f"{path}[{k}]"
                kids.append((kp, x, depth + 1))
            stack.extend(reversed(kids))
    return errors


class ModelError(ValueError):
    """A robot model that cannot be used; `errors` lists every problem as {field, value, message}."""

    def __init__(self, errors: list[dict]):
        self.errors = errors
        super().__init__("; ".join(f"{e['field']}: {e['message']}" for e in errors))


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A serial chain in MD-H form, internal units mm / rad.

    `geometry` is (n, 5): a_{i-1}, alpha_{i-1}, d_i, theta_i, beta_i for each joint row.
    `limits` are in joint units (rad for revolute, mm for prismatic).
    """

    name: str
    joint_names: tuple[str, ...]
    prismatic: np.ndarray  # (n,) bool
    geometry: np.ndarray  # (n, 5)
    limits: np.ndarray  # (n, 2)
    tool: np.ndarray  # (3,) mm, in the last joint frame
    gravity: np.ndarray  # (3,) m/s^2 in the robot base frame
    mass: np.ndarray | None = None  # (n,) kg
    com: np.ndarray | None = None  # (n, 3) mm in each joint's MD-H frame
    length_unit: str = "mm"
    angle_unit: str = "deg"
    source_convention: str = "mdh"
    extra: dict = field(default_factory=dict)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def has_mass(self) -> bool:
        return self.mass is not None

    def joint_scale(self) -> np.ndarray:
        """Factor from user joint units to internal units (rad or mm) per joint, shape (n,)."""
        return np.where(self.prismatic, LENGTH_TO_MM[self.length_unit], ANGLE_TO_RAD[self.angle_unit])

    def joint_unit(self, j: int) -> str:
        return self.length_unit if self.prismatic[j] else self.angle_unit

    def to_dict(self, geometry: np.ndarray | None = None, tool: np.ndarray | None = None) -> dict:
        """The model as contract JSON (always MD-H), optionally with calibrated geometry / tool."""
        g = self.geometry if geometry is None else geometry
        t = self.tool if tool is None else tool
        ls, an = LENGTH_TO_MM[self.length_unit], ANGLE_TO_RAD[self.angle_unit]
        js = self.joint_scale()
        joints = []
        for j, name in enumerate(self.joint_names):
            row = {"name": name, "type": "prismatic" if self.prismatic[j] else "revolute"}
            for k, p in enumerate(GEOMETRIC):
                row[p] = float(g[j, k] / (an if p in ANGULAR else ls))
            row["limits"] = [float(v / js[j]) for v in self.limits[j]]
            if self.mass is not None:
                row["mass"] = float(self.mass[j])
                row["com"] = [float(v / ls) for v in self.com[j]]
            joints.append(row)
        return {
            "name": self.name,
            "convention": "mdh",
            "units": {"length": self.length_unit, "angle": self.angle_unit},
            "joints": joints,
            "tool": [float(v / ls) for v in t],
            "gravity": [float(v) for v in self.gravity],
        }


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _finite_number(errors, fieldname, value) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        errors.append({"field": fieldname, "value": value, "message": "must be a number"})
        return None
    if not math.isfinite(value):
        errors.append({"field": fieldname, "value": str(value), "message": "must be finite (no NaN or inf)"})
        return None
    return float(value)


def _in_range(errors, fieldname, value, bound: float, text: str) -> float | None:
    """value (a finite float or None) must satisfy |value| <= bound; text names the bound in the user's units."""
    if value is not None and not abs(value) <= bound:
        errors.append({"field": fieldname, "value": value, "message": f"implausible: |{fieldname.rsplit('.', 1)[-1]}| "
                       f"must be at most {text}"})
        return None
    return value


def _vector(errors, fieldname, value, n=3, bound: float | None = None, text: str = "") -> np.ndarray | None:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        errors.append({"field": fieldname, "value": value, "message": f"must be a list of {n} numbers"})
        return None
    out = [_finite_number(errors, f"{fieldname}[{k}]", v) for k, v in enumerate(value)]
    if bound is not None:
        bad = [(k, v) for k, v in enumerate(out) if v is not None and not abs(v) <= bound]
        for k, v in bad:
            errors.append({"field": f"{fieldname}[{k}]", "value": v,
                           "message": f"implausible: each component must be at most {text} in size"})
        if bad:
            return None
    return None if any(v is None for v in out) else np.array(out, dtype=float)


def parse_model(doc: dict) -> RobotModel:
    """Validate contract model JSON and build a RobotModel; raises ModelError listing every problem."""
    errors: list[dict] = []
    if not isinstance(doc, dict):
        raise ModelError([{"field": "", "value": type(doc).__name__, "message": "model must be a JSON object"}])
    bad_json = _json_problems(doc)
    if bad_json:
        raise ModelError(bad_json)
    name = doc.get("name", "robot")
    if not isinstance(name, str) or not name.strip():
        errors.append({"field": "name", "value": name, "message": "must be a non-empty string"})
    else:
        why = name_problem(name, what="robot name", max_chars=MAX_NAME_CHARS, csv_column=False)
        if why:
            errors.append({"field": "name", "value": name, "message": why})
    convention = doc.get("convention", "mdh")
    if not isinstance(convention, str) or convention not in ("mdh", "dh"):
        errors.append({"field": "convention", "value": convention, "message": "must be 'mdh' or 'dh'"})
    units = doc.get("units", {"length": "mm", "angle": "deg"})
    if not isinstance(units, dict):
        errors.append({"field": "units", "value": units, "message": "must be an object {length, angle}"})
        units = {}
    lu, au = units.get("length", "mm"), units.get("angle", "deg")
    if not isinstance(lu, str) or lu not in LENGTH_TO_MM:
        errors.append({"field": "units.length", "value": lu, "message": "unknown length unit; use 'mm' or 'm'"})
        lu = "mm"
    if not isinstance(au, str) or au not in ANGLE_TO_RAD:
        errors.append({"field": "units.angle", "value": au, "message": "unknown angle unit; use 'deg' or 'rad'"})
        au = "deg"
    ls, an = LENGTH_TO_MM[lu], ANGLE_TO_RAD[au]
    # each plausibility bound in the document's units, and in words for the messages
    len_bound, len_max = MAX_LENGTH_MM / ls, length_text(MAX_LENGTH_MM, lu)
    ang_bound, ang_max = MAX_MODEL_ANGLE_DEG * ANGLE_TO_RAD["deg"] / an, angle_text(MAX_MODEL_ANGLE_DEG, au)
    rev_bound, rev_max = revolute_bound(au), angle_text(MAX_REVOLUTE_DEG, au)

    joints = doc.get("joints")
    if not isinstance(joints, list) or not joints:
        errors.append({"field": "joints", "value": joints if not isinstance(joints, list) else [],
                       "message": "the model needs at least one joint"})
        raise ModelError(errors)

    names, prismatic, rows, limits, masses, coms = [], [], [], [], [], []
    for j, jd in enumerate(joints):
        where = f"joints[{j}]"
        if not isinstance(jd, dict):
            errors.append({"field": where, "value": jd, "message": "must be an object"})
            continue
        jname = jd.get("name")
        why = name_problem(jname)
        if why:
            errors.append({"field": f"{where}.name", "value": jname, "message": why})
        elif jname in names:
            errors.append({"field": f"{where}.name", "value": jname, "message": "duplicate joint name"})
        names.append(jname)
        jtype = jd.get("type", "revolute")
        if not isinstance(jtype, str) or jtype not in ("revolute", "prismatic"):
            errors.append({"field": f"{where}.type", "value": jtype, "message": "must be 'revolute' or 'prismatic'"})
        prismatic.append(jtype == "prismatic")
        row = []
        for p in GEOMETRIC:
            if p == "beta" and convention == "dh":
                if jd.get("beta", 0) not in (0, 0.0):
                    errors.append({"field": f"{where}.beta", "value": jd.get("beta"),
                                   "message": "standard DH has no beta; use convention 'mdh'"})
                row.append(0.0)
                continue
            v = _finite_number(errors, f"{where}.{p}", jd.get(p, 0.0))
            if p in ANGULAR:
                v = _in_range(errors, f"{where}.{p}", v, ang_bound, ang_max)
            else:
                v = _in_range(errors, f"{where}.{p}", v, len_bound, len_max)
            row.append(0.0 if v is None else v * (an if p in ANGULAR else ls))
        rows.append(row)
        lim = jd.get("limits")
        jscale = ls if jtype == "prismatic" else an
        if lim is None:
            lim = [-math.inf, math.inf] if jtype == "revolute" else None
            if lim is None:
                errors.append({"field": f"{where}.limits", "value": None, "message": "a prismatic joint needs limits"})
                lim = [0.0, 0.0]
            limits.append(lim)
        else:
            if jtype == "prismatic":
                lv = _vector(errors, f"{where}.limits", lim, 2, len_bound, len_max)
            else:
                lv = _vector(errors, f"{where}.limits", lim, 2, rev_bound,
                             rev_max + " (100 turns; leave limits out for an unlimited joint)")
            if lv is not None and lv[0] >= lv[1]:
                errors.append({"field": f"{where}.limits", "value": lim,
                               "message": "lower limit must be below upper limit"})
            limits.append([0.0, 0.0] if lv is None else list(lv * jscale))
        if "mass" in jd or "com" in jd:
            m = _finite_number(errors, f"{where}.mass", jd.get("mass"))
            if m is not None and not 0 <= m <= MAX_MASS_KG:
                errors.append({"field": f"{where}.mass", "value": m,
                               "message": f"mass must be between 0 and {MAX_MASS_KG:g} kg"})
            c = _vector(errors, f"{where}.com", jd.get("com", [0.0, 0.0, 0.0]), 3, len_bound, len_max)
            masses.append(m)
            coms.append(None if c is None else c * ls)
        else:
            masses.append(None)
            coms.append(None)
    tool = _vector(errors, "tool", doc.get("tool", [0.0, 0.0, 0.0]), 3, len_bound, len_max)
    gravity = _vector(errors, "gravity", doc.get("gravity", [0.0, 0.0, -9.81]))
    if gravity is not None and not float(np.linalg.norm(gravity)) <= MAX_GRAVITY_MS2:
        errors.append({"field": "gravity", "value": doc.get("gravity"),
                       "message": f"implausible: |gravity| is {float(np.linalg.norm(gravity)):.4g} m/s^2, at most "
                                  f"{MAX_GRAVITY_MS2:g} m/s^2 (the Earth's is 9.81; gravity is in m/s^2, not mm/s^2)"})
    has_mass = [m is not None for m in masses]
    if any(has_mass) and not all(has_mass):
        missing = [names[j] for j, h in enumerate(has_mass) if not h]
        errors.append({"field": "joints", "value": missing,
                       "message": "mass and com must be given for every joint or for none"})
    if errors:
        raise ModelError(errors)

    geometry = np.array(rows, dtype=float)
    tool = tool * ls
    mass = np.array(masses, dtype=float) if all(has_mass) else None
    com = np.array(coms, dtype=float) if all(has_mass) else None
    if convention == "dh":
        geometry, tool, com = _dh_to_mdh(geometry, tool, com)
    return RobotModel(
        name=name, joint_names=tuple(names), prismatic=np.array(prismatic), geometry=geometry,
        limits=np.array(limits, dtype=float), tool=tool, gravity=gravity, mass=mass, com=com,
        length_unit=lu, angle_unit=au, source_convention=convention,
    )


def _dh_to_mdh(dh: np.ndarray, tool: np.ndarray, com: np.ndarray | None):
    """Exact standard-DH -> MD-H rewrite.

    prod_i Rz(th_i) Tz(d_i) Tx(a_i) Rx(al_i) regroups as
    prod_i Rx(al_{i-1}) Tx(a_{i-1}) Rz(th_i) Tz(d_i), with the last Tx(a_n) Rx(al_n)
    folded into the tool point and every DH frame's COM moved into the MD-H frame.
    """
    n = len(dh)
    mdh = np.zeros_like(dh)
    mdh[:, 2:4] = dh[:, 2:4]  # d, theta
    mdh[1:, 0:2] = dh[:-1, 0:2]  # a_{i-1}, alpha_{i-1}
    a_n, al_n = dh[-1, 0], dh[-1, 1]
    tool = _rot_x(al_n) @ tool + np.array([a_n, 0.0, 0.0])
    if com is not None:
        com = np.array([_rot_x(dh[j, 1]) @ com[j] + np.array([dh[j, 0], 0.0, 0.0]) for j in range(n)])
    return mdh, tool, com
