"""What every dataset reader shares: where the datasets are, the Dataset a reader returns, CSV and frame helpers."""
from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np


SHARED_DATASETS: Path = Path(
    os.environ.get(
        "CALIB_SHARED_DATASETS",
        Path(__file__).resolve().parents[2].parent / "shared" / "datasets",
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


# --- contract section 5 helpers ----------------------------------------------------------------

def _xyz_rpy(T: np.ndarray, digits: int = 12) -> tuple[list[float], list[float]]:
    """A rigid 4x4 transform (m) as URDF xyz (m) and rpy (rad): Trans(xyz) Rz(y) Ry(p) Rx(r)."""
    from ..urdf import matrix_rpy

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
