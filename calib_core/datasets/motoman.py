"""Motoman MA1400 right arm measured by a Leica laser tracker: standard DH mm/deg, 586 points, `sigma`."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from ._common import (MOTOMAN_DIR, MOTOMAN_JOINTS, SHARED_DATASETS, _UNITS, Dataset, _csv_text, _dh_joint, _folder,
                      _read_columns)


def motoman_leica(root: Path | str = SHARED_DATASETS) -> Dataset:
    """Yaskawa Motoman MA1400 right arm (CTU Prague), 586 Leica laser-tracker points.

    Source files: ``motoman_leica/leica_right_arm_586.csv`` (joints rad, SMR xyz and
    tracker uncertainty in m) and ``motoman_nominal_dh.yaml`` (standard DH rows
    [a, d, alpha, offset] in m/rad). The joint vector is [E, S1, L1, U1, R1, B1, T1].
    The 8th DH row (reflector link LR1, q = 0) is fixed, so it is folded into the
    tool point: the reflector is the origin of frame 8, and in the T1 frame that is
    Rz(off8) Tz(d8) Tx(a8) @ 0 = [a8 cos(off8), a8 sin(off8), d8] (alpha8 does
    not move the origin). ``sigma`` = ``leica_unc`` in mm; ``sequence`` = ``pose_id``, taken as the order the
    poses were measured in (steps in it are a model extension: the set was measured with the target re-seated and
    the wrist re-homed, RESULTS 9.1). No masses are published; gravity [0, 0, -9.81] is an assumption (base z up).
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
             "point = pose_id; sequence = pose_id, taken as the order of measurement (a monotonic index; the "
             "poses a robust fit flags come in runs in it, p = 1.5e-8 for random order); no masses; gravity "
             "assumed [0,0,-9.81]; licence of data not stated")
    extra = {"sequence": (np.asarray(cols["pose_id"], float), "{:.0f}"), "sigma": (sigma_mm, "{:.6f}")}
    return Dataset("motoman_leica", model, _csv_text(points, MOTOMAN_JOINTS, q_deg, xyz_mm, extra), notes)
