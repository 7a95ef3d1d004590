"""Causes that act as an offset of one joint: compliance, backlash, cyclic (gear) error, scale error."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import RobotModel
from .base import Basis, Context, Effect, joint_basis


def _offset_unit(model: RobotModel, j: int) -> str:
    return "mm" if model.prismatic[j] else "rad"


def _load_unit(model: RobotModel, j: int) -> str:
    return "N" if model.prismatic[j] else "N*m"


@dataclass(frozen=True)
class JointCompliance(Effect):
    """dq_j = c * load_j: the joint (gear, motor, structure) deflects in proportion to its gravity load."""

    kind = "joint_compliance"
    needs = "mass"

    def parameter_names(self, model):
        return [f"{model.joint_names[self.joints[0]]}.compliance"]

    def parameter_units(self, model):
        j = self.joints[0]
        return [f"{_offset_unit(model, j)}/{_load_unit(model, j)}"]

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        load = ctx.loads[:, j]
        N, n = ctx.meas.joints.shape
        return Basis(joint_basis(N, n, j, load[:, None]), None, load,
                     f"gravity load on {ctx.model.joint_names[j]} ({_load_unit(ctx.model, j)})")

    def explain(self, model):
        return f"{model.joint_names[self.joints[0]]} deflects in proportion to its gravity and payload load"


@dataclass(frozen=True)
class Backlash(Effect):
    """dq_j = b/2 * tanh(load_j / transition): the joint sits on one flank of its gear play or the other;
    near zero load it floats in the play (transition in N*m or N; 0 = a sharp switch)."""

    kind = "backlash"
    needs = "mass"
    transition: float = 0.0
    TRANSITION_SHARE = 0.02  # of the largest load in the calibration data

    def parameter_names(self, model):
        return [f"{model.joint_names[self.joints[0]]}.backlash"]

    def parameter_units(self, model):
        return [_offset_unit(model, self.joints[0])]

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        load = ctx.loads[:, j]
        s = np.tanh(load / self.transition) if self.transition > 0 else np.sign(load)
        N, n = ctx.meas.joints.shape
        return Basis(joint_basis(N, n, j, 0.5 * s[:, None]), None, ctx.loads[:, j],
                     f"gravity load on {ctx.model.joint_names[j]} ({_load_unit(ctx.model, j)})")

    def explain(self, model):
        return f"{model.joint_names[self.joints[0]]} shifts by its gear play when its load changes sign"


@dataclass(frozen=True)
class CyclicJointError(Effect):
    """dq_j = a cos(h q_j) + b sin(h q_j): gear eccentricity (h = 1) or reducer stages (h = 2, 3)."""

    kind = "cyclic_joint_error"

    def parameter_names(self, model):
        n = model.joint_names[self.joints[0]]
        return [f"{n}.cyclic_h{self.harmonic}_cos", f"{n}.cyclic_h{self.harmonic}_sin"]

    def parameter_units(self, model):
        return ["rad", "rad"]

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        q = ctx.meas.joints[:, j]
        cols = np.column_stack([np.cos(self.harmonic * q), np.sin(self.harmonic * q)])
        N, n = ctx.meas.joints.shape
        return Basis(joint_basis(N, n, j, cols), None, np.degrees(q), f"{ctx.model.joint_names[j]} angle (deg)")

    def explain(self, model):
        return (f"{model.joint_names[self.joints[0]]} has an error that repeats {self.harmonic} time(s) per turn "
                "(gear eccentricity or reducer stage)")


@dataclass(frozen=True)
class JointScale(Effect):
    """dq_j = s * (q_j - mid_j): the joint reads off by a factor (gear ratio, encoder, linear scale)."""

    kind = "joint_scale"

    def parameter_names(self, model):
        return [f"{model.joint_names[self.joints[0]]}.scale"]

    def parameter_units(self, model):
        return ["1"]

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        q = ctx.meas.joints[:, j]
        lo, hi = ctx.model.limits[j]
        mid = 0.0 if not np.isfinite(lo + hi) else 0.5 * (lo + hi)
        N, n = ctx.meas.joints.shape
        unit = "mm" if ctx.model.prismatic[j] else "deg"
        reg = q if ctx.model.prismatic[j] else np.degrees(q)
        return Basis(joint_basis(N, n, j, (q - mid)[:, None]), None, reg, f"{ctx.model.joint_names[j]} ({unit})")

    def explain(self, model):
        return f"{model.joint_names[self.joints[0]]} moves by a slightly different amount than it reports"
