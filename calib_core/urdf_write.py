"""URDF out (contract section 5): a model, or a calibrated one, written as a URDF of its own rows.

:func:`to_urdf` writes one joint per model row (an MD-H chain: each row's ``Rx(alpha) Tx(a) Ry(gamma) Ty(b) Rz(theta)
Tz(d)`` as a joint origin with axis z, ``Ry(beta)`` as a fixed joint; any other model: each row's origin and axis
in its own link frame, :func:`general_rows`), with the link names the import kept in the model's ``"urdf"``
extension. :func:`calibrated_model_dict` is the calibrated model as contract JSON. A model imported from a URDF is
better exported as that file patched (:mod:`calib_core.urdf_patch`); this is the fallback (``?form=rows``) and the
writer for models that never were a URDF. Reading URDF is :mod:`calib_core.urdf`.
"""
from __future__ import annotations

import math
from xml.sax.saxutils import quoteattr

import numpy as np

from .frames import mdh_transform, rot_y
from .model import ANGLE_TO_RAD, LENGTH_TO_MM, MAX_LENGTH_MM, RobotModel, parse_model
from .urdf import EXTENSION, GRAVITY, matrix_rpy, origin_matrix, rpy_matrix


def general_rows(model: RobotModel, geometry: np.ndarray | None = None, tools: np.ndarray | None = None):
    """Each row of a model as a URDF joint at the given (e.g. identified) geometry and target points (default:
    the model's own): (origins (n, 4, 4) mm, each in its parent row's link frame (the base frame for a row on
    the base), axes (n, 3) unit vectors in the row's link frame, targets (T, 3) mm and centres of mass (n, 3) mm
    or None, each in its row's link frame).

    A row's link frame is the frame its xyz/rpy/axis describe (the URDF child link frame of a model imported
    from URDF): its joint frame (z along the axis) turned back by the row's axis alignment; rows given as MD-H
    have none (link frame = joint frame, axis z). The identified MD-H constants of a row (a, alpha, d, theta,
    beta, acting in its joint frame) end up in its own origin and, for beta, in its children's origins and its
    targets, so the joints move about the same lines as in the calibrated model."""
    n = model.n_joints
    g = model.geometry if geometry is None else np.asarray(geometry, float).reshape(n, -1)
    tl = model.target_points if tools is None else np.asarray(tools, float).reshape(-1, 3)
    A = np.broadcast_to(np.eye(3), (n, 3, 3)) if model.align is None else model.align
    H = np.zeros((n, 4, 4))
    H[:, :3, :3], H[:, 3, 3] = A, 1.0
    par = model.parents
    # row j's full frame is F_par @ pre_j @ Rx(alpha) Tx(a) Ry(gamma) Ty(b) Rz(theta + q) Tz(d) Ry(beta)
    # (calib_core.kinematics);
    # its link frame is that frame before Ry(beta), turned back by the axis alignment: L_j = F_j Ry(-beta) H_j^T
    origins = np.empty((n, 4, 4))
    for j in range(n):
        a, alpha, d, theta, _, gamma, b = g[j]  # beta acts after the joint: in the children's origins and targets
        pre = np.eye(4) if model.pre is None else model.pre[j]
        before = H[par[j]] @ rot_y(g[par[j], 4]) if par[j] >= 0 else np.eye(4)
        origins[j] = before @ pre @ mdh_transform(a, alpha, d, theta, gamma=gamma, b=b) @ H[j].T
    back = lambda j, v: A[j] @ (rot_y(g[j, 4])[:3, :3] @ v)  # noqa: E731  F_j coordinates -> L_j coordinates
    targets = np.array([back(r, t) for r, t in zip(model.target_rows, tl)])
    coms = None if model.com is None else np.array([back(j, c) for j, c in enumerate(model.com)])
    return origins, A[:, :, 2].copy(), targets, coms


def model_dict(model: RobotModel, geometry: np.ndarray | None = None, tools: np.ndarray | None = None) -> dict:
    """:meth:`RobotModel.to_dict` at the given geometry and target points, with a model given as xyz/rpy/axis
    rows written in its own link frames and axes (:func:`general_rows`), not in its joint frames."""
    doc = model.to_dict(geometry, tools)
    if model.pre is None:
        return doc
    origins, axes, targets, coms = general_rows(model, geometry, tools)
    ls, an = LENGTH_TO_MM[model.length_unit], ANGLE_TO_RAD[model.angle_unit]
    for j, row in enumerate(doc["joints"]):
        row["xyz"] = [float(v / ls) + 0.0 for v in origins[j, :3, 3]]
        row["rpy"] = [float(v / an) + 0.0 for v in matrix_rpy(origins[j])]
        if model.is_fixed[j]:
            row.pop("axis", None)
        else:
            row["axis"] = [float(v) + 0.0 for v in axes[j]]
        if coms is not None:
            row["com"] = [float(v / ls) + 0.0 for v in coms[j]]
    for t, v in zip(doc["targets"], targets):
        t["xyz"] = [float(c / ls) + 0.0 for c in v]
    return doc


def calibrated_model_dict(model: RobotModel, state: dict, source: dict | None = None) -> dict:
    """The calibrated model as contract JSON: the model with the identified geometry and target points (rows
    written the way the model was given: MD-H, or xyz/rpy/axis in its own link frames), the URDF extension of
    the source model document (if any) kept, and a ``"calibration"`` object listing the identified effects
    (which the model rows cannot hold) and the identified base pose (model units, in the measurement frame; one
    per setup in ``base_poses`` when there are several). `state`: a CalibratedRobot state (``to_state()``) or
    the robot itself."""
    if not isinstance(state, dict):
        state = state.to_state()
    from .calibrated import state_vector
    from .kinematics import base_rotation, layout

    n = model.n_joints
    x = state_vector(model, state)
    lay = layout(model, x)
    doc = model_dict(model, x[lay.geometry].reshape(n, -1), x[lay.tools].reshape(-1, 3))
    if source and isinstance(source.get(EXTENSION), dict):
        doc[EXTENSION] = source[EXTENSION]
    ls = LENGTH_TO_MM[model.length_unit]
    R0 = np.asarray(state.get("R0", np.eye(3)), float)
    R0s = np.broadcast_to(R0, (lay.n_setups, 3, 3)) if R0.ndim == 2 else R0
    frame = ("the robot's base frame (the MD-H base, or the base link of xyz/rpy rows) in the measurement frame")
    poses = []
    for k in range(lay.n_setups):
        b = x[lay.base(k)]
        poses.append({"position": [float(v / ls) for v in b[:3]],
                      "rotation_matrix": base_rotation(b, R0s[k]).tolist(), "frame": frame})
    doc["calibration"] = {
        "base_pose": poses[0],
        "effects": [{"kind": e.get("kind"), "joints": [_joint_name(model, j) for j in e.get("joints", [])]}
                    for e in state.get("effects", [])],
    }
    if len(poses) > 1:
        doc["calibration"]["base_poses"] = poses
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


class _Writer:
    """The lines of a URDF being written, with unique link and joint names."""

    def __init__(self, robot: str, reserved_joints=()):
        self.lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(str(robot))}>"]
        self.links: set[str] = set()
        self.joints: set[str] = set(reserved_joints)

    @staticmethod
    def _uniq(s: str, used: set) -> str:
        out, k = s, 2
        while out in used:
            out, k = f"{s}_{k}", k + 1
        used.add(out)
        return out

    def link_name(self, s: str) -> str:
        return self._uniq(s, self.links)

    def joint_name(self, s: str) -> str:
        return self._uniq(s, self.joints)

    def comment(self, text: str) -> None:
        self.lines.append(_comment(text))

    def link(self, name_: str, mass=None, com=None) -> None:
        """A link; `com` in m."""
        if mass is None:
            self.lines.append(f"  <link name={quoteattr(name_)}/>")
            return
        self.lines.extend([f"  <link name={quoteattr(name_)}>", "    <inertial>",
                           f'      <origin xyz="{_vec(com)}" rpy="0 0 0"/>', f'      <mass value="{_f(mass)}"/>',
                           '      <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>', "    </inertial>",
                           "  </link>"])

    def joint(self, name_: str, jtype: str, parent: str, child: str, T: np.ndarray, *tags: str | None,
              axis=(0.0, 0.0, 1.0)) -> None:
        """A joint; `T` the origin with its translation in mm."""
        self.lines.append(f"  <joint name={quoteattr(name_)} type={quoteattr(jtype)}>")
        self.lines.append(f"    <parent link={quoteattr(parent)}/>")
        self.lines.append(f"    <child link={quoteattr(child)}/>")
        self.lines.append(f'    <origin xyz="{_vec(T[:3, 3] / 1000.0)}" rpy="{_vec(matrix_rpy(T))}"/>')
        if jtype != "fixed":
            self.lines.append(f'    <axis xyz="{_vec(axis)}"/>')
        self.lines.extend(f"    {t}" for t in tags if t)
        self.lines.append("  </joint>")

    def text(self) -> str:
        return "\n".join(self.lines + ["</robot>"]) + "\n"


def _calibration_comments(w: _Writer, m: RobotModel, calib: dict | None) -> None:
    effects = (calib or {}).get("effects") or []
    if effects:
        w.comment("identified effects this URDF cannot hold (the calibration's predict and compensate "
                  "include them): " + "; ".join(
                      f"{e.get('kind')}" + (f" on {', '.join(map(str, e.get('joints') or []))}"
                                            if e.get("joints") else "") for e in effects))
    poses = (calib or {}).get("base_poses") or ([calib["base_pose"]] if (calib or {}).get("base_pose") else [])
    for k, bp in enumerate(poses):
        which = f" of setup {k + 1}" if len(poses) > 1 else ""
        w.comment(f"identified base pose{which} in the measurement frame ({m.length_unit}): position "
                  f"{_vec(bp['position'])}, rotation matrix rows {bp['rotation_matrix']}")


def _limit_tag(m: RobotModel, j: int, info: dict, continuous: bool) -> tuple[str, str | None]:
    """(URDF joint type, <limit> tag) of a movable row."""
    lo, hi = (float(v) for v in m.limits[j])
    eff = f' effort="{_f(info.get("effort", 0.0))}" velocity="{_f(info.get("velocity", 0.0))}"'
    if m.prismatic[j]:
        if not (math.isfinite(lo) and math.isfinite(hi)):  # a coupled prismatic row may have none
            lo, hi = -MAX_LENGTH_MM, MAX_LENGTH_MM
        return "prismatic", f'<limit lower="{_f(lo / 1000.0)}" upper="{_f(hi / 1000.0)}"{eff}/>'
    if continuous or not (math.isfinite(lo) and math.isfinite(hi)):
        return "continuous", (f"<limit{eff}/>" if info else None)
    return "revolute", f'<limit lower="{_f(lo)}" upper="{_f(hi)}"{eff}/>'


def _inputs(model):
    """(RobotModel, geometry, target points (T, 3) mm, URDF extension, calibration object) of what to_urdf takes."""
    ext: dict = {}
    calib: dict | None = None
    if isinstance(model, dict):
        ext = model.get(EXTENSION) if isinstance(model.get(EXTENSION), dict) else {}
        calib = model.get("calibration") if isinstance(model.get("calibration"), dict) else None
        m = parse_model(model)
        return m, m.geometry, m.target_points, ext, calib
    if isinstance(model, RobotModel):
        return model, model.geometry, model.target_points, ext, calib
    if hasattr(model, "model") and hasattr(model, "x"):
        from .kinematics import layout

        m = model.model
        x = np.asarray(model.x, float)
        lay = layout(m, x)
        calib = {"effects": [{"kind": e.kind, "joints": [_joint_name(m, j) for j in e.joints]}
                             for e in getattr(model, "effects", ())]}
        return m, x[lay.geometry].reshape(m.n_joints, -1), x[lay.tools].reshape(-1, 3), ext, calib
    raise TypeError("to_urdf takes a model dict, a RobotModel or a calibrated robot")


def to_urdf(model, name: str | None = None) -> str:
    """A URDF of a model: a contract model dict (any convention and units; its ``"urdf"`` extension and
    ``"calibration"`` object are used when present), a :class:`RobotModel`, or a calibrated robot (an object
    with ``model`` and ``x``, e.g. :class:`calib_core.identify.CalibratedRobot`).

    A serial chain of MD-H rows: each row becomes a joint whose origin is ``Rx(alpha) Tx(a) Rz(theta) Tz(d)``
    with axis ``0 0 1``; a row with ``beta`` adds a fixed joint ``<joint>_beta`` (``Ry(beta)``), and the tool
    point a fixed joint to the target link. The links between are the MD-H joint frames (``<joint>_link``).

    Any other model (xyz/rpy/axis rows, trees, fixed or coupled rows, several targets): one joint per row
    (fixed rows as ``fixed`` joints, coupled rows with ``<mimic>``) whose origin and axis are the row's at the
    model's geometry (:func:`general_rows`), between the rows' link frames (named as in the ``urdf`` extension,
    else ``<joint>_link``); each target is a link at its point (the row's own link when the target is at its
    origin, or folded into a fixed row's origin).

    Links carry the model's masses and centres of mass as inertials (no inertia tensor: the model has none).
    Effects a URDF cannot hold are listed in a comment."""
    m, geometry, tools, ext, calib = _inputs(model)
    rname = name or ext.get("robot") or m.name
    if m.pre is None and m.fixed is None and not m.coupling and m.is_serial:
        return _mdh_urdf(m, geometry, tools[0], ext, calib, rname)
    return _general_urdf(m, geometry, tools, ext, calib, rname)


def _general_urdf(m: RobotModel, geometry, tools, ext: dict, calib: dict | None, rname: str) -> str:
    origins, axes, tpts, coms = general_rows(m, geometry, tools)
    origins, coms = origins.copy(), None if coms is None else coms.copy()
    base_link = str(ext.get("base_link") or "base_link")
    ext_links = ext.get("links") if isinstance(ext.get("links"), dict) else {}
    continuous = set(ext.get("continuous") or ())
    extra = ext.get("limits") if isinstance(ext.get("limits"), dict) else {}
    par = m.parents
    rows_with_kids = set(int(p) for p in par if p >= 0)
    tnames, trows = m.target_names, [int(r) for r in m.target_rows]
    want = [str(ext_links.get(jn) or f"{jn}_link") for jn in m.joint_names]

    # each target: the row's own link (at its origin), folded into a fixed row's origin, or a link of its own
    own: list[int] = []
    for k, (t, r) in enumerate(zip(tnames, trows)):
        v = tpts[k]
        if want[r] != t:
            own.append(k)
        elif np.abs(v).max() <= 1e-9:
            pass
        elif m.is_fixed[r] and r not in rows_with_kids and trows.count(r) == 1:
            origins[r] = origins[r] @ origin_matrix(v, (0.0, 0.0, 0.0))
            if coms is not None:
                coms[r] = coms[r] - v
        else:
            own.append(k)
            want[r] = f"{t}_parent"
    w = _Writer(rname, m.joint_names)
    w.comment(f"written by calib from the contract model {m.name!r}: one joint per model row (fixed rows fixed, "
              "coupled rows with mimic), its origin the row's geometry in the link frame of the row it follows, "
              "its axis the row's; each target is a link at its point; lengths m, angles rad")
    _calibration_comments(w, m, calib)
    if not np.allclose(m.gravity, GRAVITY, rtol=0.0, atol=1e-12):
        w.comment(f"gravity in the base link (m/s^2): {_vec(m.gravity)} (a URDF has no gravity)")
    w.links.add(base_link)
    target_link = {k: w.link_name(tnames[k]) for k in own}  # target names first: rows give way
    link_of = [w.link_name(s) for s in want]
    js = np.where(m.prismatic, 1000.0, 1.0)  # internal -> URDF joint units
    couple = {row: (terms, off) for row, terms, off in m.coupling}
    w.link(base_link)
    for j, jn in enumerate(m.joint_names):
        mimic = None
        if j in couple:
            terms, off = couple[j]
            if len(terms) == 1:
                src, c = terms[0]
                mimic = (f"<mimic joint={quoteattr(m.joint_names[src])} multiplier=\"{_f(c * js[src] / js[j])}\" "
                         f"offset=\"{_f(off / js[j])}\"/>")
            else:
                w.comment(f"joint {jn} = " + " + ".join(f"{c * js[s] / js[j]:.12g} * {m.joint_names[s]}"
                                                         for s, c in terms)
                          + f" + {off / js[j]:.12g} (m, rad): a URDF mimic follows one joint, so it is written "
                            "as an independent joint")
        w.link(link_of[j], m.mass[j] if m.mass is not None else None,
               coms[j] / 1000.0 if coms is not None else None)
        parent = base_link if par[j] < 0 else link_of[par[j]]
        if m.is_fixed[j]:
            w.joint(jn, "fixed", parent, link_of[j], origins[j])
            continue
        info = extra.get(jn) if isinstance(extra.get(jn), dict) else {}
        jtype, limit = _limit_tag(m, j, info, jn in continuous)
        w.joint(jn, jtype, parent, link_of[j], origins[j], limit, mimic, axis=axes[j])
    for k in own:
        r = trows[k]
        w.link(target_link[k])
        w.joint(w.joint_name(f"{target_link[k]}_target"), "fixed", link_of[r], target_link[k],
                origin_matrix(tpts[k], (0.0, 0.0, 0.0)))
    return w.text()


def _mdh_urdf(m: RobotModel, geometry, tool, ext: dict, calib: dict | None, rname: str) -> str:
    au = ANGLE_TO_RAD[m.angle_unit]
    ls = LENGTH_TO_MM[m.length_unit]
    base_link = str(ext.get("base_link") or "base_link")
    target_link = str(ext.get("target_link") or "tool")
    continuous = set(ext.get("continuous") or ())
    extra = ext.get("limits") if isinstance(ext.get("limits"), dict) else {}

    w = _Writer(rname, m.joint_names)
    w.comment(f"written by calib from the contract model {m.name!r}: each MD-H row "
              "(Rx(alpha) Tx(a) Rz(theta) Tz(d) Ry(beta)) is a joint origin with axis 0 0 1; the links "
              "between are the MD-H joint frames; lengths m, angles rad")
    _calibration_comments(w, m, calib)
    w.links.add(base_link)
    w.link(base_link)
    parent = base_link
    bxyz, brpy = ext.get("base_xyz"), ext.get("base_rpy")
    if bxyz is not None and brpy is not None and (any(bxyz) or any(brpy)):
        B = origin_matrix(np.asarray(bxyz, float) * ls, np.asarray(brpy, float) * au)
        child = w.link_name("mdh_base")
        w.link(child)
        w.joint(w.joint_name(f"{base_link}_to_mdh_base"), "fixed", parent, child, B)
        parent = child
    has_mass = m.mass is not None
    for j, jn in enumerate(m.joint_names):
        a, alpha, d, theta, beta, gamma, b = (float(v) for v in geometry[j])
        T = mdh_transform(a, alpha, d, theta, gamma=gamma, b=b)  # Ry(beta) follows as a fixed joint of its own
        info = extra.get(jn) if isinstance(extra.get(jn), dict) else {}
        jtype, limit = _limit_tag(m, j, info, jn in continuous)
        child = w.link_name(f"{jn}_link")
        if beta != 0.0:
            w.link(child)
        else:
            w.link(child, m.mass[j] if has_mass else None, m.com[j] / 1000.0 if has_mass else None)
        w.joint(jn, jtype, parent, child, T, limit)
        parent = child
        if beta != 0.0:
            child = w.link_name(f"{jn}_frame")
            w.link(child, m.mass[j] if has_mass else None, m.com[j] / 1000.0 if has_mass else None)
            w.joint(w.joint_name(f"{jn}_beta"), "fixed", parent, child, rot_y(beta))
            parent = child
    trpy = ext.get("tool_rpy")
    Tt = rpy_matrix(*(np.asarray(trpy, float) * au)) if trpy is not None else np.eye(4)
    Tt[:3, 3] = tool
    tlink = w.link_name(target_link) if target_link not in w.links else w.link_name(f"{target_link}_tool")
    w.link(tlink)
    w.joint(w.joint_name(f"{tlink}_fixed"), "fixed", parent, tlink, Tt)
    return w.text()


__all__ = ["calibrated_model_dict", "general_rows", "model_dict", "to_urdf"]
