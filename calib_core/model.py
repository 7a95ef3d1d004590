"""The robot model of the contract (section 1): MD-H or standard DH joints, units, validation.

Internally every length is in mm and every angle in rad; `units` only says how the
user wrote the model and how answers are given back.  Standard DH is converted
exactly to MD-H (Craig / Hayati) so that one kinematics and one Jacobian serve both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0}
ANGLE_TO_RAD = {"deg": math.pi / 180.0, "rad": 1.0}
GEOMETRIC = ("a", "alpha", "d", "theta", "beta")
"""Per-joint MD-H parameters in the order of the parameter vector."""
ANGULAR = {"alpha", "theta", "beta"}


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


def _vector(errors, fieldname, value, n=3) -> np.ndarray | None:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        errors.append({"field": fieldname, "value": value, "message": f"must be a list of {n} numbers"})
        return None
    out = [_finite_number(errors, f"{fieldname}[{k}]", v) for k, v in enumerate(value)]
    return None if any(v is None for v in out) else np.array(out, dtype=float)


def parse_model(doc: dict) -> RobotModel:
    """Validate contract model JSON and build a RobotModel; raises ModelError listing every problem."""
    errors: list[dict] = []
    if not isinstance(doc, dict):
        raise ModelError([{"field": "", "value": type(doc).__name__, "message": "model must be a JSON object"}])
    name = doc.get("name", "robot")
    if not isinstance(name, str) or not name.strip():
        errors.append({"field": "name", "value": name, "message": "must be a non-empty string"})
    convention = doc.get("convention", "mdh")
    if convention not in ("mdh", "dh"):
        errors.append({"field": "convention", "value": convention, "message": "must be 'mdh' or 'dh'"})
    units = doc.get("units", {"length": "mm", "angle": "deg"})
    if not isinstance(units, dict):
        errors.append({"field": "units", "value": units, "message": "must be an object {length, angle}"})
        units = {}
    lu, au = units.get("length", "mm"), units.get("angle", "deg")
    if lu not in LENGTH_TO_MM:
        errors.append({"field": "units.length", "value": lu, "message": "unknown length unit; use 'mm' or 'm'"})
    if au not in ANGLE_TO_RAD:
        errors.append({"field": "units.angle", "value": au, "message": "unknown angle unit; use 'deg' or 'rad'"})
    ls, an = LENGTH_TO_MM.get(lu, 1.0), ANGLE_TO_RAD.get(au, 1.0)

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
        if not isinstance(jname, str) or not jname.strip() or "," in jname:
            errors.append({"field": f"{where}.name", "value": jname,
                           "message": "must be a non-empty string without commas (it is a CSV column)"})
        elif jname in names:
            errors.append({"field": f"{where}.name", "value": jname, "message": "duplicate joint name"})
        names.append(jname)
        jtype = jd.get("type", "revolute")
        if jtype not in ("revolute", "prismatic"):
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
            lv = _vector(errors, f"{where}.limits", lim, 2)
            if lv is not None and lv[0] >= lv[1]:
                errors.append({"field": f"{where}.limits", "value": lim,
                               "message": "lower limit must be below upper limit"})
            limits.append([0.0, 0.0] if lv is None else list(lv * jscale))
        if "mass" in jd or "com" in jd:
            m = _finite_number(errors, f"{where}.mass", jd.get("mass"))
            if m is not None and m < 0:
                errors.append({"field": f"{where}.mass", "value": m, "message": "mass must be >= 0 kg"})
            c = _vector(errors, f"{where}.com", jd.get("com", [0.0, 0.0, 0.0]))
            masses.append(m)
            coms.append(None if c is None else c * ls)
        else:
            masses.append(None)
            coms.append(None)
    tool = _vector(errors, "tool", doc.get("tool", [0.0, 0.0, 0.0]))
    gravity = _vector(errors, "gravity", doc.get("gravity", [0.0, 0.0, -9.81]))
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
