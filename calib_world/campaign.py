"""A world with a laser tracker: measurement campaigns of the physical robot, with the world's own noise model.

Tracker noise is 15 um + 6 um per metre of distance from the tracker (the tracker frame's origin), per
axis; the robot's pose repeatability is drawn once per world between 20 and 30 um per axis.  A campaign
measures a pose every 20 s while the workshop warms up; the truth (noise-free points, causes, outliers)
is kept for validation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib_core.io import Measurements
from calib_core.model import RobotModel

from .mechanics import Cause, Context, GrossOutliers, simulate
from .robot import PhysicalRobot, rigid, rotvec

TRACKER_SIGMA0_MM = 0.015
TRACKER_SIGMA_PER_M_MM = 0.006
"""Laser tracker 1-sigma per axis: 15 um + 6 um per metre from the tracker."""
REPEATABILITY_RANGE_MM = (0.020, 0.030)
"""The robot's pose repeatability per axis (1-sigma), drawn per world in this range."""
POSE_INTERVAL_S = 20.0
START_TIME = 1_800_000_000.0
"""A campaign starts at this time (2027-01-15) unless told otherwise; a pose every 20 s."""


def sample_joints(robot: PhysicalRobot, n: int, rng: np.random.Generator, margin: float = 0.05) -> np.ndarray:
    """n joint vectors uniform within the limits (rad / mm), `margin` of each range kept clear;
    an unlimited revolute joint is drawn in -pi..pi."""
    lo, hi = robot.limits[:, 0].copy(), robot.limits[:, 1].copy()
    free = ~(np.isfinite(lo) & np.isfinite(hi))
    lo[free], hi[free] = -np.pi, np.pi
    return lo + (hi - lo) * rng.uniform(margin, 1.0 - margin, (n, robot.n))


@dataclass
class Truth:
    """What really happened in a campaign: noise-free points (N, 3) mm with the hidden causes, the points
    the geometry alone would give, the noise drawn, bad readings and repeated poses (-1 where none)."""

    points: np.ndarray
    geometric: np.ndarray
    noise: np.ndarray
    outliers: np.ndarray
    repeat_of: np.ndarray
    causes: list = field(default_factory=list)

    @property
    def displacement(self) -> np.ndarray:
        """What the hidden causes add to the tool point, (N, 3) mm."""
        return self.points - self.geometric


@dataclass
class Campaign:
    """A measurement campaign: what the tracker reported and what was true."""

    meas: Measurements
    truth: Truth


class World:
    """A physical robot (true geometry, masses, hidden causes) in front of a laser tracker.

    `hide(cause)` gives the robot a cause; `measure(...)` returns contract Measurements; `true_points`
    gives the noise-free truth.  The robot: `self.robot` (PhysicalRobot)."""

    def __init__(self, model: RobotModel, seed: int | None = None, *, rng: np.random.Generator | None = None,
                 geometry_error: float = 1.0, tool_error_mm: float = 5.0, mass_error: float = 1.0,
                 level_error_rad: float = 5e-4, noise: bool = True, repeatability_mm: float | None = None,
                 outliers: int = 0, start_time: float = START_TIME):
        """noise=False: perfect tracker and robot repeatability; outliers: number of gross bad readings per
        campaign.  See PhysicalRobot for the error options."""
        self.rng = np.random.default_rng(seed) if rng is None else rng
        rng = self.rng
        self.model = model
        self.robot = PhysicalRobot(model, rng, geometry_error=geometry_error, tool_error_mm=tool_error_mm,
                                   mass_error=mass_error, level_error_rad=level_error_rad)
        self.repeatability_mm = float(rng.uniform(*REPEATABILITY_RANGE_MM) if repeatability_mm is None
                                      else repeatability_mm)
        self.noise = noise
        self.outliers = GrossOutliers(outliers, seed=int(rng.integers(2**31))) if outliers else None
        self.causes: list[Cause] = []
        self.start_time = start_time
        self.ambient_degC = float(20.0 + rng.uniform(-2.0, 2.0))
        self.warming_degC = 6.0
        self.warming_tau_s = 5400.0
        self.hvac: tuple | None = None
        """(amplitude deg C, period s, phase rad) of the air conditioning's cycle on top of the warming, or None."""
        self.last: Campaign | None = None

    # ------------------------------------------------------------------------------------ setup
    def hide(self, cause: Cause) -> Cause:
        """Give the physical robot a cause the calibration does not know about."""
        self.causes.append(cause)
        return cause

    def sample_joints(self, n: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """n random poses within the joint limits with a 5 % margin."""
        return sample_joints(self.robot, n, self.rng if rng is None else rng)

    def temperature_at(self, t: np.ndarray) -> np.ndarray:
        """The workshop's physical temperature (deg C) at times t: warming from ambient after the start, and the air
        conditioning's cycle when `hvac` is set."""
        dt = np.maximum(np.asarray(t, float) - self.start_time, 0.0)
        temp = self.ambient_degC + self.warming_degC * (1.0 - np.exp(-dt / self.warming_tau_s))
        if self.hvac is not None:
            amp, period, phase = self.hvac
            temp = temp + amp * (np.sin(2 * np.pi * dt / period + phase) - np.sin(phase))
        return temp

    def columns(self, q, payload_kg=None, temperature: bool = False, start_time: float | None = None) -> Measurements:
        """The non-positional columns of a campaign at joints q: timestamps 20 s apart, optional logged
        temperature, payload (None: no column, a value, or a list cycled over the poses). Points are zero."""
        q = np.atleast_2d(np.asarray(q, float))
        N = len(q)
        t = (self.start_time if start_time is None else start_time) + POSE_INTERVAL_S * np.arange(N)
        payload = None if payload_kg is None else np.resize(np.asarray(payload_kg, float), N)
        temp = self.temperature_at(t) if temperature else None
        return Measurements(joints=q, points=np.zeros((N, 3)), point_ids=[f"P{i + 1:04d}" for i in range(N)],
                            timestamp=t, temperature=temp, payload=payload)

    def context(self, q, columns: Measurements | None = None) -> Context:
        cols = self.columns(q) if columns is None else columns
        q = np.atleast_2d(np.asarray(q, float))
        t = cols.timestamp if cols.timestamp is not None else self.start_time + POSE_INTERVAL_S * np.arange(len(q))
        return Context(self.robot, q, t, self.temperature_at(t), cols.payload_kg(), self.ambient_degC)

    # ------------------------------------------------------------------------------------ truth
    def true_points(self, q, columns: Measurements | None = None, causes=None) -> np.ndarray:
        """Noise-free tool points (N, 3) mm in the tracker frame with the hidden causes (or `causes`)."""
        causes = self.causes if causes is None else causes
        return simulate(self.robot, causes, self.context(q, columns))

    def geometric_points(self, q) -> np.ndarray:
        """Tool points (N, 3) mm of the true rigid geometry alone."""
        return self.robot.point(q)

    def displacement(self, causes, q, columns: Measurements | None = None) -> np.ndarray:
        """What `causes` (one or a list) alone add to the tool point at these poses, (N, 3) mm."""
        causes = [causes] if isinstance(causes, Cause) else list(causes)
        return self.true_points(q, columns, causes) - self.geometric_points(q)

    # ------------------------------------------------------------------------------------ noise
    def tracker_sigma_mm(self, points) -> np.ndarray:
        """Per-axis 1-sigma (N,) mm of the tracker plus the robot's repeatability, whether or not noise is on."""
        tracker = TRACKER_SIGMA0_MM + TRACKER_SIGMA_PER_M_MM * np.linalg.norm(points, axis=1) / 1000.0
        return np.sqrt(tracker**2 + self.repeatability_mm**2)

    def noise_sigma_mm(self, points) -> np.ndarray:
        """Per-axis 1-sigma (N,) mm actually applied to a measured point (0 with noise=False)."""
        return self.tracker_sigma_mm(points) if self.noise else np.zeros(len(points))

    def noise_rms_mm(self, q) -> float:
        """3-D RMS (mm) per pose of the noise model at joints q, the yardstick of `hide` sizes (defined
        even on a noise-free world)."""
        s = self.tracker_sigma_mm(self.geometric_points(q))
        return float(np.sqrt(np.mean(3.0 * s**2)))

    # ------------------------------------------------------------------------------------ geometry absorbs
    def geometric_jacobian(self, q, h_len: float = 1e-3, h_ang: float = 1e-5) -> np.ndarray:
        """Central finite differences of the world's own FK, (3N, 5n + 9): every MD-H parameter, base
        (3 translations, 3 small rotations in the tracker frame) and tool point, in mm and rad."""
        r = self.robot
        q = np.atleast_2d(np.asarray(q, float))
        N, n = q.shape
        P = 5 * n + 9
        steps = np.r_[np.tile([h_len, h_ang, h_len, h_ang, h_ang], n), [h_len] * 3, [h_ang] * 3, [h_len] * 3]
        geo = np.broadcast_to(r.geometry, (2, P, N, n, 5)).copy()
        base = np.broadcast_to(r.base, (2, P, N, 4, 4)).copy()
        tool = np.broadcast_to(r.tool, (2, P, N, 3)).copy()
        for si, sign in enumerate((1.0, -1.0)):
            for p in range(P):
                hs = sign * steps[p]
                if p < 5 * n:
                    geo[si, p, :, p // 5, p % 5] += hs
                elif p < 5 * n + 6:
                    v = np.zeros(3)
                    v[(p - 5 * n) % 3] = hs
                    T = rigid(t=v) if p < 5 * n + 3 else rigid(R=rotvec(v))
                    base[si, p] = T @ r.base
                else:
                    tool[si, p, :, p - 5 * n - 6] += hs
        qq = np.broadcast_to(q, (2, P, N, n)).reshape(-1, n)
        pts = r.frames(qq, geometry=geo.reshape(-1, n, 5), tool=tool.reshape(-1, 3),
                       base=base.reshape(-1, 4, 4)).point.reshape(2, P, N, 3)
        J = (pts[0] - pts[1]) / (2 * steps[:, None, None])  # (P, N, 3)
        return J.reshape(P, 3 * N).T

    def absorbable_basis(self, q) -> np.ndarray:
        """Orthonormal basis (3N, r) of every displacement a change of geometry, base or tool can make."""
        J = self.geometric_jacobian(q)
        J = J / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
        U, s, _ = np.linalg.svd(J, full_matrices=False)
        return U[:, s > 1e-7 * s[0]]

    def unabsorbed(self, d: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """The part (N, 3) of a displacement d (N, 3) that no geometric parameter can absorb."""
        v = d.ravel()
        return (v - basis @ (basis.T @ v)).reshape(-1, 3)

    def unabsorbed_rms(self, causes, q, columns: Measurements | None = None, absorb: bool = True,
                       basis: np.ndarray | None = None) -> float:
        """3-D RMS (mm) of what `causes` add that no geometric parameter can absorb (all of it if not absorb)."""
        d = self.displacement(causes, q, columns)
        if absorb:
            d = self.unabsorbed(d, self.absorbable_basis(q) if basis is None else basis)
        return float(np.sqrt(np.mean((d**2).sum(1))))

    # ------------------------------------------------------------------------------------ measuring
    def campaign(self, q=None, n: int = 150, payload_kg=None, temperature: bool = False, repeats: int = 0,
                 start_time: float | None = None) -> Campaign:
        """Measure the robot at joints q (N, n) or n random poses; `repeats` poses drawn from these are
        measured again at the end.  Returns the Measurements and the Truth."""
        rng = self.rng
        q = self.sample_joints(n) if q is None else np.atleast_2d(np.asarray(q, float))
        N0 = len(q)
        repeat_of = np.full(N0, -1)
        if repeats:
            again = rng.choice(N0, repeats, replace=repeats > N0)
            q = np.vstack([q, q[again]])
            repeat_of = np.r_[repeat_of, again]
        cols = self.columns(q, payload_kg, temperature, start_time)
        true = self.true_points(q, cols)
        N = len(q)
        noise = rng.normal(size=(N, 3)) * self.noise_sigma_mm(true)[:, None]
        bad = np.zeros(0, int)
        pts = true + noise
        if self.outliers is not None:
            bad, err = dataclass_replace_seed(self.outliers, int(rng.integers(2**31))).draw(N)
            pts = pts + err
        cols.points = pts
        truth = Truth(true, self.geometric_points(q), noise, bad, repeat_of,
                      [c.describe(self.robot) for c in self.causes])
        self.last = Campaign(cols, truth)
        return self.last

    def measure(self, q=None, n: int = 150, payload_kg=None, temperature: bool = False, repeats: int = 0,
                start_time: float | None = None) -> Measurements:
        """Like `campaign` but returns only the Measurements (the truth stays in `self.last.truth`)."""
        return self.campaign(q, n, payload_kg, temperature, repeats, start_time).meas


def dataclass_replace_seed(o: GrossOutliers, seed: int) -> GrossOutliers:
    """The same outlier process with a fresh seed: each campaign has its own bad readings."""
    return GrossOutliers(o.count, o.size_mm, seed)
