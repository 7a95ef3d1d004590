"""Hilti Trailblazer: a lifting column and a Doosan arm from its URDF, 7 recordings as setups."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from ._common import SHARED_DATASETS, Dataset, _csv_text, _data_limits, _folder, _iso


# --- Hilti Trailblazer (contract section 5: URDF-style rows, mimic column, setups) -------------------------

HILTI_DIR = "hilti_trailblazer"
HILTI_FILES = ("flat", "pallet", "orthogonal_wood", "wood_left_track", "seesaw", "diagonal_wood", "outdoor")
"""The seven recordings, one base placement each (setup), in the order of the dataset README."""
HILTI_TEMPERATURE_C = {"outdoor": 9.0}
"""Air temperature per recording (README): 21 deg C except outdoor, 9 deg C; the files have no temperature field."""
HILTI_DEFAULT_TEMPERATURE_C = 21.0
HILTI_SIGMA_MM = 0.75
"""Per-axis 1-sigma of the Hilti PLT 300 total station (datasheet, dataset README)."""
HILTI_BASE, HILTI_TARGET = "base_link", "prism"
HILTI_LIMIT_PAD_RAD = math.radians(2.0)


def hilti_available(root: Path | str = SHARED_DATASETS) -> bool:
    folder = Path(root) / HILTI_DIR
    return (folder / "trailblazer.urdf").is_file() and all((folder / f"{f}.yaml").is_file() for f in HILTI_FILES)


def _urdf_rows(text: str, base: str, target: str) -> tuple[list[dict], dict, dict]:
    """A URDF's chain from `base` to the link `target` as contract section 5 rows (m, rad): every joint on the
    way as it stands (fixed joints as fixed rows, origin as ``xyz``/``rpy``, ``axis``), mimic joints as
    ``coupled`` rows, and a mimicked joint that is not on the way (a leaf) as its own row on its parent link so
    that its CSV column exists. The fixed joint into `target` becomes the target point on its parent row.
    Each row's ``mass``/``com`` is its child link's inertial (other side branches are left out).
    Returns (rows, target {name, parent, xyz}, raw limits {row: (lo, hi)})."""
    import xml.etree.ElementTree as ET

    if "<!DOCTYPE" in text:
        raise ValueError("URDF with a DOCTYPE refused")
    root_el = ET.fromstring(text)
    num = lambda s, n=3: [float(v) for v in (s or " ".join(["0"] * n)).split()]  # noqa: E731
    inertial = {}
    for link in root_el.findall("link"):
        el = link.find("inertial")
        if el is not None:
            o = el.find("origin")
            inertial[link.get("name")] = (float(el.find("mass").get("value")),
                                          num(None if o is None else o.get("xyz")))
    joints = {}
    for j in root_el.findall("joint"):
        o, ax, lim, mim = j.find("origin"), j.find("axis"), j.find("limit"), j.find("mimic")
        joints[j.get("name")] = {
            "name": j.get("name"), "type": j.get("type"), "parent": j.find("parent").get("link"),
            "child": j.find("child").get("link"),
            "xyz": num(None if o is None else o.get("xyz")), "rpy": num(None if o is None else o.get("rpy")),
            "axis": [1.0, 0.0, 0.0] if ax is None else num(ax.get("xyz")),
            "limits": None if lim is None else (float(lim.get("lower")), float(lim.get("upper"))),
            "mimic": None if mim is None else (mim.get("joint"), float(mim.get("multiplier", 1.0)),
                                               float(mim.get("offset", 0.0)))}
    by_child = {j["child"]: j for j in joints.values()}
    path, link = [], target
    while link != base:
        if link not in by_child:
            raise ValueError(f"link {link!r} is not connected to {base!r}")
        path.append(by_child[link])
        link = by_child[link]["parent"]
    path.reverse()
    last = path.pop()  # the fixed joint into the target link: the target point
    if last["type"] != "fixed":
        raise ValueError(f"the target link {target!r} must hang on a fixed joint")
    on_path = {j["name"] for j in path}
    for j in list(path):  # a mimicked joint off the path gets a row of its own (a leaf with the CSV column)
        if j["mimic"] is not None and j["mimic"][0] not in on_path:
            src = joints[j["mimic"][0]]
            path.insert(path.index(j), src)
            on_path.add(src["name"])
    row_of_link = {base: "base"}
    rows, raw_limits = [], {}
    for k, j in enumerate(path):
        row = {"name": j["name"], "type": "fixed" if j["type"] == "fixed" else
               "prismatic" if j["type"] == "prismatic" else "revolute"}
        parent = row_of_link[j["parent"]]
        if parent != (rows[-1]["name"] if rows else "base"):
            row["parent"] = parent
        row["xyz"], row["rpy"] = j["xyz"], j["rpy"]
        if row["type"] != "fixed":
            row["axis"] = j["axis"]
            if j["limits"] is not None:
                raw_limits[j["name"]] = j["limits"]
                row["limits"] = list(j["limits"])
        if j["mimic"] is not None:
            src, mult, off = j["mimic"]
            row["coupled"] = {src: mult, "offset": off}
        m, com = inertial.get(j["child"], (0.0, [0.0, 0.0, 0.0]))
        row["mass"], row["com"] = m, com
        rows.append(row)
        row_of_link.setdefault(j["child"], j["name"])
    tgt = {"name": target, "parent": row_of_link[last["parent"]], "xyz": last["xyz"]}
    return rows, tgt, raw_limits


def _hilti_rows(path: Path) -> tuple[list[dict], list[str]]:
    """Every measurement of one recording (height, IK solution space, stationing / evaluation, the YAML fields)
    and the recording's joint names."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # the C loader when built: 5x faster on 250 kB
    doc = yaml.load(path.read_text(), Loader=loader)
    out = []
    for h, hv in doc["column_heights"].items():
        for s, sv in hv["solution_spaces"].items():
            for kind in ("stationing_measurements", "evaluation_measurements"):
                for m in sv.get(kind) or []:
                    out.append({"height": float(h), "space": int(s), "kind": kind.split("_")[0], **m})
    return out, doc["joint_names"]


def hilti_trailblazer(root: Path | str = SHARED_DATASETS, *, files: tuple[str, ...] = HILTI_FILES,
                      setup_by: str = "file") -> Dataset:
    """Hilti Trailblazer (JaiBot prototype): lifting column + Doosan M1013, a total station's prism, 7 base setups.

    Source files: ``hilti_trailblazer/trailblazer.urdf`` (CAD kinematics and inertials, m/rad/kg) and the seven
    recordings ``<name>.yaml`` (joint states m/rad, ``prism_position`` m in the total-station frame, unix time).
    Licence CC BY-NC-SA 3.0 (non-commercial, share alike): the converted files carry it too.

    Model (contract section 5, ``"mdh"`` with URDF-style rows, m/rad): the URDF chain base_link -> prism joint by
    joint (:func:`_urdf_rows`): fixed joints as ``"type": "fixed"`` rows with ``xyz``/``rpy``; the lifting column's
    actuated ``column_prismatic_joint`` (in the URDF a leaf: it only moves ``column_pseudo_tip``) as its own row
    on ``column_base``, so its CSV column exists; the telescope stages ``column_middle_joint`` and
    ``column_top_joint`` as ``coupled`` rows (URDF mimic: 0.5 q - 0.706 m and 0.5 q - 0.736 m, no CSV column);
    ``dsr_joint1..6``; ``dsr_tool_to_tool``; the target ``prism`` at the ``prism_calib`` offset (already a
    calibrated value in the URDF) in ``tool_link``. Masses and centres of mass are each row's child link
    inertial from the URDF (CAD); side branches (tracks_compartments, 0.1 kg) are left out. Gravity -z of
    base_link; the seesaw / wooden-slab setups tilt the base a little (the accelerometers show it; not modelled).
    Limits: the URDF's (the data stay within them: dsr_joint3 reaches -2.53 .. 1.59 rad of +-2.7925, the column
    1.98 .. 3.87 m of 1.48 .. 3.972); a limit the data went beyond would be widened to the data + 2 deg (1 cm) and
    listed in the notes, so the CSV uploads with the default ``?limits=reject``.

    CSV: one row per measurement (stationing and evaluation alike), ``point`` =
    ``<file>/h<height>/s<solution space>/<stationing|evaluation><id>``, the 7 joints (m, rad), ``x,y,z`` (m),
    ``setup``, ``timestamp`` (ISO 8601, UTC), ``temperature`` (21 deg C, outdoor 9; README), ``sigma`` 0.00075 m
    (0.75 mm per axis, datasheet). Not carried: the two accelerometers, ``doosan_cmd``, ``upside_down``.

    ``setup_by="file"`` (default): one base placement per recording (7 setups; the robot stands still within a
    recording). ``"station"``: one per column height x IK solution space, as the dataset's stationing does (15 per
    recording, 105 in all): it absorbs deflection the per-file base cannot and leaves far fewer poses per base.
    """
    if setup_by not in ("file", "station"):
        raise ValueError(f"setup_by must be 'file' or 'station', not {setup_by!r}")
    unknown = [f for f in files if f not in HILTI_FILES]
    if unknown:
        raise ValueError(f"unknown Hilti recordings {unknown}; available: {list(HILTI_FILES)}")
    folder = _folder(root, HILTI_DIR)
    rows, target, raw_limits = _urdf_rows((folder / "trailblazer.urdf").read_text(), HILTI_BASE, HILTI_TARGET)
    recs = []
    joint_names = None
    for f in files:
        r, jn = _hilti_rows(folder / f"{f}.yaml")
        joint_names = joint_names or jn
        if jn != joint_names:
            raise ValueError(f"{f}.yaml names its joints {jn}, not {joint_names}")
        recs += [{**m, "file": f} for m in r]
    q = np.array([m["joint_states"] for m in recs], float)
    widened: list[str] = []
    for row in rows:
        if row["name"] in joint_names and "limits" in row:
            k = joint_names.index(row["name"])
            prism = row["type"] == "prismatic"
            row["limits"] = _data_limits(row["name"], raw_limits[row["name"]], float(q[:, k].min()),
                                         float(q[:, k].max()), 0.01 if prism else HILTI_LIMIT_PAD_RAD,
                                         "m" if prism else "rad", 1.0, widened)
    model = {"name": "hilti_trailblazer", "convention": "mdh", "units": {"length": "m", "angle": "rad"},
             "joints": rows, "targets": [target], "gravity": [0.0, 0.0, -9.81]}
    xyz = np.array([m["prism_position"] for m in recs], float)
    points = [f"{m['file']}/h{m['height']:.2f}/s{m['space']}/{m['kind']}{m['id']}" for m in recs]
    if setup_by == "file":
        setup = np.array([m["file"] for m in recs], dtype=object)
    else:
        setup = np.array([f"{m['file']}/h{m['height']:.2f}/s{m['space']}" for m in recs], dtype=object)
    temp = np.array([HILTI_TEMPERATURE_C.get(m["file"], HILTI_DEFAULT_TEMPERATURE_C) for m in recs])
    extra = {"setup": (setup, "{}"), "timestamp": (_iso(np.array([m["time"] for m in recs])), "{}"),
             "temperature": (temp, "{:g}"), "sigma": (np.full(len(recs), HILTI_SIGMA_MM / 1000.0), "{:g}")}
    csv_text = _csv_text(points, tuple(joint_names), q, xyz, extra, q_fmt="{:.12g}", xyz_fmt="{:.10g}")
    notes = (f"Hilti Trailblazer (lifting column + Doosan M1013), Hilti-Research/construction_robot_stationing_"
             f"datasets f26546d, {len(recs)} measurements of {len(files)} recordings ({', '.join(files)}), "
             "total-station prism in m; model from trailblazer.urdf joint by joint (fixed rows, xyz/rpy/axis rows, "
             "telescope stages as coupled rows 0.5 q - 0.706 / 0.5 q - 0.736 m, column_prismatic_joint as its own "
             "leaf row, target prism at prism_calib in tool_link), masses/com = URDF inertials (CAD); "
             f"setup per {setup_by} ({len(dict.fromkeys(setup))} setups); temperature 21 deg C (outdoor 9, README); "
             f"sigma {HILTI_SIGMA_MM} mm per axis (PLT 300 datasheet); limits widened to the data: "
             f"{'; '.join(widened) or 'none'}; accelerometers, doosan_cmd and upside_down not carried; "
             "units m/rad; LICENCE CC BY-NC-SA 3.0 (non-commercial, share alike)")
    return Dataset("hilti_trailblazer", model, csv_text, notes)
