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
              xyz_mm: np.ndarray, extra: dict[str, tuple[np.ndarray, str]] | None = None) -> str:
    """Contract CSV: ``point,<joints>,x,y,z[,extra...]``; joints 8 decimals (deg), mm 6 decimals."""
    extra = extra or {}
    q_deg = np.round(q_deg, 8) + 0.0  # +0.0 turns -0.0 into 0.0 so no "-0.00000000" cells
    xyz_mm = np.round(xyz_mm, 6) + 0.0
    out = io.StringIO()
    out.write(",".join(["point", *joint_names, "x", "y", "z", *extra]) + "\n")
    for i, pid in enumerate(points):
        cells = [pid]
        cells += [f"{v:.8f}" for v in q_deg[i]]
        cells += [f"{v:.6f}" for v in xyz_mm[i]]
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
