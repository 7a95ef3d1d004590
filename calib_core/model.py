"""The robot model of the contract (section 1): MD-H or standard DH joints, units, validation.

Internally every length is in mm and every angle in rad; `units` only says how the
user wrote the model and how answers are given back.  Standard DH is converted
exactly to MD-H (Craig / Hayati) so that one kinematics and one Jacobian serve both.
"""
from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass, field

import numpy as np

LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0}
ANGLE_TO_RAD = {"deg": math.pi / 180.0, "rad": 1.0}
GEOMETRIC = ("a", "alpha", "d", "theta", "beta", "gamma", "b")
"""Per-row geometric parameters in the order of the parameter vector: the MD-H row
``Rx(alpha) Tx(a) Ry(gamma) Ty(b) Rz(theta [+q]) Tz(d [+q]) Ry(beta)``. `gamma` and `b` are the y-counterparts of
`alpha` and `a` (zero in a plain MD-H row): with them the constant part of every row, before its joint moves, is a
complete rigid transform (three turns and three shifts), so any error of any joint origin is absorbed whatever
form the row was given in (xyz/rpy/axis rows, a tree's second branch, fixed rows); the identifiability analysis
takes them only where the classic parameters cannot say the same (docs/REAL_CELLS.md, "Completeness")."""
MDH = GEOMETRIC[:5]
"""The classic MD-H (Hayati) parameters; `gamma` and `b` extend them."""
ANGULAR = {"alpha", "theta", "beta", "gamma"}

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
MAX_COUPLING = 1e3
"""|coefficient| of a coupled joint in the model's units: a linkage, gear or mimic ratio (Agile Justin -1, a
telescopic column 0.5); 1e200 made the drive's load overflow into an SVD that did not converge."""
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
RESERVED_COLUMNS = ("point", "x", "y", "z", "timestamp", "sequence", "temperature", "payload", "payload_kg", "sigma",
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

    `geometry` is (n, 7): a_{i-1}, alpha_{i-1}, d_i, theta_i, beta_i, gamma_i, b_i for each joint row (GEOMETRIC).
    `limits` are in joint units (rad for revolute, mm for prismatic).
    """

    name: str
    joint_names: tuple[str, ...]
    prismatic: np.ndarray  # (n,) bool
    geometry: np.ndarray  # (n, 7): GEOMETRIC
    limits: np.ndarray  # (n, 2)
    tool: np.ndarray  # (3,) mm, in the last joint frame
    gravity: np.ndarray  # (3,) m/s^2 in the robot base frame
    mass: np.ndarray | None = None  # (n,) kg
    com: np.ndarray | None = None  # (n, 3) mm in each joint's MD-H frame
    length_unit: str = "mm"
    angle_unit: str = "deg"
    source_convention: str = "mdh"
    extra: dict = field(default_factory=dict)
    # real cells (contract section 5); the defaults make a serial chain with one target at the last row
    parent: np.ndarray | None = None  # (n,) int: the row each row follows, -1 = the base; default the previous
    fixed: np.ndarray | None = None  # (n,) bool: rows without a joint variable
    coupling: tuple = ()  # ((row, ((src_row, coef), ...), offset in internal units), ...): mimic joints
    pre: np.ndarray | None = None  # (n, 4, 4) constant transform before each row's MD-H (rows given as xyz/rpy)
    align: np.ndarray | None = None  # (n, 3, 3): each row's user (URDF) link frame -> its joint frame (z = axis)
    targets: tuple = ()  # ((name, row, xyz (3,) mm in the row's frame), ...); empty: ("tool", n - 1, tool)

    @property
    def n_joints(self) -> int:
        """Rows of the kinematic model (fixed and coupled ones included)."""
        return len(self.joint_names)

    @property
    def parents(self) -> np.ndarray:
        return np.arange(self.n_joints) - 1 if self.parent is None else self.parent

    @property
    def is_fixed(self) -> np.ndarray:
        return np.zeros(self.n_joints, bool) if self.fixed is None else self.fixed

    @property
    def is_coupled(self) -> np.ndarray:
        out = np.zeros(self.n_joints, bool)
        out[[c[0] for c in self.coupling]] = True
        return out

    @property
    def actuated(self) -> np.ndarray:
        """Rows whose value is measured and commanded (a CSV column each): neither fixed nor coupled."""
        return np.flatnonzero(~self.is_fixed & ~self.is_coupled)

    @property
    def actuated_names(self) -> tuple[str, ...]:
        return tuple(self.joint_names[j] for j in self.actuated)

    @property
    def moving(self) -> np.ndarray:
        """Rows with a joint variable (actuated or coupled), where joint-space causes can act."""
        return ~self.is_fixed

    @property
    def is_serial(self) -> bool:
        return (self.parent is None or bool(np.all(self.parent == np.arange(self.n_joints) - 1))) \
            and len(self.target_rows) == 1 and self.target_rows[0] == self.n_joints - 1

    @property
    def target_names(self) -> tuple[str, ...]:
        return tuple(t[0] for t in self.targets) if self.targets else ("tool",)

    @property
    def target_rows(self) -> np.ndarray:
        return np.array([t[1] for t in self.targets] if self.targets else [self.n_joints - 1], dtype=int)

    @property
    def target_points(self) -> np.ndarray:
        """(T, 3) mm, each target in its row's MD-H frame."""
        return np.array([t[2] for t in self.targets], float) if self.targets else self.tool[None].copy()

    @property
    def n_targets(self) -> int:
        return len(self.target_names)

    def ancestors(self) -> np.ndarray:
        """(n, n) bool: [r, j] is True when row j is row r or on its way from the base."""
        n, par = self.n_joints, self.parents
        A = np.eye(n, dtype=bool)
        for j in range(n):
            if par[j] >= 0:
                A[j] |= A[par[j]]
        return A

    def descendants(self, j: int) -> np.ndarray:
        """Rows carried by row j (itself included), in row order."""
        return np.flatnonzero(self.ancestors()[:, j])

    def expand_joints(self, q_act: np.ndarray) -> np.ndarray:
        """Row values (N, n) in internal units from the actuated joints' values (N, n_act): fixed rows 0,
        coupled rows their linear combination."""
        q_act = np.atleast_2d(np.asarray(q_act, float))
        q = np.zeros((q_act.shape[0], self.n_joints))
        q[:, self.actuated] = q_act
        for row, terms, offset in self.coupling:
            q[:, row] = offset + sum(c * q[:, src] for src, c in terms)
        return q

    def coupling_matrix(self) -> np.ndarray:
        """(n, n_act): d(row values) / d(actuated values)."""
        act = self.actuated
        A = np.zeros((self.n_joints, len(act)))
        A[act, np.arange(len(act))] = 1.0
        for row, terms, _ in self.coupling:
            A[row] = sum(c * A[src] for src, c in terms)
        return A

    def drive_motion(self) -> np.ndarray:
        """(n, n): column j, how each row moves per unit motion of row j's own drive. An actuated row's drive
        moves the coupled rows that follow it by their coefficients (a drive's deflection, play or gear error
        turns the whole coupled mechanism); a coupled or fixed row moves only itself."""
        M = np.eye(self.n_joints)
        if self.coupling:
            M[:, self.actuated] = self.coupling_matrix()
        return M

    def followers(self, j: int) -> np.ndarray:
        """The coupled rows that row j's drive turns with it (drive_motion), itself excluded."""
        moved = np.flatnonzero(self.drive_motion()[:, j])
        return moved[moved != j]

    @property
    def has_mass(self) -> bool:
        return self.mass is not None

    def joint_scale(self) -> np.ndarray:
        """Factor from user joint units to internal units (rad or mm) per joint, shape (n,)."""
        return np.where(self.prismatic, LENGTH_TO_MM[self.length_unit], ANGLE_TO_RAD[self.angle_unit])

    def joint_unit(self, j: int) -> str:
        return self.length_unit if self.prismatic[j] else self.angle_unit

    def to_dict(self, geometry: np.ndarray | None = None, tool: np.ndarray | None = None) -> dict:
        """The model as contract JSON, optionally with calibrated geometry / target points ((3,) or (T, 3)).

        MD-H rows (with `parent`, `coupled`, `fixed` and `targets` where the model has them); a model given with
        xyz/rpy/axis rows is written back that way, each row's origin from the identified geometry."""
        g = self.geometry if geometry is None else geometry
        tools = self.target_points if tool is None else np.asarray(tool, float).reshape(-1, 3)
        ls, an = LENGTH_TO_MM[self.length_unit], ANGLE_TO_RAD[self.angle_unit]
        js = self.joint_scale()
        general = self.pre is not None
        if general:
            links, targets_xyz, coms = self._link_frames(g, tools)
        else:
            targets_xyz, coms = tools, self.com
        couple = {row: (terms, off) for row, terms, off in self.coupling}
        joints = []
        for j, name in enumerate(self.joint_names):
            kind = "fixed" if self.is_fixed[j] else "prismatic" if self.prismatic[j] else "revolute"
            row = {"name": name, "type": kind}
            if self.parent is not None and self.parent[j] != j - 1:
                row["parent"] = "base" if self.parent[j] < 0 else self.joint_names[self.parent[j]]
            if general:
                row["xyz"] = [float(v / ls) for v in links[j][:3, 3]]
                row["rpy"] = [float(v / an) for v in _rpy(links[j][:3, :3])]
                row["axis"] = [float(v) for v in (self.align[j][:, 2] if self.align is not None else (0, 0, 1))]
            else:
                for k, p in enumerate(GEOMETRIC):
                    if p in MDH or g[j, k] != 0.0:  # gamma and b only where a calibration (or the user) set them
                        row[p] = float(g[j, k] / (an if p in ANGULAR else ls))
            if j in couple:
                terms, off = couple[j]
                row["coupled"] = {self.joint_names[src]: float(c * js[src] / js[j]) for src, c in terms}
                if off:
                    row["coupled"]["offset"] = float(off / js[j])
            if not self.is_fixed[j] and np.isfinite(self.limits[j]).all():
                row["limits"] = [float(v / js[j]) for v in self.limits[j]]
            if self.mass is not None:
                row["mass"] = float(self.mass[j])
                row["com"] = [float(v / ls) for v in coms[j]]
            joints.append(row)
        doc = {"name": self.name, "convention": "mdh", "units": {"length": self.length_unit, "angle": self.angle_unit},
               "joints": joints}
        if self.targets or general:
            doc["targets"] = [{"name": t, "parent": self.joint_names[r], "xyz": [float(v / ls) for v in xyz]}
                              for t, r, xyz in zip(self.target_names, self.target_rows, targets_xyz)]
        else:
            doc["tool"] = [float(v / ls) for v in tools[0]]
        doc["gravity"] = [float(v) for v in self.gravity]
        return doc

    def _link_frames(self, g: np.ndarray, tools: np.ndarray):
        """For xyz/rpy export at geometry g: each row's origin (4x4, mm) in its parent's link frame, the targets and
        centres of mass in their rows' link frames. A row's link frame is the user's: its joint frame before
        Ry(beta) turned back by `align`, so the axes and link orientations written are the ones given."""
        from .kinematics import Chain  # the kinematics builds on this module

        n = self.n_joints
        x = np.concatenate([g.ravel(), np.zeros(6), tools.ravel()])
        ch = Chain(self, x, np.zeros((1, n)))
        C = np.empty((n, 4, 4))
        for j in range(n):
            C[j] = np.eye(4)
            C[j, :3, :3] = ch.R[j, 0] @ _rot_y(-g[j, 4]) @ (self.align[j].T if self.align is not None else np.eye(3))
            C[j, :3, 3] = ch.o_beta[j, 0]
        inv = np.linalg.inv(C)
        par = self.parents
        links = [C[j] if par[j] < 0 else inv[par[j]] @ C[j] for j in range(n)]
        world = lambda j, v: ch.o_beta[j, 0] + ch.R[j, 0] @ v  # noqa: E731
        local = lambda j, w: inv[j, :3, :3] @ w + inv[j, :3, 3]  # noqa: E731
        targets = [local(r, world(r, t)) for r, t in zip(self.target_rows, tools)]
        coms = None if self.com is None else [local(j, world(j, self.com[j])) for j in range(n)]
        return links, targets, coms


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw (rad) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return np.array([math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0]))),
                     math.atan2(R[1, 0], R[0, 0])])


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


MODEL_KEYS = ("name", "convention", "units", "joints", "tool", "targets", "gravity", "meta", "urdf", "calibration")
"""The keys a model document may carry: the contract's (sections 1 and 5), `meta` (the user's own free-form data),
and the two objects the project writes into the documents it answers (`urdf`, the import's extension;
`calibration`, a calibrated model's effects and base pose), so an answer can be posted back."""
JOINT_KEYS = ("name", "type", *GEOMETRIC, "xyz", "rpy", "axis", "limits", "mass", "com", "parent", "coupled", "meta")
TARGET_KEYS = ("name", "parent", "xyz", "meta")
UNIT_KEYS = ("length", "angle")
MAX_KEY_ERRORS = 50
"""Unknown keys listed at most (as NaN, NUL and depth problems are)."""


def _unknown_keys(errors: list, where: str, obj, allowed: tuple[str, ...]) -> None:
    """A 422 entry for every key of `obj` (a dict) that `allowed` does not hold, with the nearest valid key: a
    misspelt key must never change the robot silently (contract section 1)."""
    if not isinstance(obj, dict):
        return
    for k in obj:
        if k in allowed:
            continue
        if len(errors) >= MAX_KEY_ERRORS:  # a document of a million unknown keys gets a bounded answer
            return
        k = str(k)[:80]  # echoed, not the whole of a 5 MB key
        near = difflib.get_close_matches(k, allowed, n=1, cutoff=0.6)
        hint = f"did you mean '{near[0]}'? " if near else ""
        errors.append({"field": f"{where}.{k}" if where else k, "value": k,
                       "message": f"unknown key; {hint}valid here: {', '.join(allowed)} (free-form data of your "
                                  "own goes under 'meta')"})


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
    _unknown_keys(errors, "", doc, MODEL_KEYS)
    _unknown_keys(errors, "units", doc.get("units"), UNIT_KEYS)
    for j, jd in enumerate(doc.get("joints") if isinstance(doc.get("joints"), list) else []):
        _unknown_keys(errors, f"joints[{j}]", jd, JOINT_KEYS)
    for k, t in enumerate(doc.get("targets") if isinstance(doc.get("targets"), list) else []):
        _unknown_keys(errors, f"targets[{k}]", t, TARGET_KEYS)
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
    fixed, parent_names, couplings, origins, axes = [], [], [], [], []
    for j, jd in enumerate(joints):
        where = f"joints[{j}]"
        if not isinstance(jd, dict):
            errors.append({"field": where, "value": jd, "message": "must be an object"})
            jd = {"name": f"_{j}"}
        jname = jd.get("name")
        why = name_problem(jname)
        if why:
            errors.append({"field": f"{where}.name", "value": jname, "message": why})
        elif jname in names:
            errors.append({"field": f"{where}.name", "value": jname, "message": "duplicate joint name"})
        names.append(jname)
        jtype = jd.get("type", "revolute")
        if not isinstance(jtype, str) or jtype not in JOINT_TYPES:
            errors.append({"field": f"{where}.type", "value": jtype,
                           "message": "must be 'revolute', 'prismatic' or 'fixed'"})
        prismatic.append(jtype == "prismatic")
        fixed.append(jtype == "fixed")
        parent_names.append(jd.get("parent", _PREVIOUS))
        general = any(k in jd for k in ("xyz", "rpy", "axis"))
        row = []
        if general:  # the URDF way: a transform from the parent's link frame, then motion about / along `axis`
            given = [p for p in GEOMETRIC if p in jd]
            if given:
                errors.append({"field": f"{where}.{given[0]}", "value": jd[given[0]],
                               "message": "give a row either as MD-H constants or as xyz/rpy/axis, not both"})
            xyz = _vector(errors, f"{where}.xyz", jd.get("xyz", [0.0, 0.0, 0.0]), 3, len_bound, len_max)
            rpy = _vector(errors, f"{where}.rpy", jd.get("rpy", [0.0, 0.0, 0.0]), 3, ang_bound, ang_max)
            axis = _vector(errors, f"{where}.axis", jd.get("axis", [0.0, 0.0, 1.0]), 3)
            if axis is not None and not np.linalg.norm(axis) > 1e-9:
                errors.append({"field": f"{where}.axis", "value": jd.get("axis"), "message": "must not be zero"})
                axis = None
            origins.append(None if xyz is None or rpy is None else _origin(xyz * ls, rpy * an))
            axes.append(None if axis is None else axis / np.linalg.norm(axis))
            row = [0.0] * len(GEOMETRIC)
        else:
            origins.append(None)
            axes.append(None)
            for p in GEOMETRIC:
                if p in ("beta", "gamma", "b") and convention == "dh":
                    if jd.get(p, 0) not in (0, 0.0):
                        errors.append({"field": f"{where}.{p}", "value": jd.get(p),
                                       "message": f"standard DH has no {p}; use convention 'mdh'"})
                    row.append(0.0)
                    continue
                v = _finite_number(errors, f"{where}.{p}", jd.get(p, 0.0))
                if p in ANGULAR:
                    v = _in_range(errors, f"{where}.{p}", v, ang_bound, ang_max)
                else:
                    v = _in_range(errors, f"{where}.{p}", v, len_bound, len_max)
                row.append(0.0 if v is None else v * (an if p in ANGULAR else ls))
        rows.append(row)
        couplings.append(jd.get("coupled"))
        if couplings[-1] is not None and jtype == "fixed":
            errors.append({"field": f"{where}.coupled", "value": couplings[-1],
                           "message": "a fixed row has no joint value to couple"})
        lim = jd.get("limits")
        jscale = ls if jtype == "prismatic" else an
        if jtype == "fixed":
            if lim is not None:
                errors.append({"field": f"{where}.limits", "value": lim, "message": "a fixed row has no limits"})
            limits.append([0.0, 0.0])
        elif lim is None:
            lim = [-math.inf, math.inf] if jtype != "prismatic" or couplings[-1] is not None else None
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
    prismatic_a = np.array(prismatic, bool)
    scale = np.where(prismatic_a, ls, an)
    parent = _parents(errors, names, parent_names)
    coupling = _couplings(errors, names, couplings, fixed, scale)
    targets_doc = doc.get("targets")
    if targets_doc is not None and "tool" in doc:
        errors.append({"field": "tool", "value": doc["tool"],
                       "message": "give either `tool` (one target at the last row) or `targets`, not both"})
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
    targets = _targets(errors, names, targets_doc, len_bound, len_max, ls) if targets_doc is not None else ()
    fixed_a = np.array(fixed, bool)
    general = any(o is not None for o in origins) or any(a is not None for a in axes)
    tree = parent is not None and not np.all(parent == np.arange(len(names)) - 1)
    if convention == "dh" and (general or tree or targets or fixed_a.any() or coupling):
        errors.append({"field": "convention", "value": "dh", "message": "rows with parent, fixed rows, coupled "
                       "joints, targets or xyz/rpy need convention 'mdh' (or xyz/rpy/axis rows)"})
    if errors:
        raise ModelError(errors)

    geometry = np.array(rows, dtype=float)
    tool = tool * ls
    mass = np.array(masses, dtype=float) if all(has_mass) else None
    com = np.array(coms, dtype=float) if all(has_mass) else None
    pre = align = None
    if general:  # each row's constant part in its parent's joint frame; points given in a link frame moved in
        par = np.arange(len(names)) - 1 if parent is None else parent
        align = np.array([np.eye(3) if a is None else _z_to(a) for a in axes])
        pre = np.array([(_hom(align[par[j]].T) if par[j] >= 0 else np.eye(4))
                        @ (np.eye(4) if origins[j] is None else origins[j]) @ _hom(align[j]) for j in range(len(names))])
        if com is not None:
            com = np.einsum("jba,jb->ja", align, com)
        targets = tuple((t, r, align[r].T @ v) for t, r, v in targets)
        tool = align[-1].T @ tool
    if convention == "dh":
        geometry, tool, com = _dh_to_mdh(geometry, tool, com)
    if targets:
        tool = targets[0][2].copy()
    return RobotModel(
        name=name, joint_names=tuple(names), prismatic=prismatic_a, geometry=geometry,
        limits=np.array(limits, dtype=float), tool=tool, gravity=gravity, mass=mass, com=com,
        length_unit=lu, angle_unit=au, source_convention=convention,
        parent=parent, fixed=fixed_a if fixed_a.any() else None, coupling=coupling, pre=pre, align=align,
        targets=targets,
    )


JOINT_TYPES = ("revolute", "prismatic", "fixed")
_PREVIOUS = object()
"""`parent` not given: the row follows the previous row (the base for the first)."""


def _hom(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _origin(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    """URDF origin: Trans(xyz) Rz(yaw) Ry(pitch) Rx(roll), lengths mm, angles rad."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                          [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                          [-sp, cp * sr, cp * cr]])
    T[:3, 3] = xyz
    return T


def _z_to(axis: np.ndarray) -> np.ndarray:
    """The smallest rotation taking z to the unit vector `axis` (a half turn about x for -z)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, axis), float(z @ axis)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + V + V @ V / (1 + c)


def _parents(errors, names, given) -> np.ndarray | None:
    """Row index of each row's parent (-1: the base); None when every row follows the previous one."""
    if all(p is _PREVIOUS for p in given):
        return None
    out = np.arange(len(names)) - 1
    for j, p in enumerate(given):
        if p is _PREVIOUS:
            continue
        if p is None or p == "base":
            out[j] = -1
        elif not isinstance(p, str) or p not in names[:j]:
            why = ("must name a joint listed before this one (or 'base')" if p not in names
                   else "must name a joint listed before this one: list a tree from the base outwards")
            errors.append({"field": f"joints[{j}].parent", "value": p, "message": why})
        else:
            out[j] = names.index(p)
    return out


def _couplings(errors, names, given, fixed, scale) -> tuple:
    """Mimic joints: (row, ((src_row, coef), ...), offset) in internal units; sources are actuated joints or
    coupled joints listed before, so the values follow in row order."""
    out, coupled_rows = [], set()
    for j, c in enumerate(given):
        if c is None:
            continue
        where = f"joints[{j}].coupled"
        if not isinstance(c, dict) or not c:
            errors.append({"field": where, "value": c, "message": "must be an object {joint: coefficient, ...}"})
            continue
        terms, offset = [], 0.0
        for k, v in c.items():
            v = _finite_number(errors, f"{where}.{k}", v)
            if v is None:
                continue
            if k == "offset":
                offset = v * scale[j]
            elif abs(v) > MAX_COUPLING:
                errors.append({"field": f"{where}.{k}", "value": v,
                               "message": f"a coupling coefficient must be within +-{MAX_COUPLING:g} (model units)"})
            elif k not in names or k == names[j]:
                errors.append({"field": f"{where}.{k}", "value": k, "message": "must name another joint of the model"})
            elif fixed[names.index(k)]:
                errors.append({"field": f"{where}.{k}", "value": k, "message": "a fixed row has no value to follow"})
            elif names.index(k) in {r for r in range(len(names)) if given[r] is not None} and names.index(k) not in coupled_rows:
                errors.append({"field": f"{where}.{k}", "value": k,
                               "message": "a coupled joint may follow another coupled joint only if that one is "
                                          "listed before it"})
            else:
                src = names.index(k)
                terms.append((src, v * scale[j] / scale[src]))
        coupled_rows.add(j)
        out.append((j, tuple(terms), offset))
    return tuple(out)


def _targets(errors, names, doc, len_bound, len_max, ls) -> tuple:
    """((name, row, xyz mm in the row's link frame), ...) from the model's `targets` list."""
    if not isinstance(doc, list) or not doc:
        errors.append({"field": "targets", "value": doc, "message": "must be a non-empty list of "
                       "{name, parent, xyz}"})
        return ()
    out, seen = [], set()
    for k, t in enumerate(doc):
        where = f"targets[{k}]"
        if not isinstance(t, dict):
            errors.append({"field": where, "value": t, "message": "must be an object {name, parent, xyz}"})
            continue
        tname = t.get("name")
        why = name_problem(tname, what="target name", csv_column=False)
        if why or tname in seen:
            errors.append({"field": f"{where}.name", "value": tname, "message": why or "duplicate target name"})
        seen.add(tname)
        p = t.get("parent", names[-1])
        if p not in names:
            errors.append({"field": f"{where}.parent", "value": p, "message": "must name a joint of the model"})
            continue
        xyz = _vector(errors, f"{where}.xyz", t.get("xyz", [0.0, 0.0, 0.0]), 3, len_bound, len_max)
        if xyz is not None:
            out.append((tname, names.index(p), xyz * ls))
    return tuple(out)


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
