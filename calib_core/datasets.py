"""Readers that turn third-party *real* calibration datasets into our contract formats.

The raw files live outside the repository (licences unclear or non-commercial, see each NOTES.md under
``SHARED_DATASETS``); nothing here copies them. Each reader returns a :class:`Dataset` holding

* ``model``: the robot model JSON dict of the contract (sections 1 and 5), and
* ``csv_text``: the measurement CSV of the contract (sections 2 and 5), in the model's units,

exactly what a user would ``POST`` (``calib convert-dataset NAME OUTDIR`` writes them), so they exercise the
service on measured data instead of simulation. Only numpy, pyyaml and the stdlib are used.

=====================  ==============================================================================
reader                 what it writes
=====================  ==============================================================================
motoman_leica          Motoman MA1400 right arm, standard DH mm/deg, 586 Leica points, ``sigma``
iiwa7_payload          KUKA iiwa 7, standard DH mm/deg with masses, 4 payload runs (``payload``); optional
                       6-D rows (``qw,qx,qy,qz``) and measured torques (``tau_A1..tau_A7``)
iiwa7_run              the iiwa's other runs (exp1, exp2, 20161118: every joint moves), 6-D rows + torques
agile_justin_tree      DLR Agile Justin as ONE robot: torso with the coupled passive joint, two arms as
                       branches (``parent``), mount frames as ``fixed`` xyz/rpy rows, two ``targets``
hilti_trailblazer      Hilti lifting column + Doosan arm from its URDF (fixed, xyz/rpy/axis, mimic as
                       ``coupled`` rows), 7 recordings as ``setup`` s, ``timestamp``, ``temperature``
agile_justin           (older) torso + one arm folded into a serial MD-H chain, coupled joint as a column
=====================  ==============================================================================

Joint limits: where the robot really went beyond the published limits, a reader widens them to the data (padded)
and says so in ``notes`` rather than have the default upload (``?limits=reject``) refuse rows.
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
    instrument: str | None = None  # the noise model to upload with when the CSV has no sigma column


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


def _iiwa_model(folder: Path, q_deg: np.ndarray | None = None, widened: list[str] | None = None) -> dict:
    """KUKA LBR iiwa 7 R800 nominal standard-DH model in mm/deg with link masses and COMs. With the data's
    joints `q_deg`, a limit the data go beyond is widened to the data + 2 deg (listed in `widened`): the author's
    model says +-170 deg for A7, which really turns +-175 deg (KUKA datasheet) and reaches 173 deg in exp1."""
    y = yaml.safe_load((folder / "iiwa7_nominal_dh.yaml").read_text())
    joints = []
    for k, (name, j, lim, m, com) in enumerate(zip(IIWA_JOINTS, y["joints"], y["joint_limits_rad"],
                                                    y["mass"], y["com"])):
        lim_deg = [round(math.degrees(v), 6) for v in lim]
        if q_deg is not None:
            lim_deg = _data_limits(name, tuple(lim_deg), float(q_deg[:, k].min()), float(q_deg[:, k].max()), 2.0,
                                   "deg", 1.0, widened if widened is not None else [])
        row = _dh_joint(name, j["a"], j["d"], j["alpha"], j["offset"], lim_deg)
        # COM is given in the RTB (standard-DH) frame i of the link moved by joint i.
        row["mass"] = float(m)
        row["com"] = [round(1000.0 * c, 9) for c in com]
        joints.append(row)
    return {"name": "kuka_iiwa7_r800", "convention": "dh", "units": dict(_UNITS),
            "joints": joints, "tool": [0.0, 0.0, 0.0], "gravity": [0.0, 0.0, -9.81]}


IIWA_OTHER_RUNS = {"20161118": "20161118_run_1.csv", "exp1": "exp1_data1402.csv", "exp2": "exp2_data2636.csv"}
"""The runs without a stated payload (probably none): an early run (304 rows) and the author's exp1 / exp2 (1402 /
2636 rows); unlike the payload runs, every joint moves in them."""


IIWA_TAU_SIGN = -1.0
"""tau_<joint> = IIWA_TAU_SIGN x the file's tau_i (see iiwa7_payload)."""


def _iiwa_run(folder: Path, file: str, tag: str, orientation: bool, torques: bool):
    """One iiwa run: point ids, joints deg, marker position mm, extra columns (quaternion, torques)."""
    cols = _read_columns(folder / file)
    n = len(cols["theta_1"])
    numbers = cols["number"].astype(int) if "number" in cols else np.arange(n)
    points = [f"{tag}-{int(k):03d}" for k in numbers]
    q = np.degrees(np.column_stack([cols[f"theta_{i}"] for i in range(1, 8)]))
    xyz = np.column_stack([cols["m_03"], cols["m_13"], cols["m_23"]])
    extra = {}
    if orientation:
        R = np.stack([np.column_stack([cols[f"m_{r}{c}"] for c in range(3)]) for r in range(3)], axis=1)
        quat = quaternion_wxyz(R)
        extra.update({c: quat[:, k] for k, c in enumerate(("qw", "qx", "qy", "qz"))})
    if torques:
        # the sensors report the gravity torque acting on the joint; the contract's tau is what the joint applies
        extra.update({f"tau_{name}": IIWA_TAU_SIGN * cols[f"tau_{i}"] + 0.0
                      for i, name in enumerate(IIWA_JOINTS, start=1)})
    return points, q, xyz, extra


_IIWA_EXTRA_FMT = {"qw": "{:.12f}", "qx": "{:.12f}", "qy": "{:.12f}", "qz": "{:.12f}"}


def iiwa7_payload(payload_kg: float | None = 0.0, root: Path | str = SHARED_DATASETS, *,
                  orientation: bool = False, torques: bool = False, marker_per_run: bool = True) -> Dataset:
    """KUKA LBR iiwa 7 R800 optical-tracker data (Zhangzhongqiu/new-calibration, 2016-12-16).

    ``payload_kg`` selects one 198-row run (0, 1.25, 2.5 or 5 kg); ``None`` gives
    all four runs (792 rows). The measured point is the translation column
    (m_03, m_13, m_23) of the marker pose, already in mm in the camera frame;
    joints rad -> deg. The marker -> flange offset is unknown, so ``tool`` is
    [0, 0, 0] (the flange centre) and is left for the calibration to identify.
    Every row is kept, including the repeated pairs of the 5 kg run; ``point`` is
    ``run<k>-<row number>`` so the ids stay unique when runs are combined.
    Only A1 and A2 move in these runs (A3..A7 stay within 0.1 deg of 0).

    Contract section 5 columns (``calib convert-dataset iiwa7_payload`` writes both):

    * ``orientation=True``: ``qw,qx,qy,qz``, the rotation of the tracker's 4x4 marker pose (m_00..m_22) as a
      unit quaternion (w >= 0): the orientation of the marker body in the camera frame, every row a 6-D row.
      The marker body's rotation relative to the flange frame is unknown (like its offset): a constant a 6-D
      calibration must identify along with the base.
    * ``torques=True``: ``tau_A1..tau_A7``, the iiwa's joint torque sensors (N*m), so load-driven causes use
      the measured load instead of the model's statics. SIGN FLIPPED (``IIWA_TAU_SIGN``): calib_core reads
      ``tau_<joint>`` as the torque the joint applies to hold the arm (dV/dq, the opposite of the gravity load
      of calib_core.statics), while the iiwa's sensors report the gravity torque acting on the joint: raw
      ``tau_i`` = -1.3 .. -1.45 x dV/dq of the nominal model (correlation 0.9997-1.0 on A2, A4, A6; the factor
      is the model's too light links, 15.5 kg against the real arm's ~22 kg).

    Several runs (``payload_kg=None``) with ``marker_per_run`` (default): one target per run, ``run1`` ..
    ``run4`` on A7 (a ``target`` column; the model as the exact MD-H form of the DH table, since targets need
    it). The marker body was mounted anew for each payload run: its rotation about the flange axis is 17.1,
    36.6, -0.6 and 112.8 deg in runs 1-4 (constant within a run to 0.1-0.4 deg, over 240 deg of A1 and 170 deg
    of A2) and its fitted offset along the flange axis 66.3, 63.0, 68.1, 69.0 mm. One shared marker point
    (``marker_per_run=False``, the earlier form) leaves that in the residual: held-out 2.71 mm against 1.72 mm,
    and it wrecks a 6-D fit (docs/RESULTS.md 7.1).
    """
    folder = _folder(root, IIWA_DIR)
    if payload_kg is None:
        runs = list(IIWA_RUNS)
    else:
        runs = [p for p in IIWA_RUNS if abs(p - float(payload_kg)) < 1e-9]
        if not runs:
            raise ValueError(f"no iiwa7 run with payload {payload_kg} kg; "
                             f"available: {sorted(IIWA_RUNS)} or None for all")
    points, q, xyz, payload, extra = [], [], [], [], {}
    for p in runs:
        run_no = list(IIWA_RUNS).index(p) + 1
        pts, qq, pp, ex = _iiwa_run(folder, IIWA_RUNS[p], f"run{run_no}", orientation, torques)
        points += pts
        q.append(qq)
        xyz.append(pp)
        payload.append(np.full(len(pts), p))
        for c, v in ex.items():
            extra.setdefault(c, []).append(v)
    which = "all four payload runs" if payload_kg is None else f"payload {runs[0]:g} kg run"
    per_run = marker_per_run and len(runs) > 1
    tags = [f"run{list(IIWA_RUNS).index(p) + 1}" for p in runs]
    cols = {"payload": (np.concatenate(payload), "{:g}")}
    if per_run:
        cols["target"] = (np.concatenate([np.full(len(pl), t) for pl, t in zip(payload, tags)]), "{}")
    cols.update({c: (np.concatenate(v), _IIWA_EXTRA_FMT.get(c, "{:.9g}")) for c, v in extra.items()})
    notes = (f"Zhangzhongqiu/new-calibration 20161216 iiwa7 {which} (optical tracker, camera frame, "
             "marker translation already mm); converted rad->deg, DH m->mm, COM m->mm; "
             + ("one target per run (run1..run4 on A7, [0,0,0] = flange): the marker was mounted anew for "
                "each payload run (its rotation about the flange axis 17 / 37 / -1 / 113 deg), offsets unknown; "
                "model as MD-H (targets need it); " if per_run else "tool [0,0,0] = flange, marker offset unknown; ")
             + "only A1/A2 move in these runs; "
             "5 kg rows are repeated pairs; "
             + ("qw..qz = marker rotation (m_00..m_22) as a unit quaternion, marker-to-flange rotation unknown; "
                if orientation else "")
             + ("tau_A1..tau_A7 = measured joint torques N*m, sign flipped to the torque the joint applies (the "
                "sensors report the gravity torque acting on it); " if torques else "")
             + "no sigma column: upload with ?instrument=optical (the tracker is an unnamed optical one); "
             + "licence none stated")
    name = "iiwa7_payload" if payload_kg is None else f"iiwa7_payload_{runs[0]:g}kg"
    csv_text = _csv_text(points, IIWA_JOINTS, np.vstack(q), np.vstack(xyz), cols)
    model = _iiwa_model(folder)
    if per_run:  # the exact MD-H form of the DH table (same parameters and names), one marker per run
        from .model import parse_model

        model = parse_model(model).to_dict()
        model.pop("tool", None)
        model["targets"] = [{"name": t, "parent": IIWA_JOINTS[-1], "xyz": [0.0, 0.0, 0.0]} for t in tags]
    return Dataset(name, model, csv_text, notes, instrument="optical")


def iiwa7_run(run: str, root: Path | str = SHARED_DATASETS, *, orientation: bool = True,
              torques: bool = True) -> Dataset:
    """One of the iiwa runs without a stated payload (``IIWA_OTHER_RUNS``: "20161118", "exp1", "exp2"), in which
    every joint moves: same model and columns as :func:`iiwa7_payload` but no ``payload`` column (unknown,
    probably none). exp2 holds at least one gross outlier (about 52 mm, NOTES)."""
    if run not in IIWA_OTHER_RUNS:
        raise ValueError(f"unknown iiwa7 run {run!r}; available: {list(IIWA_OTHER_RUNS)}")
    folder = _folder(root, IIWA_DIR)
    points, q, xyz, extra = _iiwa_run(folder, IIWA_OTHER_RUNS[run], run, orientation, torques)
    cols = {c: (v, _IIWA_EXTRA_FMT.get(c, "{:.9g}")) for c, v in extra.items()}
    widened: list[str] = []
    model = _iiwa_model(folder, q, widened)
    notes = (f"Zhangzhongqiu/new-calibration iiwa7 run {run} ({IIWA_OTHER_RUNS[run]}, {len(points)} rows, every joint "
             "moves; payload not stated); optical tracker, camera frame, mm; rad->deg; tool [0,0,0] = flange, "
             f"marker offset unknown; limits widened to the data: {'; '.join(widened) or 'none'}"
             + ("; qw..qz = marker rotation as a unit quaternion" if orientation else "")
             + ("; tau_A1..tau_A7 = measured joint torques N*m, sign flipped to the torque the joint applies"
                if torques else "") + "; no sigma column: upload with ?instrument=optical; licence none stated")
    return Dataset(f"iiwa7_{run}", model, _csv_text(points, IIWA_JOINTS, q, xyz, cols), notes, instrument="optical")


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


# --- contract section 5 helpers ----------------------------------------------------------------

def _xyz_rpy(T: np.ndarray, digits: int = 12) -> tuple[list[float], list[float]]:
    """A rigid 4x4 transform (m) as URDF xyz (m) and rpy (rad): Trans(xyz) Rz(y) Ry(p) Rx(r)."""
    from .urdf import matrix_rpy

    xyz = [round(float(v), digits) + 0.0 for v in T[:3, 3]]
    rpy = [round(float(v), digits) + 0.0 for v in matrix_rpy(T[:3, :3])]
    return xyz, rpy


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) [w, x, y, z] with w >= 0 of rotation matrices (N, 3, 3) (Shepperd's method:
    the largest of the four squared components is taken first, so every branch is well conditioned)."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((len(R), 4))
    for i, (Ri, ki) in enumerate(zip(R, k)):
        if ki == 0:
            s = 2.0 * math.sqrt(max(1.0 + tr[i], 0.0))
            q[i] = [0.25 * s, (Ri[2, 1] - Ri[1, 2]) / s, (Ri[0, 2] - Ri[2, 0]) / s, (Ri[1, 0] - Ri[0, 1]) / s]
        else:
            a = ki - 1
            b, c = (a + 1) % 3, (a + 2) % 3
            s = 2.0 * math.sqrt(max(1.0 + Ri[a, a] - Ri[b, b] - Ri[c, c], 0.0))
            v = np.empty(3)
            v[a] = 0.25 * s
            v[b] = (Ri[b, a] + Ri[a, b]) / s
            v[c] = (Ri[c, a] + Ri[a, c]) / s
            q[i] = [(Ri[c, b] - Ri[b, c]) / s, *v]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _data_limits(name: str, vendor: tuple[float, float] | None, lo_d: float, hi_d: float, pad: float,
                 unit: str, scale: float, widened: list[str]) -> list[float] | None:
    """The vendor limits, widened to the data range padded by `pad` where the data go beyond them (noted in
    `widened`); values in the joint's unit, rounded outward to 9 decimals. `scale` converts to the note's unit."""
    if vendor is None:
        return None
    lo, hi = vendor
    if lo_d < lo or hi_d > hi:
        new = (min(lo, lo_d - pad), max(hi, hi_d + pad))
        widened.append(f"{name} [{lo * scale:g}, {hi * scale:g}] -> [{new[0] * scale:.1f}, {new[1] * scale:.1f}] "
                       f"{unit} "
                       f"(data {lo_d * scale:.1f} .. {hi_d * scale:.1f})")
        lo, hi = new
    return [math.floor(lo * 1e9) / 1e9, math.ceil(hi * 1e9) / 1e9]


def _iso(t: np.ndarray) -> np.ndarray:
    from datetime import datetime, timezone

    return np.array([datetime.fromtimestamp(float(v), timezone.utc).isoformat(timespec="milliseconds") for v in t],
                    dtype=object)


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
    from .frames import nearest_rotation

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
