"""DLR Agile Justin: the older serial torso + one arm, and the whole robot as one tree (coupled torso, two arms)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from ._common import SHARED_DATASETS, Dataset, _csv_text, _data_limits, _folder, _read_columns, _xyz_rpy


# --- DLR Agile Justin ---------------------------------------------------------------------

JUSTIN_DIR = "dlr_agile_justin"
JUSTIN_TORSO = ("T1", "T2", "T3", "T4c")
"""Torso pan, tilt 1, tilt 2 and the passive coupled joint T4c = -T2 - T3 (computed, not measured)."""
JUSTIN_ARMS = {"right": tuple(f"R{i}" for i in range(1, 8)), "left": tuple(f"L{i}" for i in range(1, 8))}
JUSTIN_Q = {"right": range(3, 10), "left": range(10, 17)}
"""Columns q3..q9 (right arm) and q10..q16 (left arm) of measurements_flat.csv."""
JUSTIN_MARKER_M = {"right": (-0.1, -0.03, 0.1), "left": (-0.1, 0.03, 0.05)}
"""Marker in each arm's TCP frame (m), the dataset site's initial guesses."""
JUSTIN_SIGMA_MM = 0.2
"""Per-axis 1-sigma of a Vicon marker position: Merriaux et al., "A Study of Vicon System Positioning
Performance", Sensors 17(7):1591 (2017) measured a static mean absolute error of 0.15 mm (variability
< 0.025 mm), i.e. ~0.1 mm per axis for a 3-D Gaussian; doubled for Justin's larger volume (markers
2-4 m from the Vicon origin, six cameras) and a marker on a hand that has just stopped."""
JUSTIN_LIMIT_PAD_DEG = 5.0


def justin_available(root: Path | str = SHARED_DATASETS) -> bool:
    """True when the DLR Agile Justin dataset (model YAML and flat CSV) is present under ``root``."""
    folder = Path(root) / JUSTIN_DIR
    return (folder / "justin19_nominal.yaml").is_file() and (folder / "measurements_flat.csv").is_file()


def _rokin_dh(d: float, theta: float, a: float, alpha: float) -> np.ndarray:
    """rokin's dh2frame (Craig / modified DH) at q = 0: Rx(alpha) Tx(a) Rz(theta) Tz(d)."""
    from ..frames import rot_x, rot_z, trans

    return rot_x(alpha) @ trans(a) @ rot_z(theta) @ trans(z=d)


def agile_justin_links(arm: str = "right", root: Path | str = SHARED_DATASETS):
    """The rokin chain of one arm as :class:`calib_core.frames.Link` s (m, rad) and the marker in the last frame.

    F_TORSO_BASE, DH_TORSO(q0, q1, q2, -q1-q2), F_<ARM>_BASE, DH_<ARM>(7 joints), F_TCP, marker.
    Every link's Rz(q) sits after its own Tz(d) (they commute), so each DH row at q = 0 is the
    fixed part. The published F_<ARM>_BASE rotations are rounded (0.866 for cos 30 deg): they
    are replaced by the nearest rotation (changes entries by < 3e-5)."""
    from ..frames import Link, nearest_rotation

    if arm not in JUSTIN_ARMS:
        raise ValueError(f"arm must be 'right' or 'left', not {arm!r}")
    folder = _folder(root, JUSTIN_DIR)
    y = yaml.safe_load((folder / "justin19_nominal.yaml").read_text())
    lim_deg = y["joint_limits_deg"]
    torso_lim = [np.radians(v) for v in lim_deg["torso"]] + [None]
    links = []
    for k, (row, name) in enumerate(zip(y["DH_TORSO"], JUSTIN_TORSO)):
        T = _rokin_dh(*row)
        if k == 0:
            T = np.array(y["F_TORSO_BASE"], float) @ T
        lim = None if torso_lim[k] is None else (float(torso_lim[k][0]), float(torso_lim[k][1]))
        links.append(Link(T, "revolute", name, lim))
    arm_base = nearest_rotation(y[f"F_{arm.upper()}_BASE"])
    for k, (row, name) in enumerate(zip(y[f"DH_{arm.upper()}"], JUSTIN_ARMS[arm])):
        T = _rokin_dh(*row)
        if k == 0:
            T = arm_base @ T
        lo, hi = np.radians(lim_deg["arm"][k])
        links.append(Link(T, "revolute", name, (float(lo), float(hi))))
    links.append(Link(np.array(y["F_TCP"], float), "fixed", "TCP"))
    return links, np.array(JUSTIN_MARKER_M[arm], float)


def agile_justin(arm: str = "right", root: Path | str = SHARED_DATASETS) -> Dataset:
    """DLR Agile Justin, torso + one 7-DoF arm, 500 Vicon marker positions (dlr-alr/dlr-elastic-calibration).

    Source files: ``dlr_agile_justin/justin19_nominal.yaml`` (rokin's modified-DH tables and static
    frames, m/rad) and ``measurements_flat.csv`` (19 commanded joint angles in rad; right and left
    hand marker in the Vicon frame, m). The chain F_TORSO_BASE, the torso rows (q0 pan, q1 tilt 1,
    q2 tilt 2, passive q3c = -q1 - q2), F_<ARM>_BASE, the 7 arm rows, F_TCP and the marker
    (right [-0.1, -0.03, 0.1], left [-0.1, 0.03, 0.05] m in the TCP frame) is folded exactly
    into contract MD-H rows by :mod:`calib_core.frames` (Hayati beta where axes are parallel:
    the three torso tilt axes are). The model is in m and rad (``units`` says so), CSV likewise.

    * The passive coupled joint has no column in the data: it is written as the extra joint
      column ``T4c`` = -T2 - T3. The contract cannot yet express coupling (issue 11 will), so a
      calibration treats T4c as an independent measured joint; its limits are the data range
      padded by 5 deg.
    * The vendor pan limit (+-120 deg) rejects rows the robot really reached (-130 .. 199 deg):
      every limit the data exceed is widened to the data range padded by 5 deg.
    * ``sigma`` = 0.2 mm per axis (Vicon, not a laser tracker; see ``JUSTIN_SIGMA_MM``): without
      it the service would assume a laser tracker (15 um + 6 um/m).
    * Gravity is -z of the robot base (the Vicon frame is z up and T_c0 only turns about z),
      rotated into the folded base frame (here the identity: the pan axis is the base z).
    * No masses or COMs are published for this model: none are written. Joint values are
      commanded, and the arm is visibly elastic (the paper's 21 mm before calibration).
    """
    from ..frames import fold_links

    links, marker = agile_justin_links(arm, root)
    folder = _folder(root, JUSTIN_DIR)
    cols = _read_columns(folder / "measurements_flat.csv")
    torso = np.column_stack([cols["q0"], cols["q1"], cols["q2"], -cols["q1"] - cols["q2"]])
    arm_q = np.column_stack([cols[f"q{i}"] for i in JUSTIN_Q[arm]])
    q = np.hstack([torso, arm_q])
    names = JUSTIN_TORSO + JUSTIN_ARMS[arm]

    pad = math.radians(JUSTIN_LIMIT_PAD_DEG)
    limits, widened = [], []
    for j, link in enumerate(lk for lk in links if lk.type != "fixed"):
        lo_d, hi_d = float(q[:, j].min()), float(q[:, j].max())
        if link.limits is None:
            lim = (lo_d - pad, hi_d + pad)
        elif lo_d < link.limits[0] or hi_d > link.limits[1]:
            lim = (min(link.limits[0], lo_d - pad), max(link.limits[1], hi_d + pad))
            widened.append(f"{names[j]} [{math.degrees(link.limits[0]):g}, {math.degrees(link.limits[1]):g}] -> "
                           f"[{math.degrees(lim[0]):.1f}, {math.degrees(lim[1]):.1f}] deg")
        else:
            lim = link.limits
        limits.append((math.floor(lim[0] * 1e9) / 1e9, math.ceil(lim[1] * 1e9) / 1e9))  # outward, 9 decimals

    folded = fold_links(links, marker, gravity=(0.0, 0.0, -9.81))
    model = folded.model_dict(f"dlr_agile_justin_{arm}", length_unit="m", angle_unit="rad", limits=limits)
    xyz = np.column_stack([cols[f"{arm}_{c}"] for c in "xyz"])
    points = [str(int(i)) for i in cols["idx"]]
    sigma = np.full(len(points), JUSTIN_SIGMA_MM / 1000.0)
    csv_text = _csv_text(points, names, q, xyz, {"sigma": (sigma, "{:g}")}, q_fmt="{:.12g}", xyz_fmt="{:.10g}")
    notes = (f"DLR Agile Justin {arm} arm + torso, dlr-alr/dlr-elastic-calibration measurements.csv "
             f"(commit 35149b7, 500 poses, commanded joints rad, Vicon hand marker m) with rokin justin19 "
             f"nominal modified DH; chain torso + F_{arm.upper()}_BASE + 7 arm joints + F_TCP + marker "
             f"{list(JUSTIN_MARKER_M[arm])} m folded exactly to MD-H (frames.py; Hayati form d = 0 / beta "
             f"at the parallel torso tilt axes); "
             f"units m/rad; passive coupled torso joint written as extra column T4c = -T2 - T3 (coupling not "
             f"expressible in the contract yet, issue 11; T4c limits = data range +-5 deg); "
             f"vendor limits widened to the data: {'; '.join(widened) or 'none'}; "
             f"sigma {JUSTIN_SIGMA_MM} mm per axis (Vicon; Merriaux et al. 2017 static 0.15 mm mean error, doubled "
             f"for a larger volume) instead of the laser-tracker default; gravity -z of the robot base; "
             f"no masses; F_{arm.upper()}_BASE rotation (rounded 0.866) replaced by the nearest rotation; "
             f"licence none stated")
    return Dataset(f"agile_justin_{arm}", model, csv_text, notes)


# --- DLR Agile Justin as one robot (contract section 5: tree, coupled joint, two targets) --------------------

JUSTIN_FIXED = {"torso": "torso_base", "right": ("R_base", "R_tcp"), "left": ("L_base", "L_tcp")}
"""Names of the fixed rows: F_TORSO_BASE, and per arm F_<ARM>_BASE (on the torso's last row) and F_TCP."""
JUSTIN_TORSO_MASS = ((5.0, (0.0, 0.0, 0.0)), (8.0, (0.15, 0.0, 0.0)), (8.0, (0.15, 0.0, 0.0)),
                     (15.0, (0.15, 0.05, 0.0)))
"""GUESSED lumped masses (kg) and centres of mass (m, in each torso row's MD-H frame) of the torso bodies moved by
T1, T2, T3 and T4c (T4c: upper torso and head), from benchmarks/justin_reference.py. Not published by DLR."""
JUSTIN_ARM_LINK_KG = 2.0
"""GUESSED mass of each arm link (kg), its centre of mass in the middle of the link's d segment."""
JUSTIN_HAND_KG = 2.0
"""GUESSED mass of each hand (kg), at the TCP frame's origin."""
JUSTIN_VENDOR_LIMITS_NOTE = ("vendor limits (deg): torso [-120, 120], [-90, 90], [0, 135]; arm [-170, 170], "
                             "[-120, 120], [-170, 170], [-120, 120], [-170, 170], [-45.1, 80], [-45, 135]")


def agile_justin_tree(root: Path | str = SHARED_DATASETS, *, limits: str = "data", masses: bool = True) -> Dataset:
    """DLR Agile Justin as ONE robot: torso, both 7-DoF arms as branches, one Vicon marker per hand.

    Source files: ``dlr_agile_justin/justin19_nominal.yaml`` (rokin's modified-DH tables ``[d, theta, a, alpha]``,
    the static frames, m/rad) and ``measurements_flat.csv`` (19 commanded joint angles, rad; right and left hand
    marker in the Vicon frame, m). Contract section 5 model (``"mdh"``, m/rad), nothing folded by hand:

    * ``torso_base``: fixed row, ``xyz``/``rpy`` = F_TORSO_BASE; then T1 (pan), T2, T3 (tilts) as MD-H rows
      (rokin's ``Rx(alpha) Tx(a) Rz(theta + q) Tz(d)`` is the contract's MD-H row as it stands).
    * T4c: the passive torso joint, ``"coupled": {"T2": -1, "T3": -1}`` (q = -q1 - q2): no CSV column.
    * Per arm: ``R_base`` / ``L_base`` fixed rows with ``"parent": "T4c"`` and ``xyz``/``rpy`` = F_<ARM>_BASE
      (its rotation, published rounded to 0.866 = cos 30 deg, replaced by the nearest rotation), the 7 arm rows
      (MD-H), then ``R_tcp`` / ``L_tcp`` fixed rows = F_TCP.
    * ``targets``: ``right`` on ``R_tcp`` at [-0.1, -0.03, 0.1] m, ``left`` on ``L_tcp`` at [-0.1, 0.03, 0.05] m
      (the dataset site's initial guesses, in the TCP frame).
    * CSV: two rows per recorded pose (points ``<idx>-right`` and ``<idx>-left``, ``target`` column), joints
      T1..T3, R1..R7, L1..L7 (rad), ``x,y,z`` (m, Vicon frame), ``sigma`` 0.0002 m (0.2 mm per axis, see
      ``JUSTIN_SIGMA_MM``). Head joints (q17, q18) are 0 throughout and not modelled.

    Limits (``limits=``):
      ``"data"`` (default): the vendor limits, widened to the data range padded by 5 deg where the robot really
      went beyond them (only the torso pan T1: the data reach -130.4 .. 199 deg against the vendor's +-120), so
      the CSV uploads with the default ``?limits=reject`` and nothing is rejected. The notes list what was widened.
      ``"vendor"``: the vendor limits as published; T1 of 178 of the 500 poses (356 of the 1000 rows) lies outside
      them, so upload that CSV with ``POST /robots/{id}/measurements?limits=warn`` (``calib demo --limits
      warn``), which accepts the rows and reports the extent (the default ``?limits=reject`` refuses the file).

    Masses (``masses=True``): GUESSES, not published by DLR (benchmarks/justin_reference.py): torso 5 / 8 / 8 /
    15 kg (T1 / T2 / T3 / T4c, the last with the head), 2 kg per arm link at the middle of its d segment, 2 kg per
    hand at the TCP; mount rows 0 kg. Gravity -z of the robot base (the Vicon frame is z up; T_c0 turns about z).
    Joint values are commanded; the robot is visibly elastic (21 mm before calibration in the paper).
    """
    if limits not in ("data", "vendor"):
        raise ValueError(f"limits must be 'data' or 'vendor', not {limits!r}")
    from ..frames import nearest_rotation

    folder = _folder(root, JUSTIN_DIR)
    y = yaml.safe_load((folder / "justin19_nominal.yaml").read_text())
    cols = _read_columns(folder / "measurements_flat.csv")
    lim_deg = y["joint_limits_deg"]
    pad = math.radians(JUSTIN_LIMIT_PAD_DEG)
    widened: list[str] = []

    def mdh(name: str, row, q: np.ndarray | None, vendor_deg) -> dict:
        d, theta, a, alpha = (float(v) for v in row)
        out = {"name": name, "type": "revolute", "a": a, "alpha": alpha, "d": d, "theta": theta, "beta": 0.0}
        if vendor_deg is not None:
            vendor = (math.radians(vendor_deg[0]), math.radians(vendor_deg[1]))
            out["limits"] = (_data_limits(name, vendor, float(q.min()), float(q.max()), pad, "deg",
                                          180.0 / math.pi, widened)
                             if limits == "data" else [vendor[0], vendor[1]])
        return out

    def fixed(name: str, T, parent: str | None = None) -> dict:
        xyz, rpy = _xyz_rpy(np.asarray(T, float))
        out = {"name": name, "type": "fixed", "xyz": xyz, "rpy": rpy}
        if parent is not None:
            out["parent"] = parent
        return out

    q_torso = [cols["q0"], cols["q1"], cols["q2"]]
    rows = [fixed(JUSTIN_FIXED["torso"], y["F_TORSO_BASE"])]
    for k, name in enumerate(JUSTIN_TORSO[:3]):
        rows.append(mdh(name, y["DH_TORSO"][k], q_torso[k], lim_deg["torso"][k]))
    t4 = mdh(JUSTIN_TORSO[3], y["DH_TORSO"][3], None, None)
    t4["coupled"] = {JUSTIN_TORSO[1]: -1.0, JUSTIN_TORSO[2]: -1.0, "offset": 0.0}
    rows.append(t4)
    masses_of = {JUSTIN_FIXED["torso"]: (0.0, (0.0, 0.0, 0.0))}
    masses_of.update({n: m for n, m in zip(JUSTIN_TORSO, JUSTIN_TORSO_MASS)})
    for arm in ("right", "left"):
        base_name, tcp_name = JUSTIN_FIXED[arm]
        rows.append(fixed(base_name, nearest_rotation(y[f"F_{arm.upper()}_BASE"]), parent=JUSTIN_TORSO[3]))
        masses_of[base_name] = (0.0, (0.0, 0.0, 0.0))
        for k, (name, i) in enumerate(zip(JUSTIN_ARMS[arm], JUSTIN_Q[arm])):
            row = y[f"DH_{arm.upper()}"][k]
            rows.append(mdh(name, row, cols[f"q{i}"], lim_deg["arm"][k]))
            masses_of[name] = (JUSTIN_ARM_LINK_KG, (0.0, 0.0, -0.5 * float(row[0])))
        rows.append(fixed(tcp_name, y["F_TCP"]))
        masses_of[tcp_name] = (JUSTIN_HAND_KG, (0.0, 0.0, 0.0))
    if masses:
        for r in rows:
            m, com = masses_of[r["name"]]
            r["mass"], r["com"] = m, [float(c) + 0.0 for c in com]
    targets = [{"name": arm, "parent": JUSTIN_FIXED[arm][1], "xyz": list(JUSTIN_MARKER_M[arm])}
               for arm in ("right", "left")]
    model = {"name": "dlr_agile_justin", "convention": "mdh", "units": {"length": "m", "angle": "rad"},
             "joints": rows, "targets": targets, "gravity": [0.0, 0.0, -9.81]}

    names = JUSTIN_TORSO[:3] + JUSTIN_ARMS["right"] + JUSTIN_ARMS["left"]
    q = np.column_stack([cols[f"q{i}"] for i in range(17)])
    idx = [str(int(i)) for i in cols["idx"]]
    n = len(idx)
    q2 = np.repeat(q, 2, axis=0)
    xyz = np.empty((2 * n, 3))
    xyz[0::2] = np.column_stack([cols[f"right_{c}"] for c in "xyz"])
    xyz[1::2] = np.column_stack([cols[f"left_{c}"] for c in "xyz"])
    points = [f"{i}-{arm}" for i in idx for arm in ("right", "left")]
    target = np.array(["right", "left"] * n, dtype=object)
    sigma = np.full(2 * n, JUSTIN_SIGMA_MM / 1000.0)
    csv_text = _csv_text(points, names, q2, xyz, {"target": (target, "{}"), "sigma": (sigma, "{:g}")},
                         q_fmt="{:.12g}", xyz_fmt="{:.10g}")
    lim_note = (f"limits widened to the data (+-{JUSTIN_LIMIT_PAD_DEG:g} deg): {'; '.join(widened) or 'none'}"
                if limits == "data" else
                "vendor limits kept: upload with ?limits=warn (calib demo --limits warn), T1 goes to 199 deg")
    notes = ("DLR Agile Justin as one robot (torso T1-T3 + passive T4c coupled = -T2 - T3, right and left arm as "
             "branches on T4c), dlr-alr/dlr-elastic-calibration measurements.csv (commit 35149b7, 500 poses x 2 "
             "markers = 1000 rows with a target column; commanded joints rad; Vicon m) with rokin justin19 nominal "
             "modified DH as MD-H rows; F_TORSO_BASE, F_<ARM>_BASE (nearest rotation to the rounded 0.866) and F_TCP "
             "as fixed xyz/rpy rows; markers right [-0.1, -0.03, 0.1], left [-0.1, 0.03, 0.05] m in the TCP "
             f"frames (site's initial guesses); units m/rad; {lim_note}; {JUSTIN_VENDOR_LIMITS_NOTE}; "
             f"sigma {JUSTIN_SIGMA_MM} mm per axis (Vicon); gravity -z of the robot base; "
             + ("masses GUESSED (torso 5/8/8/15 kg, 2 kg per arm link, 2 kg per hand; not published)"
                if masses else "no masses") + "; licence none stated")
    return Dataset("dlr_agile_justin", model, csv_text, notes)
