"""Real-data readers: shape, units, limits, and a physics check independent of our solver.

(The Agile Justin checks at the end also run our registration: ``identify(free=("base", "tool"))``.)

The physics check re-parses the contract CSV, runs a tiny standard-DH forward
kinematics written here (numpy only), fits the unknown tracker -> base transform
(and for the iiwa the unknown marker offset) and checks the residual is the few
millimetres an uncalibrated real arm shows. A wrong joint order, unit, sign or
tool fold-in would give tens to hundreds of millimetres.
"""
from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from calib_core.datasets import (
    IIWA_JOINTS,
    JUSTIN_ARMS,
    JUSTIN_MARKER_M,
    JUSTIN_TORSO,
    MOTOMAN_JOINTS,
    SHARED_DATASETS,
    Dataset,
    agile_justin,
    available,
    iiwa7_payload,
    justin_available,
    motoman_leica,
)

needs_shared = pytest.mark.skipif(not available(), reason="../shared/datasets not present")
needs_justin = pytest.mark.skipif(not justin_available(), reason="../shared/datasets/dlr_agile_justin not present")


# --- helpers written independently of calib_core ---------------------------------------

def parse_csv(text: str) -> tuple[list[str], dict[str, np.ndarray], list[str]]:
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].startswith(("#", "//"))]
    header, body = rows[0], rows[1:]
    cols = {h: np.array([float(r[i]) for r in body]) for i, h in enumerate(header) if h not in ("point", "target")}
    return header, cols, [r[0] for r in body]


def dh_fk(model: dict, q_deg: np.ndarray, tool_mm) -> np.ndarray:
    """Standard DH, Rz(theta+q) Tz(d) Tx(a) Rx(alpha), mm/deg; returns (N, 3) tool points in base."""
    n = len(q_deg)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i, j in enumerate(model["joints"]):
        th = np.radians(j["theta"] + q_deg[:, i])
        al = np.radians(j["alpha"])
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(al), np.sin(al)
        A = np.zeros((n, 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, j["a"] * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, j["a"] * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa, ca, j["d"]
        A[:, 3, 3] = 1.0
        T = T @ A
    return T[:, :3, :3] @ np.asarray(tool_mm, float) + T[:, :3, 3]


def kabsch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R P + t - Q| (rows are points)."""
    pm, qm = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - pm).T @ (Q - qm))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, qm - R @ pm


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def joints_and_xyz(ds: Dataset, names) -> tuple[np.ndarray, np.ndarray, dict]:
    header, cols, _ = parse_csv(ds.csv_text)
    q = np.column_stack([cols[n] for n in names])
    xyz = np.column_stack([cols["x"], cols["y"], cols["z"]])
    return q, xyz, cols


def check_limits(ds: Dataset, q: np.ndarray) -> None:
    lim = np.array([j["limits"] for j in ds.model["joints"]])
    assert np.all(q >= lim[:, 0]) and np.all(q <= lim[:, 1])


# --- tests --------------------------------------------------------------------------

@needs_shared
def test_motoman_shape_units_limits():
    ds = motoman_leica()
    assert ds.model["convention"] == "dh"
    assert ds.model["units"] == {"length": "mm", "angle": "deg"}
    assert [j["name"] for j in ds.model["joints"]] == list(MOTOMAN_JOINTS)
    header, cols, points = parse_csv(ds.csv_text)
    assert header == ["point", *MOTOMAN_JOINTS, "x", "y", "z", "sequence", "sigma"]
    assert len(points) == 586 and len(set(points)) == 586
    # the measurement order: pose_id, increasing with the rows
    assert np.array_equal(cols["sequence"], [float(p) for p in points]) and np.all(np.diff(cols["sequence"]) > 0)
    q, xyz, _ = joints_and_xyz(ds, MOTOMAN_JOINTS)
    check_limits(ds, q)
    assert np.abs(q[:, 0]).max() < 0.1  # torso E is ~0
    assert np.abs(q[:, 1:]).max() > 100  # degrees, not radians
    # tracker 2.4 .. 4.2 m away: millimetres, not metres
    assert 2000 < xyz[:, 0].min() and xyz[:, 0].max() < 4500
    assert 0 < cols["sigma"].min() and cols["sigma"].max() < 0.1  # microns-level, in mm
    # reflector link folded into the tool: |tool| = hypot(45, 245) mm
    assert np.hypot(*ds.model["tool"][:2]) == pytest.approx(45.0)
    assert ds.model["tool"][2] == pytest.approx(245.0)
    assert "\n" not in ds.notes


@needs_shared
def test_motoman_physics_rms():
    ds = motoman_leica()
    q, xyz, _ = joints_and_xyz(ds, MOTOMAN_JOINTS)
    p = dh_fk(ds.model, q, ds.model["tool"])
    R, t = kabsch(p, xyz)
    r = rms(p @ R.T + t - xyz)
    print(f"motoman nominal DH, tracker->base fitted: RMS {r:.3f} mm")
    assert 1.0 < r < 6.0
    # negative control: dropping the LR1 offset angle (tool [45, 0, 245]) costs ~10 mm RMS
    p_bad = dh_fk(ds.model, q, [45.0, 0.0, 245.0])
    R, t = kabsch(p_bad, xyz)
    assert rms(p_bad @ R.T + t - xyz) > 2 * r


@needs_shared
@pytest.mark.parametrize("payload", [0.0, 1.25, 2.5, 5.0])
def test_iiwa_shape_units_limits(payload):
    ds = iiwa7_payload(payload)
    assert [j["name"] for j in ds.model["joints"]] == list(IIWA_JOINTS)
    assert all(j["mass"] > 0 and len(j["com"]) == 3 for j in ds.model["joints"])
    assert max(abs(c) for j in ds.model["joints"] for c in j["com"]) > 50  # COM in mm
    header, cols, points = parse_csv(ds.csv_text)
    assert header == ["point", *IIWA_JOINTS, "x", "y", "z", "payload"]
    assert len(points) == 198 and len(set(points)) == 198
    assert np.all(cols["payload"] == payload)
    q, xyz, _ = joints_and_xyz(ds, IIWA_JOINTS)
    check_limits(ds, q)
    assert np.abs(q).max() > 90  # degrees
    assert 1200 < xyz[:, 2].max() < 1400  # marker above the 1266 mm tall arm, mm


@needs_shared
def test_iiwa_all_runs():
    ds = iiwa7_payload(None)
    _, cols, points = parse_csv(ds.csv_text)
    assert len(points) == 792 and len(set(points)) == 792
    assert sorted(set(cols["payload"])) == [0.0, 1.25, 2.5, 5.0]
    assert all(np.sum(cols["payload"] == p) == 198 for p in (0.0, 1.25, 2.5, 5.0))
    # one marker target per run (mounted anew for each payload), named like the run in the point ids
    header, _, _ = parse_csv(ds.csv_text)
    k = header.index("target")
    rows = [r for r in csv.reader(io.StringIO(ds.csv_text))][1:]
    assert all(r[0].split("-")[0] == r[k] for r in rows)
    assert [t["name"] for t in ds.model["targets"]] == ["run1", "run2", "run3", "run4"]
    assert "tool" not in ds.model and ds.model["convention"] == "mdh"


@needs_shared
def test_iiwa_unknown_payload_and_missing_folder(tmp_path):
    with pytest.raises(ValueError):
        iiwa7_payload(3.0)
    assert not available(tmp_path)
    with pytest.raises(FileNotFoundError, match="iiwa7_payload"):
        iiwa7_payload(0.0, root=tmp_path)
    with pytest.raises(FileNotFoundError, match="motoman_leica"):
        motoman_leica(root=tmp_path)


def fit_base_and_marker(model: dict, q: np.ndarray, xyz: np.ndarray) -> float:
    """Fit tracker->base (6) and marker-in-flange offset (3); return RMS in mm."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    # flange origin and axes from dh_fk with unit tool vectors
    pf = dh_fk(model, q, [0.0, 0.0, 0.0])
    Rf = np.stack([dh_fk(model, q, e) - pf for e in np.eye(3)], axis=2)

    R0, t0 = kabsch(pf, xyz)

    def resid(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        p = Rf @ x[6:9] + pf
        return (p @ R.T + x[3:6] - xyz).ravel()

    x0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), t0, np.zeros(3)])
    sol = least_squares(resid, x0, x_scale=np.r_[np.full(3, 0.01), np.full(6, 10.0)])
    return rms(sol.fun.reshape(-1, 3))


@needs_shared
def test_iiwa_physics_rms():
    found = {}
    for payload in (0.0, 5.0):
        ds = iiwa7_payload(payload)
        q, xyz, _ = joints_and_xyz(ds, IIWA_JOINTS)
        # the contract tool [0,0,0] is the flange: straight up at q = 0, 340+400+400+126 mm
        assert dh_fk(ds.model, np.zeros((1, 7)), ds.model["tool"])[0] == pytest.approx(
            [0.0, 0.0, 1266.0], abs=1e-6)
        found[payload] = fit_base_and_marker(ds.model, q, xyz)
    print("iiwa7 tracker->base + marker offset fitted: "
          + ", ".join(f"{p:g} kg RMS {r:.3f} mm" for p, r in found.items()))
    assert found[0.0] < 4.0
    assert found[5.0] < 6.0


# --- DLR Agile Justin (torso + one arm, Vicon) ------------------------------------------------

def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _tr(x=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def rokin_marker(arm: str, q: np.ndarray, orthonormal: bool) -> np.ndarray:
    """rokin's chain straight from the YAML, plain 4x4 products (m); q = [T1, T2, T3, T4c, arm 1..7]."""
    import yaml

    y = yaml.safe_load((SHARED_DATASETS / "dlr_agile_justin" / "justin19_nominal.yaml").read_text())
    F_arm = np.array(y[f"F_{arm.upper()}_BASE"], float)
    if orthonormal:  # the published 0.866 entries are cos 30 deg rounded: nearest rotation
        U, _, Vt = np.linalg.svd(F_arm[:3, :3])
        F_arm[:3, :3] = U @ Vt

    def dh(row, qi):  # Rx(alpha) Tx(a) Rz(theta + q) Tz(d), rows [d, theta, a, alpha]
        d, th, a, al = row
        return _rot("x", al) @ _tr(x=a) @ _rot("z", th + qi) @ _tr(z=d)

    out = []
    for qi in q:
        T = np.array(y["F_TORSO_BASE"], float)
        for k in range(4):
            T = T @ dh(y["DH_TORSO"][k], qi[k])
        T = T @ F_arm
        for k in range(7):
            T = T @ dh(y[f"DH_{arm.upper()}"][k], qi[4 + k])
        T = T @ np.array(y["F_TCP"], float)
        out.append((T @ np.r_[JUSTIN_MARKER_M[arm], 1.0])[:3])
    return np.array(out)


def _justin(arm):
    from calib_core.io import parse_measurements
    from calib_core.model import parse_model

    ds = agile_justin(arm)
    model = parse_model(ds.model)  # validates the contract model
    return ds, model, parse_measurements(ds.csv_text, model)  # validates the CSV against it (limits too)


@needs_justin
@pytest.mark.parametrize("arm", ["right", "left"])
def test_justin_shape_units_limits(arm):
    ds, model, meas = _justin(arm)
    names = [*JUSTIN_TORSO, *JUSTIN_ARMS[arm]]
    assert ds.name == f"agile_justin_{arm}"
    assert ds.model["convention"] == "mdh" and ds.model["units"] == {"length": "m", "angle": "rad"}
    assert [j["name"] for j in ds.model["joints"]] == names
    assert all("mass" not in j and "com" not in j for j in ds.model["joints"])
    assert ds.model["gravity"] == [0.0, 0.0, -9.81]  # the pan axis is the base z: base frame kept
    header, cols, points = parse_csv(ds.csv_text)
    assert header == ["point", *names, "x", "y", "z", "sigma"]
    assert meas.n_poses == 500 and len(set(points)) == 500
    assert np.allclose(cols["T4c"], -cols["T2"] - cols["T3"], atol=1e-11, rtol=0)  # the passive coupled joint
    assert np.all(cols["sigma"] == 0.0002)  # 0.2 mm, in metres like x, y, z
    assert np.abs(meas.sigma - 0.2).max() < 1e-12  # internally mm
    assert 1.0 < np.abs(np.column_stack([cols["x"], cols["y"]])).max() < 5.0  # metres
    assert np.degrees(cols["T1"]).max() > 190  # the pan really went past the vendor's 120 deg
    q, _, _ = joints_and_xyz(ds, names)
    check_limits(ds, q)
    assert "\n" not in ds.notes and "issue 11" in ds.notes and "sigma" in ds.notes


@needs_justin
@pytest.mark.parametrize("arm", ["right", "left"])
def test_justin_fold_matches_rokin_chain(arm):
    """The folded MD-H model through calib_core.kinematics gives rokin's marker point exactly."""
    from calib_core.kinematics import forward, nominal_vector

    ds, model, meas = _justin(arm)
    q = meas.joints[:60]  # rad
    p = forward(model, nominal_vector(model), q)  # mm, MD-H base = robot base here
    assert np.abs(p - 1000.0 * rokin_marker(arm, q, orthonormal=True)).max() < 1e-9
    # the published (rounded, not quite rigid) F_X_BASE differs by a few hundredths of a millimetre
    assert np.abs(p - 1000.0 * rokin_marker(arm, q, orthonormal=False)).max() < 0.05


@needs_justin
@pytest.mark.parametrize("arm", ["right", "left"])
def test_justin_registration_residual(arm):
    """Base and marker registered, nominal kinematics: ~20 mm mean as the NOTES and the paper (21 mm) say."""
    from calib_core.identify import identify

    ds, model, meas = _justin(arm)
    cal = identify(model, meas, free=("base", "tool"), folds=1)
    m = cal.metrics()
    print(f"agile justin {arm}: registration only mean {m['mean_mm']:.2f} mm, RMS {m['rms_mm']:.2f} mm")
    assert 15.0 < m["mean_mm"] < 25.0
    assert np.linalg.norm(cal.x[-3:] - model.tool) < 30.0  # the marker guess was close (mm)


def test_justin_missing_folder_and_bad_arm(tmp_path):
    assert not justin_available(tmp_path)
    with pytest.raises(FileNotFoundError, match="dlr_agile_justin"):
        agile_justin("right", root=tmp_path)
    with pytest.raises(ValueError, match="arm"):
        agile_justin("middle", root=tmp_path)
