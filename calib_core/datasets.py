"""Readers that turn third-party *real* calibration datasets into our contract formats.

The raw files live outside the repository (licences unclear, see each NOTES.md
under ``SHARED_DATASETS``); nothing here copies them. Each reader returns a
:class:`Dataset` holding

* ``model``: the robot model JSON dict of contract section 1 (standard DH,
  ``"convention": "dh"``, millimetres and degrees), and
* ``csv_text``: the measurement CSV of contract section 2 (joints in degrees,
  ``x,y,z`` and ``sigma`` in millimetres, ``payload`` in kg).

Both are exactly what a user would ``POST``, so they exercise the service on
measured data instead of simulation. Only numpy, pyyaml and the stdlib are used.
"""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

SHARED_DATASETS: Path = Path(
    os.environ.get(
        "CALIB_SHARED_DATASETS",
        Path(__file__).resolve().parents[1].parent / "shared" / "datasets",
    )
)
"""Folder with the third-party datasets: ``<repo>/../shared/datasets`` unless
the environment variable ``CALIB_SHARED_DATASETS`` says otherwise."""

MOTOMAN_DIR = "motoman_leica"
IIWA_DIR = "iiwa7_payload"
MOTOMAN_JOINTS = ("E", "S1", "L1", "U1", "R1", "B1", "T1")
IIWA_JOINTS = ("A1", "A2", "A3", "A4", "A5", "A6", "A7")
#: payload (kg) -> file of the 2016-12-16 payload series (198 rows each).
IIWA_RUNS = {
    0.0: "20161216_run1_0kg.csv",
    1.25: "20161216_run2_1.25kg.csv",
    2.5: "20161216_run3_2.5kg.csv",
    5.0: "20161216_run4_5kg.csv",
}
_UNITS = {"length": "mm", "angle": "deg"}


@dataclass(frozen=True)
class Dataset:
    """One real dataset in contract form.

    ``model``: contract section 1 dict (``"dh"``, mm/deg). ``csv_text``: contract
    section 2 CSV in the model's units. ``notes``: one line on source, units and
    what was converted.
    """

    name: str
    model: dict
    csv_text: str
    notes: str


def available(root: Path | str = SHARED_DATASETS) -> bool:
    """True when both the Motoman and the iiwa dataset folders are present under ``root``."""
    root = Path(root)
    return (root / MOTOMAN_DIR / "leica_right_arm_586.csv").is_file() and (
        root / IIWA_DIR / IIWA_RUNS[0.0]
    ).is_file()


def _folder(root: Path | str, sub: str) -> Path:
    folder = Path(root) / sub
    if not folder.is_dir():
        raise FileNotFoundError(
            f"dataset folder {folder} not found; put the shared datasets there "
            f"or set CALIB_SHARED_DATASETS to the folder that contains {sub}/"
        )
    return folder


def _read_columns(path: Path) -> dict[str, np.ndarray]:
    """Read a numeric CSV with one header line (spaces after commas allowed) into name -> float array."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh, skipinitialspace=True))
    header = [h.strip() for h in rows[0]]
    data = np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=float)
    return {h: data[:, i] for i, h in enumerate(header)}


def _deg(rad: float) -> float:
    return round(math.degrees(rad), 9)


def _dh_joint(name: str, a_m: float, d_m: float, alpha_rad: float, theta_rad: float,
              limits_deg: list[float]) -> dict:
    """One revolute standard-DH joint row of the model JSON (m/rad in, mm/deg out)."""
    return {"name": name, "type": "revolute", "a": round(a_m * 1000.0, 9),
            "alpha": _deg(alpha_rad), "d": round(d_m * 1000.0, 9), "theta": _deg(theta_rad),
            "limits": limits_deg}


def _csv_text(points: list[str], joint_names: tuple[str, ...], q_deg: np.ndarray,
              xyz_mm: np.ndarray, extra: dict[str, tuple[np.ndarray, str]] | None = None,
              q_fmt: str = "{:.8f}", xyz_fmt: str = "{:.6f}") -> str:
    """Contract CSV: ``point,<joints>,x,y,z[,extra...]``; joints 8 decimals (deg), mm 6 decimals
    unless ``q_fmt`` / ``xyz_fmt`` say otherwise (fixed-point formats are rounded first)."""
    extra = extra or {}
    if q_fmt.endswith("f}"):
        q_deg = np.round(q_deg, int(q_fmt[3:-2]))
    if xyz_fmt.endswith("f}"):
        xyz_mm = np.round(xyz_mm, int(xyz_fmt[3:-2]))
    q_deg = q_deg + 0.0  # +0.0 turns -0.0 into 0.0 so no "-0.00000000" cells
    xyz_mm = xyz_mm + 0.0
    out = io.StringIO()
    out.write(",".join(["point", *joint_names, "x", "y", "z", *extra]) + "\n")
    for i, pid in enumerate(points):
        cells = [pid]
        cells += [q_fmt.format(v) for v in q_deg[i]]
        cells += [xyz_fmt.format(v) for v in xyz_mm[i]]
        cells += [fmt.format(col[i]) for col, fmt in extra.values()]
        out.write(",".join(cells) + "\n")
    return out.getvalue()


def motoman_leica(root: Path | str = SHARED_DATASETS) -> Dataset:
    """Yaskawa Motoman MA1400 right arm (CTU Prague), 586 Leica laser-tracker points.

    Source files: ``motoman_leica/leica_right_arm_586.csv`` (joints rad, SMR xyz and
    tracker uncertainty in m) and ``motoman_nominal_dh.yaml`` (standard DH rows
    [a, d, alpha, offset] in m/rad). The joint vector is [E, S1, L1, U1, R1, B1, T1].
    The 8th DH row (reflector link LR1, q = 0) is fixed, so it is folded into the
    tool point: the reflector is the origin of frame 8, and in the T1 frame that is
    Rz(off8) Tz(d8) Tx(a8) @ 0 = [a8 cos(off8), a8 sin(off8), d8] (alpha8 does
    not move the origin). ``sigma`` = ``leica_unc`` in mm. No masses are published;
    gravity [0, 0, -9.81] is an assumption (base z up).
    """
    folder = _folder(root, MOTOMAN_DIR)
    dh = yaml.safe_load((folder / "motoman_nominal_dh.yaml").read_text())["rightArm"]
    cols = _read_columns(folder / "leica_right_arm_586.csv")

    joints = [_dh_joint(n, a, d, al, off, [-180.0, 180.0])
              for n, (a, d, al, off) in zip(MOTOMAN_JOINTS, dh[:7])]
    a8, d8, _alpha8, off8 = dh[7]
    tool = [round(1000.0 * a8 * math.cos(off8), 9), round(1000.0 * a8 * math.sin(off8), 9),
            round(1000.0 * d8, 9)]
    model = {"name": "motoman_ma1400_right_leica", "convention": "dh", "units": dict(_UNITS),
             "joints": joints, "tool": tool, "gravity": [0.0, 0.0, -9.81]}

    q_deg = np.degrees(np.column_stack([cols[n] for n in MOTOMAN_JOINTS]))
    xyz_mm = 1000.0 * np.column_stack([cols["leica_x"], cols["leica_y"], cols["leica_z"]])
    sigma_mm = 1000.0 * cols["leica_unc"]
    points = [str(int(p)) for p in cols["pose_id"]]
    notes = ("CTU Prague ctu-vras/multirobot-calibration updated_leica_dataset.mat (Aug 2019), "
             "586 poses of the right arm, Leica SMR in tracker frame; converted m->mm, rad->deg, "
             "leica_unc->sigma mm, reflector DH row LR1 (initial guess) folded into tool; "
             "point = pose_id; no masses; gravity assumed [0,0,-9.81]; licence of data not stated")
    return Dataset("motoman_leica", model, _csv_text(points, MOTOMAN_JOINTS, q_deg, xyz_mm,
                                                      {"sigma": (sigma_mm, "{:.6f}")}), notes)


def _iiwa_model(folder: Path) -> dict:
    """KUKA LBR iiwa 7 R800 nominal standard-DH model in mm/deg with link masses and COMs."""
    y = yaml.safe_load((folder / "iiwa7_nominal_dh.yaml").read_text())
    joints = []
    for name, j, lim, m, com in zip(IIWA_JOINTS, y["joints"], y["joint_limits_rad"],
                                    y["mass"], y["com"]):
        row = _dh_joint(name, j["a"], j["d"], j["alpha"], j["offset"],
                        [round(math.degrees(v), 6) for v in lim])
        # COM is given in the RTB (standard-DH) frame i of the link moved by joint i.
        row["mass"] = float(m)
        row["com"] = [round(1000.0 * c, 9) for c in com]
        joints.append(row)
    return {"name": "kuka_iiwa7_r800", "convention": "dh", "units": dict(_UNITS),
            "joints": joints, "tool": [0.0, 0.0, 0.0], "gravity": [0.0, 0.0, -9.81]}


def iiwa7_payload(payload_kg: float | None = 0.0, root: Path | str = SHARED_DATASETS) -> Dataset:
    """KUKA LBR iiwa 7 R800 optical-tracker data (Zhangzhongqiu/new-calibration, 2016-12-16).

    ``payload_kg`` selects one 198-row run (0, 1.25, 2.5 or 5 kg); ``None`` gives
    all four runs (792 rows). The measured point is the translation column
    (m_03, m_13, m_23) of the marker pose, already in mm in the camera frame;
    joints rad -> deg. The marker -> flange offset is unknown, so ``tool`` is
    [0, 0, 0] (the flange centre) and is left for the calibration to identify.
    Every row is kept, including the repeated pairs of the 5 kg run; ``point`` is
    ``run<k>-<row number>`` so the ids stay unique when runs are combined.
    """
    folder = _folder(root, IIWA_DIR)
    if payload_kg is None:
        runs = list(IIWA_RUNS)
    else:
        runs = [p for p in IIWA_RUNS if abs(p - float(payload_kg)) < 1e-9]
        if not runs:
            raise ValueError(f"no iiwa7 run with payload {payload_kg} kg; "
                             f"available: {sorted(IIWA_RUNS)} or None for all")
    points, q, xyz, payload = [], [], [], []
    for p in runs:
        run_no = list(IIWA_RUNS).index(p) + 1
        cols = _read_columns(folder / IIWA_RUNS[p])
        points += [f"run{run_no}-{int(n):03d}" for n in cols["number"]]
        q.append(np.degrees(np.column_stack([cols[f"theta_{i}"] for i in range(1, 8)])))
        xyz.append(np.column_stack([cols["m_03"], cols["m_13"], cols["m_23"]]))
        payload.append(np.full(len(cols["number"]), p))
    which = "all four payload runs" if payload_kg is None else f"payload {runs[0]:g} kg run"
    notes = (f"Zhangzhongqiu/new-calibration 20161216 iiwa7 {which} (optical tracker, camera frame, "
             "marker translation already mm); converted rad->deg, DH m->mm, COM m->mm; "
             "tool [0,0,0] = flange, marker offset unknown; only A1/A2 move in these runs; "
             "5 kg rows are repeated pairs; licence none stated")
    name = "iiwa7_payload" if payload_kg is None else f"iiwa7_payload_{runs[0]:g}kg"
    csv_text = _csv_text(points, IIWA_JOINTS, np.vstack(q), np.vstack(xyz),
                         {"payload": (np.concatenate(payload), "{:g}")})
    return Dataset(name, _iiwa_model(folder), csv_text, notes)


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
    from .frames import rot_x, rot_z, trans

    return rot_x(alpha) @ trans(a) @ rot_z(theta) @ trans(z=d)


def agile_justin_links(arm: str = "right", root: Path | str = SHARED_DATASETS):
    """The rokin chain of one arm as :class:`calib_core.frames.Link` s (m, rad) and the marker in the last frame.

    F_TORSO_BASE, DH_TORSO(q0, q1, q2, -q1-q2), F_<ARM>_BASE, DH_<ARM>(7 joints), F_TCP, marker.
    Every link's Rz(q) sits after its own Tz(d) (they commute), so each DH row at q = 0 is the
    fixed part. The published F_<ARM>_BASE rotations are rounded (0.866 for cos 30 deg): they
    are replaced by the nearest rotation (changes entries by < 3e-5)."""
    from .frames import Link, nearest_rotation

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
    from .frames import fold_links

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
