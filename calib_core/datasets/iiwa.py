"""KUKA iiwa 7 with an optical tracker: standard DH with masses, payload runs, optional 6-D rows and torques."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from ._common import (IIWA_DIR, IIWA_JOINTS, IIWA_RUNS, SHARED_DATASETS, _UNITS, Dataset, _csv_text, _data_limits,
                      _dh_joint, _folder, _read_columns, quaternion_wxyz)


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
        from ..model import parse_model

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
