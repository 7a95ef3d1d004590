"""The calibrated URDF as the original file patched (issue 30): a drop-in ``robot_description``.

:func:`patch_urdf` takes the URDF a model was imported from (its text, kept by the import as
``doc["urdf"]["source"]``), the nominal model and the calibrated geometry, and returns the same text with only
the ``<origin xyz rpy>`` attributes of the joints the calibration moved rewritten: every link and joint name,
mesh, collision, inertial, transmission, gazebo tag, comment and attribute order stays as it was, byte for byte,
so a unified diff of the original against the export shows the changed origin lines and one comment line (plus
the base joint when asked). What a URDF has no place for goes into a side document (:attr:`PatchedUrdf.side`,
served as ``calibration.json``).

Method (exact, whatever form the model rows were given in: MD-H folded chain or xyz/rpy/axis rows)

* For every model row r, its body frame at q = 0 in the model's base frame, ``G_r``: the row's frame before its
  post-motion ``Ry(beta)`` (:class:`calib_core.kinematics.Chain` with the base block of the parameter vector
  zeroed and R0 = identity: rotation ``R[r] Ry(-beta_r)``, origin ``o_beta[r]``). Its z axis is the joint axis
  and its origin lies on it, for the nominal and for the calibrated parameters alike.
* ``D_r = G_r(calibrated) G_r(nominal)^-1`` is the rigid motion that takes row r's nominal body onto its
  calibrated body; it maps the nominal joint axis (a line) onto the calibrated one exactly.
* Each URDF link is carried by one row: the row whose URDF joint (rows are named after their URDF joints in
  both forms) has it as child link, else the row carrying its parent link (through fixed joints and joints the
  model did not take in: off-path branches, fingers, sensors); the URDF base link and everything not below it
  by none (D = identity). Its calibrated frame at q = 0 is ``D_r L(link)``, ``L`` its nominal frame from the
  URDF's own origins. In the MD-H form the model's base frame is ``B`` in the URDF base link (``base_xyz`` /
  ``base_rpy`` of the ``urdf`` extension), so ``D`` acts as ``B D_r B^-1`` there.
* A joint's new origin is ``L'(parent)^-1 L'(child)``; its axis, given in its child link's frame, is unchanged
  (D moves the child link and the axis together). A joint whose parent and child links are carried by the same
  row keeps its text; so does an origin whose new value equals the old to 1e-12 m / rad (e.g. a row the
  calibration left alone), attribute by attribute (a new ``xyz`` may come with the old ``rpy`` text).
* The URDF then moves every link as the calibrated model moves its rows: at q = 0 by construction, and at any q
  because each joint turns (slides) about (along) the same line in its child link as before, which D maps onto
  the calibrated joint axis. Joint offsets (``theta``) are absorbed in the origins exactly: a URDF joint has
  no zero offset of its own; URDF ``<calibration>`` (a homing switch position) is not used.

Side document (what a URDF cannot hold; lengths m, angles rad, URDF frames)

* ``targets``: each calibrated SMR / marker point in its target link's frame (the calibrated link).
* ``base_poses``: per setup, the URDF base link's pose in the measurement (tracker) frame.
* ``effects``: the identified effects (joint compliance, scale, backlash, ...) with their values, as the
  calibration stores them: predict and compensate include them, the URDF does not.
* ``mimic``: every coupled row's multiplier / offset (URDF units) and whether the export changed them (a mimic
  joint whose source is the joint the model couples it to gets its ``<mimic multiplier offset>`` rewritten when
  they differ; a coupling a URDF mimic cannot say stays here).
* ``changed_joints``, ``base_joint``, the source's base link and the method in one sentence.

``base_joint``: with a name (``True``: ``measurement_frame``), a new root link of that name and a fixed joint
``<name>_joint`` from it to the URDF's root link are added after the comment, carrying the identified pose of
setup `setup` (the root link's pose in the measurement frame), so TF has the tracker frame. When movable joints
lie between the URDF root and the model's base link, that pose holds with them at zero (the side document says
so).

Not handled: a URDF whose XML declaration names an encoding other than UTF-8 with non-ASCII text (the answer is
UTF-8 text with the declaration as it was).
"""
from __future__ import annotations

import json
import math
import re
import xml.parsers.expat as expat
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .model import ANGLE_TO_RAD, GEOMETRIC, LENGTH_TO_MM, ModelError, RobotModel, parse_model
from .urdf import EXTENSION, matrix_rpy, origin_matrix
from .urdf_xml import MOVABLE, UrdfError, _parse_joints, _read

DEFAULT_BASE_LINK = "measurement_frame"
"""The new root link's name for ``base_joint=True``."""
SIDE_FILE = "calibration.json"
"""The side document's file name (``GET /calibrations/{id}/urdf/calibration.json``)."""
SAME_M = 1e-12
"""An origin's translation (m) or rotation (matrix entries) that moved less than this keeps its text."""
CONSISTENT_MM = 1e-6
"""The nominal model and the URDF must agree to this (mm, and 1e-9 rad) on every movable row's joint axis line."""
FORMAT = "calib-urdf-calibration/1"

_BETA = GEOMETRIC.index("beta")


@dataclass
class PatchedUrdf:
    """The patched URDF text, the side document, and which joints' origins changed."""

    urdf: str
    side: dict
    changed: list[str] = field(default_factory=list)

    def side_json(self) -> str:
        return json.dumps(self.side, indent=2) + "\n"


# --- small geometry ----------------------------------------------------------------------

def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    R = T[:3, :3].T
    out[:3, :3] = R
    out[:3, 3] = -R @ T[:3, 3]
    return out


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _f(v: float) -> str:
    v = float(v)
    return "0" if v == 0.0 else repr(v)


def _vec(v) -> str:
    return " ".join(_f(c) for c in v)


def row_frames(model: RobotModel, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row at q = 0 in the model's base frame (mm): the body frame G (n, 4, 4) (before ``Ry(beta)``: z the
    joint axis, origin on it), the full row frame F (n, 4, 4) the targets are given in, and the target points
    (T, 3) mm in their rows' frames F; from the parameter vector `x` with its base block zeroed and R0 = I."""
    from .kinematics import Chain, layout

    x = np.array(x, float)
    lay = layout(model, x)
    x[lay.bases] = 0.0
    n = model.n_joints
    ch = Chain(model, x, np.zeros((1, n)), np.eye(3))
    g = x[lay.geometry].reshape(n, len(GEOMETRIC))
    R, o = ch.R[:, 0], ch.o_beta[:, 0]
    G = np.tile(np.eye(4), (n, 1, 1))
    F = G.copy()
    F[:, :3, :3], F[:, :3, 3] = R, o
    G[:, :3, :3] = np.einsum("nab,nbc->nac", R, np.array([_ry(-b) for b in g[:, _BETA]]))
    G[:, :3, 3] = o
    return G, F, x[lay.tools].reshape(-1, 3)


# --- locating elements in the text ----------------------------------------------------------

_ATTR = re.compile(rb"""\s+([^\s=/>]+)\s*=\s*("[^"]*"|'[^']*')""")


def _tag_end(b: bytes, start: int) -> int:
    """Index of the '>' closing the start tag that begins at `start` (quote-aware)."""
    q = None
    for i in range(start, len(b)):
        c = b[i]
        if q is not None:
            if c == q:
                q = None
        elif c in (0x22, 0x27):
            q = c
        elif c == 0x3E:
            return i
    raise UrdfError([{"field": "urdf", "value": start, "message": "a start tag is not closed"}])


@dataclass
class _Places:
    robot_end: int = -1  # '>' of <robot ...>
    joint: dict = field(default_factory=dict)  # name -> (start of <joint, '>' of it)
    origin: dict = field(default_factory=dict)  # joint name -> start of its first <origin
    mimic: dict = field(default_factory=dict)  # joint name -> start of its first <mimic
    indent: bytes = b"  "  # of the robot's children
    child_indent: dict = field(default_factory=dict)  # joint name -> indentation of its first child


def _places(text: str, b: bytes) -> _Places:
    out = _Places()
    p = expat.ParserCreate()
    stack: list[tuple[str, Any]] = []
    first_child = [True]

    def indent_at(off: int) -> bytes:
        k = b.rfind(b"\n", 0, off)
        ws = b[k + 1: off]
        return ws if ws.strip() == b"" else b""

    def start(name, attrs):
        off = p.CurrentByteIndex
        depth = len(stack)
        tag = None
        if depth == 0 and name == "robot":
            out.robot_end = _tag_end(b, off)
        elif depth == 1:
            if first_child[0]:
                first_child[0] = False
                out.indent = indent_at(off) or b"  "
            if name == "joint" and attrs.get("name") and attrs["name"] not in out.joint:
                tag = attrs["name"]
                out.joint[tag] = (off, _tag_end(b, off))
        elif depth == 2 and stack[-1][0] == "joint" and stack[-1][1] is not None:
            jn = stack[-1][1]
            out.child_indent.setdefault(jn, indent_at(off))
            if name == "origin":
                out.origin.setdefault(jn, off)
            elif name == "mimic":
                out.mimic.setdefault(jn, off)
        stack.append((name, tag))

    def end(name):
        stack.pop()

    p.StartElementHandler, p.EndElementHandler = start, end
    p.Parse(text, True)
    return out


def _set_attrs(b: bytes, start: int, values: dict[str, str]) -> tuple[int, int, bytes]:
    """(start, end, new bytes) of the start tag at `start` with the attributes in `values` set: an existing
    attribute's value replaced in place (its quotes kept), a missing one appended after the last attribute."""
    end = _tag_end(b, start)
    tag = b[start: end + 1]
    m = re.match(rb"<[^\s/>]+", tag)
    pos, seen, last, quote = m.end(), set(), m.end(), b'"'
    out = bytearray(tag[: m.end()])
    while True:
        a = _ATTR.match(tag, pos)
        if a is None:
            break
        name = a.group(1).decode()
        quote = a.group(2)[:1]
        if name in values:
            q = a.group(2)[:1]
            out += tag[pos: a.start(2)] + q + values[name].encode() + q
            seen.add(name)
        else:
            out += tag[pos: a.end()]
        pos = last = a.end()
    for name, v in values.items():
        if name not in seen:
            out += b" " + name.encode() + b"=" + quote + v.encode() + quote  # in the tag's own quotes
    out += tag[last:]
    return start, end + 1, bytes(out)


def _comment(text: str) -> str:
    return "<!-- " + text.replace("--", "- -").rstrip("-") + " -->"


def _quote(s: str) -> str:
    from xml.sax.saxutils import quoteattr

    return quoteattr(s)


# --- the patch ------------------------------------------------------------------------------

def _base_matrix(ext: dict, model: RobotModel) -> np.ndarray:
    """The model's base frame in the URDF base link (mm): B of the MD-H form, identity in the xyz form."""
    bxyz, brpy = ext.get("base_xyz"), ext.get("base_rpy")
    if bxyz is None or brpy is None:
        return np.eye(4)
    return origin_matrix(np.asarray(bxyz, float) * LENGTH_TO_MM[model.length_unit],
                         np.asarray(brpy, float) * ANGLE_TO_RAD[model.angle_unit])


def _target_links(ext: dict, model: RobotModel) -> list[str]:
    links = ext.get("target_links")
    if isinstance(links, list) and len(links) == model.n_targets:
        return [str(t) for t in links]
    tl = ext.get("target_link")
    if isinstance(tl, str):
        names = [t.strip() for t in tl.split(",") if t.strip()]
        if len(names) == model.n_targets:
            return names
    raise ModelError([{"field": f"{EXTENSION}.target_links", "value": links or tl,
                       "message": f"the model has {model.n_targets} targets; its URDF extension must name as many "
                                  "target links"}])


def patch_urdf(source: str | bytes, ext: dict, nominal: RobotModel, x=None, *, calibrated: RobotModel | None = None,
               x_nominal=None, base_poses=(), setup_names=None, effects=(), base_joint=None, setup: int = 0,
               calibration_id: str | None = None, side_ref: str | None = None) -> PatchedUrdf:
    """The URDF `source` (the text `nominal` was imported from; `ext` the model's ``urdf`` extension) with the
    calibrated geometry in its joint origins, and the side document.

    `x`: the calibrated parameter vector in `nominal`'s layout (default: its nominal vector); or `calibrated`, a
    model with the same rows whose own parameters (``x`` in its layout, default its nominal vector) are the
    calibrated geometry (e.g. ``GET /calibrations/{id}/model`` parsed). `x_nominal`: the nominal vector
    (default ``nominal_vector(nominal)``). `base_poses`: per setup, the model's base frame in the measurement
    frame (4x4, mm); default from `x`'s base blocks (R0 = identity) when `x` is given. `effects`: effect states
    (JSON) for the side document. `base_joint`: None/False, True (``measurement_frame``) or the new root link's
    name. `side_ref`: where the side document is served (said in the URDF's comment)."""
    from .kinematics import base_rotation, layout, nominal_vector

    if isinstance(source, (bytes, bytearray)):
        source = bytes(source).decode("utf-8-sig")
    root_el = _read(source)
    links, joints, by_child = _parse_joints(root_el)
    cal_model = calibrated if calibrated is not None else nominal
    if x is None:
        x = nominal_vector(cal_model)
    x = np.asarray(x, float)
    x_nom = nominal_vector(nominal) if x_nominal is None else np.asarray(x_nominal, float)
    if tuple(cal_model.joint_names) != tuple(nominal.joint_names):
        raise ModelError([{"field": "joints", "value": list(cal_model.joint_names),
                           "message": "the calibrated model's rows must be the nominal model's"}])
    names = nominal.joint_names
    missing = [jn for jn in names if jn not in joints]
    if missing:
        raise UrdfError([{"field": "joint", "value": missing, "message":
                          "the model's rows are not joints of this URDF (is it the URDF the model came from?)"}])
    base_link = str(ext.get("base_link") or "")
    if base_link not in links:
        raise UrdfError([{"field": f"{EXTENSION}.base_link", "value": base_link,
                          "message": "the model's base link is not a link of this URDF"}])
    tlinks = _target_links(ext, nominal)
    bad = [t for t in tlinks if t not in links]
    if bad:
        raise UrdfError([{"field": f"{EXTENSION}.target_links", "value": bad, "message": "no such link in the URDF"}])

    # nominal link frames at q = 0 from the URDF's own origins (mm): from the root(s), then in the base link
    kids: dict[str, list] = {}
    for j in joints.values():
        kids.setdefault(j.parent, []).append(j)
    T_root: dict[str, np.ndarray] = {}
    for r in [ln for ln in links if ln not in by_child]:
        T_root[r] = np.eye(4)
        stack = [r]
        while stack:
            ln = stack.pop()
            for j in kids.get(ln, []):
                if j.child not in T_root:
                    T_root[j.child] = T_root[ln] @ origin_matrix(j.xyz * 1000.0, j.rpy)
                    stack.append(j.child)
    to_base = _inv(T_root[base_link])
    L = {ln: to_base @ T for ln, T in T_root.items()}

    # which row carries each link: below the base link only
    row_of = {jn: i for i, jn in enumerate(names)}
    carrier: dict[str, int | None] = {base_link: None}
    stack = [base_link]
    while stack:
        ln = stack.pop()
        for j in kids.get(ln, []):
            carrier[j.child] = row_of.get(j.name, carrier[ln])
            stack.append(j.child)
    off_base = [jn for jn in names if joints[jn].child not in carrier]
    if off_base:
        raise UrdfError([{"field": "joint", "value": off_base,
                          "message": f"these rows' joints are not below the base link {base_link!r}"}])

    B = _base_matrix(ext, nominal)
    Binv = _inv(B)
    G_nom, _, _ = row_frames(nominal, x_nom)
    G_cal, F_cal, tools = row_frames(cal_model, x)
    # the nominal model must be the URDF's: every movable row's joint line where the URDF has it
    for i, jn in enumerate(names):
        j = joints[jn]
        if j.type not in MOVABLE:
            continue
        M = _inv(B @ G_nom[i]) @ L[j.child]  # the child link in the row's body frame
        z = M[:3, :3] @ j.axis
        off_axis = 0.0 if j.type == "prismatic" else float(np.abs(M[:2, 3]).max())
        if not (np.abs(z - [0.0, 0.0, 1.0]).max() <= 1e-9 and off_axis <= CONSISTENT_MM):
            raise UrdfError([{"field": f"joint[@name={jn!r}]", "value": {"axis": z.tolist(), "off_axis_mm": off_axis},
                              "message": "the nominal model's joint axis is not this URDF joint's: the URDF is not "
                                         "the one the model was imported from"}])
    D = [B @ G_cal[i] @ _inv(G_nom[i]) @ Binv for i in range(len(names))]

    def moved(ln: str) -> np.ndarray:
        r = carrier.get(ln)
        return L[ln] if r is None else D[r] @ L[ln]

    b = source.encode("utf-8")
    nl = b"\r\n" if b"\r\n" in b else b"\n"  # the file's own line ends in what is inserted
    places = _places(source, b)
    edits: list[tuple[int, int, bytes]] = []
    changed: list[str] = []
    for j in joints.values():
        if j.child not in carrier or carrier.get(j.parent, None) == carrier[j.child]:
            continue
        rp, rc = carrier.get(j.parent), carrier[j.child]
        Dp = np.eye(4) if rp is None else D[rp]
        Dc = np.eye(4) if rc is None else D[rc]
        O = origin_matrix(j.xyz * 1000.0, j.rpy)
        Lc = L[j.child]
        O_new = O @ _inv(Lc) @ _inv(Dp) @ Dc @ Lc
        values = {}
        if np.abs(O_new[:3, 3] - O[:3, 3]).max() > SAME_M * 1000.0:
            values["xyz"] = _vec(O_new[:3, 3] / 1000.0)
        if np.abs(O_new[:3, :3] - O[:3, :3]).max() > SAME_M:
            values["rpy"] = _vec(matrix_rpy(O_new))
        if not values:
            continue
        changed.append(j.name)
        if j.name in places.origin:
            edits.append(_set_attrs(b, places.origin[j.name], values))
        else:  # no <origin> (identity): one after the joint's start tag
            _, end = places.joint[j.name]
            ind = places.child_indent.get(j.name) or places.indent * 2
            values.setdefault("xyz", "0 0 0")
            values.setdefault("rpy", "0 0 0")
            edits.append((end + 1, end + 1, nl + ind + f'<origin xyz="{values["xyz"]}" rpy="{values["rpy"]}"/>'
                          .encode()))

    # couplings: the model's (never identified here, but a calibrated model document may differ) against the URDF
    js_cal = _joint_to_urdf(cal_model)
    mimic_out = []
    nom_c = {row: (terms, off) for row, terms, off in nominal.coupling}
    for row, terms, off in cal_model.coupling:
        jn = names[row]
        entry: dict[str, Any] = {"joint": jn}
        if len(terms) == 1:
            src, c = terms[0]
            entry.update({"source": names[src], "multiplier": float(c * js_cal[src] / js_cal[row]),
                          "offset": float(off / js_cal[row])})
        else:
            entry["terms"] = {names[s]: float(c * js_cal[s] / js_cal[row]) for s, c in terms}
            entry["offset"] = float(off / js_cal[row])
        n_terms, n_off = nom_c.get(row, ((), 0.0))
        same = (len(n_terms) == len(terms) and all(s1 == s2 and abs(c1 - c2) <= 1e-12 for (s1, c1), (s2, c2)
                                                   in zip(n_terms, terms)) and abs(n_off - off) <= 1e-12)
        entry["changed"] = not same
        j = joints[jn]
        if not same and len(terms) == 1 and j.mimic == names[terms[0][0]] and jn in places.mimic:
            edits.append(_set_attrs(b, places.mimic[jn], {"multiplier": _f(entry["multiplier"]),
                                                          "offset": _f(entry["offset"])}))
            entry["where"] = "urdf"
        else:
            entry["where"] = "urdf (unchanged)" if same else "side file only (a URDF mimic cannot say it)"
        mimic_out.append(entry)

    # targets in their calibrated links (m)
    targets = []
    for k, (tn, r, link) in enumerate(zip(nominal.target_names, nominal.target_rows, tlinks)):
        p = B @ F_cal[int(r)] @ np.r_[tools[k], 1.0]
        v = (_inv(moved(link)) @ p)[:3] / 1000.0
        targets.append({"name": tn, "link": link, "xyz": [float(c) + 0.0 for c in v]})

    # base poses: the URDF base link in the measurement frame (m)
    if base_poses is None or len(base_poses) == 0:
        base_poses = []
        if x is not None and calibrated is None:
            lay = layout(nominal, x)
            for s in range(lay.n_setups):
                bb = x[lay.base(s)]
                P = np.eye(4)
                P[:3, :3], P[:3, 3] = base_rotation(bb, np.eye(3)), bb[:3]
                base_poses.append(P)
    poses = []
    snames = list(setup_names) if setup_names is not None else [""] * len(base_poses)
    for s, P in enumerate(base_poses):
        Pu = np.asarray(P, float) @ Binv  # the URDF base link in the measurement frame
        poses.append({"setup": snames[s] if s < len(snames) else "", "child": base_link,
                      "xyz": [float(v / 1000.0) + 0.0 for v in Pu[:3, 3]],
                      "rpy": [float(v) + 0.0 for v in matrix_rpy(Pu)],
                      "rotation_matrix": Pu[:3, :3].tolist()})

    # the optional base joint and the comment, after <robot ...>
    root_links = [ln for ln in links if ln not in by_child]
    bj = None
    if base_joint:
        bname = DEFAULT_BASE_LINK if base_joint is True else str(base_joint)
        jname = f"{bname}_joint"
        if not poses:
            raise ModelError([{"field": "base_joint", "value": bname,
                               "message": "the calibration has no identified base pose"}])
        if not 0 <= setup < len(poses):
            raise ModelError([{"field": "setup", "value": setup, "message": f"there are {len(poses)} setups"}])
        if bname in links or jname in joints:
            raise UrdfError([{"field": "base_joint", "value": bname, "message":
                              f"the URDF already has a link {bname!r} or a joint {jname!r}; name the base link "
                              "differently"}])
        if len(root_links) != 1:
            raise UrdfError([{"field": "base_joint", "value": root_links,
                              "message": "the URDF needs one root link to hang the measurement frame on"}])
        root = root_links[0]
        Pu = np.asarray(base_poses[setup], float) @ Binv  # URDF base link in the measurement frame, mm
        T = Pu @ L[root]  # the root link in the measurement frame (at q = 0 of any joint between)
        between, ln = [], base_link
        while ln != root:
            j = by_child[ln]
            if j.type != "fixed":
                between.append(j.name)
            ln = j.parent
        bj = {"link": bname, "joint": jname, "parent_of": root, "setup": poses[setup]["setup"],
              "xyz": [float(v / 1000.0) + 0.0 for v in T[:3, 3]], "rpy": [float(v) + 0.0 for v in matrix_rpy(T)]}
        if between:
            bj["valid_with_zero"] = between
    what = (f"calibrated by calib{f' (calibration {calibration_id})' if calibration_id else ''}: only the origins "
            f"of the joints {', '.join(changed) if changed else '(none)'} differ from the original file (lengths "
            "m, angles rad; joint offsets absorbed in them, axes unchanged in their child links). Not in this "
            "URDF: the measured target point(s) in their links, the identified base pose(s) in the measurement "
            "frame, identified effects" + (f" ({', '.join(sorted({str(e.get('kind')) for e in effects}))})"
                                           if effects else "")
            + f"; see the side file {side_ref or SIDE_FILE}")
    if bj:
        what += (f". Link {bj['link']} is the measurement (tracker) frame of setup {bj['setup'] or 1}, fixed "
                 f"to {bj['parent_of']} by joint {bj['joint']}")
    ind = places.indent
    add = nl + ind + _comment(what).encode()
    if bj:
        ind2 = ind * 2 if ind else b"  "
        add += (nl + ind + f"<link name={_quote(bj['link'])}/>".encode()
                + nl + ind + f"<joint name={_quote(bj['joint'])} type=\"fixed\">".encode()
                + nl + ind2 + f"<parent link={_quote(bj['link'])}/>".encode()
                + nl + ind2 + f"<child link={_quote(bj['parent_of'])}/>".encode()
                + nl + ind2 + f'<origin xyz="{_vec(bj["xyz"])}" rpy="{_vec(bj["rpy"])}"/>'.encode()
                + nl + ind + b"</joint>")
    edits.append((places.robot_end + 1, places.robot_end + 1, add))

    out = bytearray()
    pos = 0
    for s0, e0, new in sorted(edits, key=lambda e: (e[0], e[1])):
        out += b[pos:s0] + new
        pos = e0
    out += b[pos:]
    text = out.decode("utf-8")

    side = {
        "format": FORMAT,
        "robot": root_el.get("name"),
        "calibration_id": calibration_id,
        "units": {"length": "m", "angle": "rad"},
        "base_link": base_link,
        "method": "every link moved rigidly with the model row that carries it (D = G_calibrated G_nominal^-1 "
                  "at q = 0); only joint origins changed, axes unchanged in their child links",
        "changed_joints": changed,
        "targets": targets,
        "base_poses": poses,
        "base_joint": bj,
        "joint_offsets": "absorbed in the joint origins (a URDF joint has no zero offset; <calibration> unused)",
        "mimic": mimic_out,
        "effects": [_named_effect(nominal, e) for e in effects],
        "effects_note": "identified effects a URDF cannot hold: the calibration's predict and compensate include "
                        "them, a controller using this URDF alone does not",
    }
    return PatchedUrdf(text, side, changed)


def _joint_to_urdf(model: RobotModel) -> np.ndarray:
    """Per row, internal joint units per URDF unit (mm per m for prismatic rows, 1 for revolute)."""
    return np.where(model.prismatic, 1000.0, 1.0)


def _named_effect(model: RobotModel, e: dict) -> dict:
    out = dict(e)
    if isinstance(out.get("joints"), (list, tuple)):
        out["joints"] = [model.joint_names[j] if isinstance(j, (int, np.integer)) and 0 <= j < model.n_joints
                         else str(j) for j in out["joints"]]
    return out


# --- entry points -----------------------------------------------------------------------------

def source_of(doc: dict | None) -> str | None:
    """The URDF text a model document was imported from (``doc["urdf"]["source"]``), or None."""
    ext = (doc or {}).get(EXTENSION)
    src = ext.get("source") if isinstance(ext, dict) else None
    return src if isinstance(src, str) and src.strip() else None


def _state_x(model: RobotModel, state: dict) -> np.ndarray:
    """The state's parameter vector in today's layout (a state saved with fewer parameters per row is widened by
    calib_core.calibrated.state_vector)."""
    from .calibrated import state_vector

    return np.asarray(state_vector(model, state), float)


def export_calibration(doc: dict, state: dict, *, source: str | None = None, base_joint=None, setup: int = 0,
                       calibration_id: str | None = None, side_ref: str | None = None) -> PatchedUrdf:
    """The patched URDF of a stored calibration: `doc` the robot's model document (with its ``urdf`` extension
    and, unless `source` is given, ``urdf.source``), `state` the calibration's state
    (:meth:`calib_core.identify.CalibratedRobot.to_state`: ``x``, ``R0``, ``effects``, ``setup_names``)."""
    from .kinematics import base_rotation, layout

    src = source if source is not None else source_of(doc)
    if src is None:
        raise ModelError([{"field": f"{EXTENSION}.source", "value": None,
                           "message": "the model has no URDF source to patch (it was not imported from a URDF)"}])
    model = parse_model({k: v for k, v in doc.items() if k != "calibration"})
    x = _state_x(model, state)
    lay = layout(model, x)
    R0 = np.asarray(state.get("R0", np.eye(3)), float)
    R0s = np.broadcast_to(R0, (lay.n_setups, 3, 3)) if R0.ndim == 2 else R0
    poses = []
    for s in range(lay.n_setups):
        bb = x[lay.base(s)]
        P = np.eye(4)
        P[:3, :3], P[:3, 3] = base_rotation(bb, R0s[s]), bb[:3]
        poses.append(P)
    names = state.get("setup_names") or [""] * lay.n_setups
    return patch_urdf(src, doc[EXTENSION], model, x, base_poses=poses, setup_names=names,
                      effects=state.get("effects") or (), base_joint=base_joint, setup=setup,
                      calibration_id=calibration_id, side_ref=side_ref)


def export_calibrated_model(cal_doc: dict, *, source: str | None = None, base_joint=None, setup: int = 0,
                            side_ref: str | None = None) -> PatchedUrdf:
    """The patched URDF from a calibrated model document alone (``GET /calibrations/{id}/model``, offline: ``calib
    export-urdf``): its rows carry the calibrated geometry, its ``calibration`` object the base pose(s) and
    effects, its ``urdf`` extension the import's choices and (unless `source` is given) the source text. The
    nominal model is the source imported again with the same choices."""
    from .urdf import parse_urdf

    ext = cal_doc.get(EXTENSION)
    if not isinstance(ext, dict):
        raise ModelError([{"field": EXTENSION, "value": None,
                           "message": "the model has no URDF extension (it was not imported from a URDF)"}])
    src = source if source is not None else source_of(cal_doc)
    if src is None:
        raise ModelError([{"field": f"{EXTENSION}.source", "value": None,
                           "message": "the model has no URDF source to patch; give the original URDF file"}])
    units = cal_doc.get("units") or {}
    targets = ext.get("target_links") or ext.get("target_link")
    nom_doc = parse_urdf(src, ext.get("base_link"), targets, length_unit=units.get("length", "m"),
                         angle_unit=units.get("angle", "rad"), form=ext.get("form", "mdh"))
    nominal = parse_model(nom_doc)
    calib = cal_doc.get("calibration") if isinstance(cal_doc.get("calibration"), dict) else {}
    cal_model = parse_model({k: v for k, v in cal_doc.items() if k != "calibration"})
    ls = LENGTH_TO_MM[cal_model.length_unit]
    poses = calib.get("base_poses") or ([calib["base_pose"]] if calib.get("base_pose") else [])
    mats = []
    for bp in poses:
        P = np.eye(4)
        P[:3, :3], P[:3, 3] = np.asarray(bp["rotation_matrix"], float), np.asarray(bp["position"], float) * ls
        mats.append(P)
    return patch_urdf(src, {**nom_doc[EXTENSION], **{k: v for k, v in ext.items() if k != "source"}}, nominal,
                      calibrated=cal_model, base_poses=mats, setup_names=[str(bp.get("setup", "")) for bp in poses],
                      effects=calib.get("effects") or (), base_joint=base_joint, setup=setup,
                      calibration_id=calib.get("id"), side_ref=side_ref)


__all__ = ["DEFAULT_BASE_LINK", "PatchedUrdf", "SIDE_FILE", "export_calibrated_model", "export_calibration",
           "patch_urdf", "row_frames", "source_of"]
