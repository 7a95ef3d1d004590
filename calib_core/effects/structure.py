"""Structure outside the named causes: what a residual follows (time order, one joint, the load, a region
of the workspace), as plug-ins of the same shape, so the same F-test tells whether the residual follows it.

`SessionStep` is also a model extension: something changed mid-session (a re-homing, a bumped tracker or
SMR nest). It never extrapolates: after the session the robot stays in its last state.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from ..kinematics import _cross
from .base import Basis, Context, Effect
from .joint_effects import _offset_unit


CLOCKS = {"time": "timestamp", "sequence": "sequence"}
"""A step's source -> the measurement column that places each pose in the session (the row order has none: it is
only a guess at the order, so a step in row order is never a model extension)."""
ORDER_NAMES = {"time": "time order", "sequence": "measurement order (sequence)", "row": "row order (no timestamps)"}
"""A clock's order as the answer names it."""


def session_clock(meas) -> tuple[np.ndarray, str]:
    """Per-pose time (s since the epoch), else the measurement order of the `sequence` column, else the row order;
    and its name ("time", "sequence", "row")."""
    for source, column in CLOCKS.items():
        if getattr(meas, column) is not None:
            return np.asarray(getattr(meas, column), float), source
    return np.arange(meas.n_poses, dtype=float), "row"


def _clock_column(meas, source: str) -> np.ndarray | None:
    """The column a step of this source reads on these poses (None: the poses do not say, or the row order)."""
    column = CLOCKS.get(source)
    return None if column is None or getattr(meas, column) is None else np.asarray(getattr(meas, column), float)


@dataclass(frozen=True)
class SessionStep(Effect):
    """A step at `at` in time order (`source`: "time", the timestamps; "sequence", the measurement order; "row",
    the row order, only to say what a residual follows): a joint offset (joints = (j,)) or a 6-DoF shift of the
    whole robot against the tracker (joints = ()). Poses at or after `at` carry the step; poses without a time or a
    sequence number (new programs) are taken to be after it, the robot's current state."""

    kind = "unexplained"
    bounded = False  # a joint re-homed or a tracker moved can be off by any amount
    at: float = 0.0
    source: str = "time"
    gap: tuple = ()  # (the times of the measured poses either side of `at`): where the step may be

    def misplaced(self, ctx: Context) -> np.ndarray:
        """(N,) probability that a pose is on the wrong side of the step: the step lies anywhere in `gap` (uniform),
        so a pose inside it is wrong with the share of the gap between it and `at`'s side; 0 elsewhere and for
        poses without a time."""
        meas = ctx.meas
        t = _clock_column(meas, self.source)
        if len(self.gap) != 2 or t is None:
            return np.zeros(meas.n_poses)
        lo, hi = self.gap
        share = np.clip((t - lo) / max(hi - lo, 1e-300), 0.0, 1.0)
        return np.where(t >= self.at, 1.0 - share, share) * ((t > lo) & (t < hi))

    def after(self, meas) -> np.ndarray:
        t = _clock_column(meas, self.source)
        if t is not None:
            return (t >= self.at).astype(float)
        if self.source == "row" and session_clock(meas)[1] == "row" and meas.n_poses > self.at:
            return (np.arange(meas.n_poses) >= self.at).astype(float)
        return np.ones(meas.n_poses)

    def place(self) -> str:
        """Where the step sits, in its parameters' names (two steps of one joint are two parameters): the UTC time
        to the second, else the sequence number or row."""
        if self.source == "time":
            return datetime.fromtimestamp(self.at, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
        return f"{self.at:.12g}"  # a sequence number as written (:g read 1234567.5 as 1.23457e+06)

    def parameter_names(self, model):
        if self.joints:
            return [f"{model.joint_names[self.joints[0]]}.step[{self.place()}]"]
        return [f"step[{self.place()}].{a}" for a in ("x", "y", "z", "rx", "ry", "rz")]

    def parameter_units(self, model):
        if self.joints:
            return ["mm" if model.prismatic[self.joints[0]] else "rad"]
        return ["mm"] * 3 + ["rad"] * 3

    def basis(self, ctx: Context) -> Basis:
        s = self.after(ctx.meas)
        N, n = ctx.meas.joints.shape
        if self.joints:
            b = np.zeros((N, n, 1))
            b[:, self.joints[0], 0] = s
            return Basis(b, None, s, "after the step (0 / 1)")
        lever = ctx.chain.p - ctx.chain.base_origin
        cart = np.zeros((N, 3, 6))
        for a in range(3):
            cart[:, a, a] = s
            e = np.zeros(3)
            e[a] = 1.0
            cart[:, :, 3 + a] = _cross(np.broadcast_to(e, lever.shape), lever) * s[:, None]
        return Basis(None, cart, s, "after the step (0 / 1)")

    def label(self, model):
        return f"step[{','.join(model.joint_names[j] for j in self.joints) or 'robot'} @ {self.place()}]"

    def stepped(self, model) -> str:
        """What stepped, for people."""
        return f"{model.joint_names[self.joints[0]]}'s zero" if self.joints else "the robot against the tracker"

    def explain(self, model):
        return f"{self.stepped(model)} shifted mid-session (a re-homing, a bumped tracker or SMR nest)"


@dataclass(frozen=True)
class TargetStep(SessionStep):
    """A step at `at` in time order of the measured target against the frame it sits on (a marker, SMR nest or tool
    taken off and re-mounted mid-campaign): from then on the point sits (x, y, z) mm further in that frame (the
    flange's, for a tool), at every pose after the step; 3 parameters. A joint's zero or the whole robot's shift
    cannot carry it: the offset turns with the flange (issue 34, a target re-mounted at pose N)."""

    def parameter_names(self, model):
        return [f"target_step[{self.place()}].{a}" for a in ("x", "y", "z")]

    def parameter_units(self, model):
        return ["mm"] * 3

    def basis(self, ctx: Context) -> Basis:
        s = self.after(ctx.meas)
        return Basis(None, ctx.chain.R_end * s[:, None, None], s, "after the step (0 / 1)")

    def label(self, model):
        return f"step[target @ {self.place()}]"

    def stepped(self, model) -> str:
        return "the target on its flange"

    def explain(self, model):
        return ("the measured target (a marker, SMR nest or tool) moved on the flange mid-session: re-mounted or "
                "knocked, it sits elsewhere on the frame it is fixed to from then on")


def step_candidates(meas, joints: list[int], n_splits: int = 16, margin: int = 8) -> list[SessionStep]:
    """Steps at n_splits evenly spaced places in time order, each on the whole robot, of the target on its flange
    (TargetStep) and on every joint."""
    clock, source = session_clock(meas)
    order = np.sort(clock)
    N = len(order)
    if N < 2 * margin + 2:
        return []
    return _steps_at(order, source, np.unique(np.linspace(margin, N - margin, n_splits).astype(int)), joints)


STEP_WINDOW = 8
"""Poses either side of a found step among which its exact place is sought."""


def steps_near(meas, joints: list[int], at: float) -> list[SessionStep]:
    """Every kind of step (the whole robot, the target, each joint) at every gap within STEP_WINDOW poses of `at`
    in time order: the grid of step_candidates puts a step up to half its spacing off, and the kinds are compared
    at the exact place (a pose on the wrong side favours the kind with more parameters)."""
    clock, source = session_clock(meas)
    order = np.sort(clock)
    k = int(np.searchsorted(order, at))
    return _steps_at(order, source, range(max(k - STEP_WINDOW, 1), min(k + STEP_WINDOW, len(order) - 1) + 1), joints)


def _steps_at(order: np.ndarray, source: str, idx, joints: list[int]) -> list[SessionStep]:
    """The whole robot's, the target's and each joint's step between poses i - 1 and i of the sorted clock, per i."""
    out = []
    for i in idx:
        place = at_gap(order, i, source)
        out.append(SessionStep((), source=source, **place))
        out.append(TargetStep((), source=source, **place))
        out += [SessionStep((j,), source=source, **place) for j in joints]
    return out


def at_gap(order: np.ndarray, i: int, source: str) -> dict:
    """Where a step between the poses i - 1 and i of the sorted clock goes: halfway in time (or in the sequence),
    and the gap it may lie anywhere in (the poses' times); by row number without either."""
    if source not in CLOCKS:
        return {"at": float(i)}
    return {"at": float(0.5 * (order[i - 1] + order[i])), "gap": (float(order[i - 1]), float(order[i]))}


@dataclass(frozen=True)
class Probe(Effect):
    """A regression on one family of regressors, only to ask what a residual follows: 'joint' (harmonics of one
    joint, Cartesian), 'drive' (the other joints' offsets as harmonics of one joint: a cable or hose it pulls),
    'region' (quadratic in the tool position), 'time' (drift)."""

    kind = "unexplained"
    family: str = "joint"

    def _features(self, ctx: Context) -> tuple[np.ndarray, np.ndarray, str]:
        m, q = ctx.model, ctx.meas.joints
        if self.family in ("joint", "drive"):
            j = self.joints[0]
            if m.prismatic[j]:
                lo, hi = m.limits[j]
                s = (q[:, j] - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
                return np.column_stack([s, s**2, s**3]), q[:, j], f"{m.joint_names[j]} (mm)"
            a = q[:, j]
            return (np.column_stack([np.cos(a), np.sin(a), np.cos(2 * a), np.sin(2 * a)]), np.degrees(a),
                    f"{m.joint_names[j]} (deg)")
        if self.family == "region":
            p = ctx.chain.p - ctx.chain.p.mean(0)
            p = p / max(float(np.abs(p).max()), 1e-9)
            x, y, z = p.T
            return np.column_stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z]), ctx.chain.p[:, 2], \
                "tool height in the measurement frame (mm)"
        clock, source = session_clock(ctx.meas)
        t = (clock - clock.mean()) / max(float(np.ptp(clock)), 1e-9)
        return np.column_stack([t, t**2]), clock, {"time": "time (s)", "sequence": "measurement order"}.get(source,
                                                                                                          "row order")

    def _n_features(self, model) -> int:
        if self.family in ("joint", "drive"):
            return 3 if model.prismatic[self.joints[0]] else 4
        return 9 if self.family == "region" else 2

    def _driven(self, model) -> list[int]:
        return [k for k in range(model.n_joints) if k != self.joints[0]]

    def parameter_names(self, model):
        F = self._n_features(model)
        if self.family == "drive":
            return [f"probe.{model.joint_names[k]}_{i}" for k in self._driven(model) for i in range(F)]
        return [f"probe.{a}{i}" for a in "xyz" for i in range(F)]

    def parameter_units(self, model):
        if self.family == "drive":
            return [_offset_unit(model, k) for k in self._driven(model) for _ in range(self._n_features(model))]
        return ["mm"] * len(self.parameter_names(model))

    def basis(self, ctx: Context) -> Basis:
        phi, reg, label = self._features(ctx)
        N, F = phi.shape
        if self.family == "drive":
            driven = self._driven(ctx.model)
            joint = np.zeros((N, ctx.model.n_joints, len(driven) * F))
            for i, k in enumerate(driven):
                joint[:, k, i * F:(i + 1) * F] = phi
            return Basis(joint, None, reg, label)
        cart = np.zeros((N, 3, 3 * F))
        for a in range(3):
            cart[:, a, a * F:(a + 1) * F] = phi
        return Basis(None, cart, reg, label)

    def describe(self, model) -> str:
        if self.family == "joint":
            return f"the angle or travel of {model.joint_names[self.joints[0]]}"
        if self.family == "drive":
            return (f"the angle or travel of {model.joint_names[self.joints[0]]} through the other joints (a cable "
                    "or hose it pulls, a coupling)")
        return {"region": "the tool's position in the workspace", "time": "time order (a drift)"}[self.family]

    def explain(self, model):
        return f"the residual follows {self.describe(model)}"


def probes(model, meas) -> list[Probe]:
    """Two probes per joint that moves (Cartesian, and through the other joints), one for the workspace region,
    one for time order."""
    moving = [j for j in range(model.n_joints) if np.ptp(meas.joints[:, j]) > 1e-3]
    out = [Probe((j,), family=f) for f in ("joint", "drive") for j in moving]
    out.append(Probe((), family="region"))
    out.append(Probe((), family="time"))
    return out
