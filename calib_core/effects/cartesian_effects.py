"""Causes that displace the tool point directly: link bending, a crooked linear axis, thermal drift."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kinematics import _cross
from ..statics import distal_loads, gravity_world, segment
from .base import Basis, Context, Effect


@dataclass(frozen=True)
class LinkDeflection(Effect):
    """Euler-Bernoulli cantilever: the link ending at joint k bends under its own weight and the load it carries.

    With c = 1/(EI): tip deflection c (F L^3/3 + W L^3/8) and tip rotation c (u x F L^2/2 + u x W L^2/6),
    F the perpendicular distal load, W the link's own perpendicular weight (Wang et al. 2023, section 5.1).
    The rotation moves the tool through its lever arm. L grows with a telescopic joint's extension.
    """

    kind = "link_deflection"
    needs = "mass"

    def parameter_names(self, model):
        return [f"{model.joint_names[self.joints[0]]}.link_compliance"]

    def parameter_units(self, model):
        return ["1/(N*mm^2)"]

    def basis(self, ctx: Context) -> Basis:
        k = self.joints[0]
        ch, m = ctx.chain, ctx.model
        start, end, L = segment(ch, k)
        u = (end - start) / np.maximum(L, 1e-9)[:, None]
        g = gravity_world(ch)
        M, _ = distal_loads(ch, ctx.meas.payload_kg())
        F = M[k][:, None] * g  # N, everything beyond the segment end
        W = (m.mass[k - 1] if k > 0 else 0.0) * np.broadcast_to(g, F.shape)  # the segment's own body
        perp = lambda v: v - (v * u).sum(1, keepdims=True) * u  # noqa: E731
        Fp, Wp = perp(F), perp(W)
        L1 = L[:, None]
        tip = Fp * L1**3 / 3 + Wp * L1**3 / 8
        rot = _cross(u, Fp) * L1**2 / 2 + _cross(u, Wp) * L1**2 / 6
        dp = tip + _cross(rot, ch.p - end)
        return Basis(None, dp[:, :, None], np.linalg.norm(dp, axis=1),
                     f"bending of the link ending at {m.joint_names[k]} per unit 1/(EI) (mm*N*mm^2)")

    def explain(self, model):
        return f"the link ending at {model.joint_names[self.joints[0]]} bends under its own weight and what it carries"


@dataclass(frozen=True)
class AxisStraightness(Effect):
    """A linear axis whose carriage wanders sideways: quadratic and cubic in travel, both perpendicular
    directions (constant and linear parts are the axis' position and direction, already geometric)."""

    kind = "axis_straightness"

    def parameter_names(self, model):
        n = model.joint_names[self.joints[0]]
        return [f"{n}.straightness_{d}{p}" for d in ("x", "y") for p in (2, 3)]

    def parameter_units(self, model):
        return ["mm"] * 4

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        lo, hi = ctx.model.limits[j]
        s = (ctx.meas.joints[:, j] - 0.5 * (lo + hi)) / (0.5 * (hi - lo))  # -1 .. 1 over the travel
        ch = ctx.chain
        Rj = ch.R[j]
        x_axis, y_axis = Rj[:, :, 0], Rj[:, :, 1]
        cols = [ax * (s**p)[:, None] for ax in (x_axis, y_axis) for p in (2, 3)]
        return Basis(None, np.stack(cols, axis=2), ctx.meas.joints[:, j],
                     f"{ctx.model.joint_names[j]} travel (mm)")

    def explain(self, model):
        return f"the linear axis {model.joint_names[self.joints[0]]} is not straight"


@dataclass(frozen=True)
class ThermalDrift(Effect):
    """Error growing with temperature (or, without it, time): a drift of the robot against the tracker
    (3 translations) and a uniform expansion of the structure about its base (1 strain)."""

    kind = "thermal_drift"
    needs = "time"
    source: str = "temperature"  # or "time"
    ref: float = 0.0  # the calibration's mean temperature (deg C) or time (s since the epoch)
    lo: float = -np.inf
    hi: float = np.inf
    """The session's range of the driver: a drift is never extrapolated beyond what it was fitted on."""

    @classmethod
    def for_data(cls, meas) -> "ThermalDrift":
        col, source = (meas.temperature, "temperature") if meas.temperature is not None else (meas.timestamp, "time")
        return cls((), source=source, ref=float(col.mean()), lo=float(col.min()), hi=float(col.max()))

    def parameter_names(self, model):
        return ["thermal.drift_x", "thermal.drift_y", "thermal.drift_z", "thermal.expansion"]

    def parameter_units(self, model):
        u = "degC" if self.source == "temperature" else "h"
        return [f"mm/{u}"] * 3 + [f"1/{u}"]

    def driver(self, meas) -> tuple[np.ndarray, str]:
        """Temperature above the calibration mean (deg C) or hours since its mean time; 0 where absent."""
        col = meas.temperature if self.source == "temperature" else meas.timestamp
        if col is None:
            return np.zeros(meas.n_poses), "none"
        col = np.clip(col, self.lo, self.hi)
        if self.source == "temperature":
            return col - self.ref, "temperature above calibration mean (deg C)"
        return (col - self.ref) / 3600.0, "time from calibration mean (h)"

    def basis(self, ctx: Context) -> Basis:
        s, label = self.driver(ctx.meas)
        N = len(s)
        cols = np.zeros((N, 3, 4))
        cols[:, [0, 1, 2], [0, 1, 2]] = s[:, None]
        cols[:, :, 3] = (ctx.chain.p - ctx.chain.base_origin) * s[:, None]
        return Basis(None, cols, s, label)

    def explain(self, model):
        return "the robot drifts against the tracker as it warms up (or over time)"
