"""Causes that act as an offset of one joint: compliance, backlash, cyclic (gear) error, scale error.

Each acts on the joint's drive: where coupled rows follow an actuated joint (a parallelogram, Agile Justin's
torso), the drive's offset moves them too (Context.moves) and its load is the drive's (base.loads)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial.hermite_e import hermegauss
from scipy import special

from ..model import RobotModel
from .base import Basis, Context, Effect, joint_basis, loads


PLAY_PRIOR_RAD = 0.01
"""Ridge prior std (rad) of a gear play: a real play is arcminutes, a worn gear's a few tenths of a degree. Without
it a play whose switch a held-out fold classifies differently (an identified load) can grow to degrees there and
its held-out poses land centimetres off, which misleads every held-out comparison after it (Agile Justin: folds
up to 107 mm off, RESULTS 3.9)."""
PLAY_PRIOR_MM = 1.0
"""The same for a prismatic joint (mm; 100 mm per rad, as diagnose's plausible sizes)."""
LOAD_DOUBT = (lambda x, w: (x, w / w.sum()))(*hermegauss(40))
"""Gauss-Hermite nodes and weights of a standard normal: expectations over a load's doubt."""


def _offset_unit(model: RobotModel, j: int) -> str:
    return "mm" if model.prismatic[j] else "rad"


def _load_unit(model: RobotModel, j: int) -> str:
    return "N" if model.prismatic[j] else "N*m"


def _followers(model: RobotModel, joints) -> str:
    """", turning X with it" for the coupled rows the joints' drives move (RobotModel.followers), else ""."""
    rows = sorted({int(r) for j in joints for r in model.followers(j)} - set(joints))
    return f", turning {', '.join(model.joint_names[r] for r in rows)} with {'it' if len(joints) == 1 else 'them'}" \
        if rows else ""


def hardening(u: np.ndarray, r: float) -> np.ndarray:
    """The deflection g of a stiffening spring, g + r g^3 = u (all in units of the largest load): the real
    root by Cardano's formula; g = u for a linear spring (r = 0)."""
    if r <= 0:
        return u
    q = -u / r
    disc = np.sqrt(q**2 / 4 + 1.0 / (27 * r**3))
    return np.cbrt(-q / 2 + disc) + np.cbrt(-q / 2 - disc)


def identified_load(ctx: Context, j: int, coef: tuple) -> np.ndarray:
    """The load on joint j's drive identified from the data, (N,): gravity regressor columns and the payload column
    weighted by `coef` (see gravity.py), in N*m or N, or in a play's transition units when its softness was fitted."""
    from .gravity import drive_payload_load, drive_regressor

    coef = np.asarray(coef, float)
    payload = drive_payload_load(ctx.chain, ctx.meas.payload_kg(), j)
    return drive_regressor(ctx.chain, j) @ coef[:-1] + coef[-1] * payload


@dataclass(frozen=True)
class JointCompliance(Effect):
    """dq_j = c_j * load_j: each joint (gear, motor, structure) deflects with its gravity and payload load from
    the model's mass data; one joint or several. With `stiffening` r > 0 the spring hardens: the deflection
    g solves g + r g^3 = load / load_scale (times load_scale), so it grows less and less with the load. With
    `load_coef` (one joint) the load is a play's identified load (identified_load) and the parameter is the
    deflection at load_scale, in rad or mm: a spring that looks like the soft play the search found."""

    kind = "joint_compliance"
    needs = "mass"
    stiffening: float = 0.0
    load_scale: float = 1.0  # N*m or N (or the identified load's units): the largest load in the calibration data
    masses: tuple = ()  # (n, 4) mass data identified from the data (kg, kg*mm), else the model's (gravity.py)
    load_coef: tuple = ()
    fitted_softness: bool = False  # load_coef came from a play whose softness was fitted (see Backlash)
    gravity: tuple = ()  # (3,) m/s^2 in the base frame identified with the masses, else the model's

    def parameter_names(self, model):
        what = "deflection_at_largest_load" if self.load_coef else "compliance"
        return [f"{model.joint_names[j]}.{what}" for j in self.joints]

    def parameter_units(self, model):
        if self.load_coef:
            return [_offset_unit(model, j) for j in self.joints]
        return [f"{_offset_unit(model, j)}/{_load_unit(model, j)}" for j in self.joints]

    def basis(self, ctx: Context) -> Basis:
        N, n = ctx.meas.joints.shape
        b = np.zeros((N, n, len(self.joints)))
        j = self.joints[0]
        if self.load_coef:
            load = np.zeros((N, n))
            load[:, j] = identified_load(ctx, j, self.load_coef)
        else:
            load = ctx.loads if not (self.masses or self.gravity) else loads(
                ctx.chain, ctx.meas, np.asarray(self.masses, float) if self.masses else None,
                np.asarray(self.gravity, float) if self.gravity else None)
        unit = 1.0 if self.load_coef else self.load_scale  # the parameter is a deflection, or a compliance
        for i, k in enumerate(self.joints):  # the drive deflects, and the coupled rows it moves with it
            spring = hardening(load[:, k] / self.load_scale, self.stiffening) * unit
            b[:, :, i] = ctx.moves[None, :, k] * spring[:, None]
        how = "identified " if self.load_coef else ""
        return Basis(b, None, load[:, j],
                     f"{how}gravity load on {ctx.model.joint_names[j]} ({_load_unit(ctx.model, j)})")

    def label(self, model):
        return (super().label(model) + (" identified load" if self.load_coef else "")
                + (f" stiffening {self.stiffening:g}" if self.stiffening else "")
                + (" identified masses" if self.masses else ""))

    def explain(self, model):
        who = ", ".join(model.joint_names[j] for j in self.joints)
        one = len(self.joints) == 1
        how = " (its load identified from the data)" if self.load_coef else ""
        also = _followers(model, self.joints)
        if self.stiffening:
            return (f"{who} deflect{'s' if one else ''} under gravity and payload load, as a spring that stiffens with "
                    f"load{how}{also}")
        return (f"{who} deflect{'s' if one else ''} in proportion to {'its' if one else 'their'} gravity and payload "
                f"load{also}")


def gravity_across(g: np.ndarray) -> np.ndarray:
    """(2, 3) m/s^2: gravity of g's size (3,) along two orthonormal directions across g, what a base tilted about
    them adds per radian (loads and bending are linear in gravity)."""
    g = np.asarray(g, float)
    z = g / np.linalg.norm(g)
    a = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.linalg.norm(g) * np.stack([a, np.cross(z, a)])


@dataclass(frozen=True)
class TiltedCompliance(Effect):
    """dq_j = c_j * (load_j under gravity tilted by t): a spring on a joint whose load the model's gravity cannot
    compute, a vertical axis on a base that is not level (issue 34). The load is linear in gravity, so for a small
    tilt t (rad, about the two horizontal axes) it is c t_1 L_1 + c t_2 L_2, L_k the load gravity of the model's size
    would put on the joint along horizontal direction k (`gravity_across`): two parameters per joint, the compliance
    times each tilt component (their size, not the split between c and t, is what the data determine)."""

    kind = "joint_compliance"
    needs = "mass"
    masses: tuple = ()  # (n, 4) mass data identified from the data (kg, kg*mm), else the model's (gravity.py)
    gravity: tuple = ()  # (3,) m/s^2 in the base frame identified with the masses, else the model's

    def parameter_names(self, model):
        return [f"{model.joint_names[j]}.compliance_times_tilt_{a}" for j in self.joints for a in "uv"]

    def parameter_units(self, model):
        return [f"{_offset_unit(model, j)}/{_load_unit(model, j)}" for j in self.joints for _ in "uv"]

    def across(self, model) -> np.ndarray:
        """(2, 3) m/s^2: gravity_across the gravity this spring's tilt is measured from."""
        return gravity_across(np.asarray(self.gravity, float) if self.gravity else model.gravity)

    def basis(self, ctx: Context) -> Basis:
        phi = np.asarray(self.masses, float) if self.masses else None
        across = [loads(ctx.chain, ctx.meas, phi, g) for g in self.across(ctx.model)]
        N, n = ctx.meas.joints.shape
        b = np.zeros((N, n, 2 * len(self.joints)))
        for i, k in enumerate(self.joints):
            for a in range(2):
                b[:, :, 2 * i + a] = ctx.moves[None, :, k] * across[a][:, k, None]
        j = self.joints[0]
        return Basis(b, None, np.hypot(across[0][:, j], across[1][:, j]),
                     f"load gravity across the base would put on {ctx.model.joint_names[j]} "
                     f"({_load_unit(ctx.model, j)})")

    def label(self, model):
        return super().label(model) + " tilted base" + (" identified masses" if self.masses else "")

    def explain(self, model):
        who = ", ".join(model.joint_names[j] for j in self.joints)
        one = len(self.joints) == 1
        return (f"{who} deflect{'s' if one else ''} under the load a base that is not level puts on "
                f"{'its axis' if one else 'their axes'} (the model's gravity gives {'it' if one else 'them'} none)"
                f"{_followers(model, self.joints)}")


@dataclass(frozen=True)
class Backlash(Effect):
    """dq_j = b/2 * tanh(load_j / transition): the joint sits on one flank of its gear play or the other;
    near zero load it floats in the play (transition in N*m or N; 0 = a sharp switch). The load is the
    model's statics, or with `load_coef` the load identified from the data (gravity regressor columns
    and the payload column, see gravity.py), so the switch follows the real load when masses are off."""

    kind = "backlash"
    needs = "mass"
    transition: float = 0.0
    load_coef: tuple = ()
    search_dof: int = 0  # parameters spent finding the load from the residual (counted in the F-test)
    fitted_softness: bool = False  # the identified load is in units of the transition (its softness fitted)
    switch_width: float = 0.0  # 1-sigma of where the load really changes sign (load units; diagnose sets it)
    switch_draws: tuple = ()  # load_coef of the switch found again on resampled calibration poses (diagnose sets it)
    TRANSITION_SHARE = 0.02  # of the largest load in the calibration data

    def parameter_names(self, model):
        return [f"{model.joint_names[self.joints[0]]}.backlash"]

    def label(self, model):
        soft = " soft, fitted" if self.fitted_softness else (
            f" soft {self.transition:.2g}" if self.load_coef and self.transition > self.TRANSITION_SHARE else "")
        return super().label(model) + (" identified load" if self.load_coef else "") + soft

    def parameter_units(self, model):
        return [_offset_unit(model, self.joints[0])]

    def prior_stds(self, model):
        return PLAY_PRIOR_MM if model.prismatic[self.joints[0]] else PLAY_PRIOR_RAD

    def load(self, ctx: Context, coef: tuple | None = None) -> np.ndarray:
        """The load whose sign picks the flank, (N,): the model's statics, or the identified load (`coef`, by
        default load_coef)."""
        j = self.joints[0]
        coef = self.load_coef if coef is None else coef
        return identified_load(ctx, j, coef) if coef else ctx.loads[:, j]

    def flank(self, load: np.ndarray) -> np.ndarray:
        """Where in the play the joint sits at this load, -1 .. 1 (times b/2)."""
        return np.tanh(load / self.transition) if self.transition > 0 else np.sign(load)

    def flank_doubt(self, ctx: Context) -> np.ndarray:
        """(N,) mean square error of the flank factor from not knowing where the load really changes sign: the
        load off by N(0, switch_width^2) (mass data off), or the switches found on resampled poses (an identified
        load separates the calibration poses in many ways), whichever is the larger. 4 P for a sharp switch
        (P: the chance of the other flank); near zero load a soft one can miss either flank by half the play."""
        load = self.load(ctx)
        s = self.flank(load)
        out = np.zeros(len(load))
        if self.switch_width > 0 and self.transition > 0:
            x, w = LOAD_DOUBT
            out = w @ (self.flank(load + self.switch_width * x[:, None]) - s) ** 2
        elif self.switch_width > 0:
            out = 4.0 * special.ndtr(-np.abs(load) / self.switch_width)
        if self.switch_draws:
            drawn = np.mean([(self.flank(self.load(ctx, c)) - s) ** 2 for c in self.switch_draws], axis=0)
            out = np.maximum(out, drawn)
        return out

    def basis(self, ctx: Context) -> Basis:
        j = self.joints[0]
        load = self.load(ctx)
        N, n = ctx.meas.joints.shape
        how = "identified " if self.load_coef else ""
        return Basis(joint_basis(N, n, j, 0.5 * self.flank(load)[:, None], ctx.moves), None, load,
                     f"{how}gravity load on {ctx.model.joint_names[j]} ({_load_unit(ctx.model, j)})")

    def explain(self, model):
        how = " (its load identified from the data)" if self.load_coef else ""
        return (f"{model.joint_names[self.joints[0]]} shifts by its gear play when its load changes sign{how}"
                f"{_followers(model, self.joints)}")


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
        return Basis(joint_basis(N, n, j, cols, ctx.moves), None, np.degrees(q),
                     f"{ctx.model.joint_names[j]} angle (deg)")

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
        mid = 0.5 * (lo + hi) if np.isfinite(lo) and np.isfinite(hi) else 0.0
        N, n = ctx.meas.joints.shape
        unit = "mm" if ctx.model.prismatic[j] else "deg"
        reg = q if ctx.model.prismatic[j] else np.degrees(q)
        return Basis(joint_basis(N, n, j, (q - mid)[:, None], ctx.moves), None, reg,
                     f"{ctx.model.joint_names[j]} ({unit})")

    def explain(self, model):
        return f"{model.joint_names[self.joints[0]]} moves by a slightly different amount than it reports"
