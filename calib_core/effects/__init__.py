"""Effects: the physical causes the diagnosis can name, each a plug-in with one shape (see base.py)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..io import Measurements
from ..kinematics import Chain, nominal_vector
from ..model import ANGULAR, GEOMETRIC, RobotModel
from .base import Basis, Context, Effect, apply, has_loads, loads
from .cartesian_effects import (AxisStraightness, GuidedLinkDeflection, LinkDeflection, LinkGrowth,
                                RootTurnLinkDeflection, ThermalDrift, TiltedLinkDeflection)
from .gravity import LateralCompliance, LateralJointCompliance, LoadCompliance, MountCompliance
from .joint_effects import Backlash, CyclicJointError, JointCompliance, JointScale, TiltedCompliance, gravity_across
from .residual import ResidualField
from .structure import Probe, SessionStep, TargetStep

CLASSES = {c.__name__: c for c in (JointCompliance, LinkDeflection, CyclicJointError, Backlash, JointScale,
                                   AxisStraightness, ThermalDrift, ResidualField, LoadCompliance, LateralCompliance,
                                   LateralJointCompliance,
                                   SessionStep, Probe, TargetStep, LinkGrowth, TiltedCompliance,
                                   TiltedLinkDeflection, GuidedLinkDeflection, RootTurnLinkDeflection, MountCompliance)}
KINDS = {"joint_compliance": JointCompliance, "link_deflection": LinkDeflection, "cyclic_joint_error": CyclicJointError,
         "backlash": Backlash, "joint_scale": JointScale, "axis_straightness": AxisStraightness,
         "thermal_drift": ThermalDrift, "unexplained": ResidualField, "base_compliance": MountCompliance}
"""Kind -> class for states stored before the class name was (the contract's kinds are not unique per class)."""
HARMONICS = (1, 2, 3)
TILT_LOADED = 0.05
"""A vertical axis is a candidate for a spring under a tilted base when gravity across the base would load it by this
share of the most loaded joint's span, or more (a few degrees of tilt then show as a tenth of a degree's load)."""
LINK_GROWTH_SHARE = 0.1
"""A link is a candidate for growing with temperature when its lengths (a, d, b) reach this share of the longest's."""


def candidates(model: RobotModel, meas: Measurements) -> tuple[list[Effect], list[str]]:
    """Every candidate the data can test, one per kind and joint (and harmonic), plus notes on what can't be."""
    out: list[Effect] = []
    notes: list[str] = []
    n = model.n_joints
    moving = [j for j in range(n) if np.ptp(meas.joints[:, j]) > 1e-3]  # rad or mm: a joint that moves
    if has_loads(model, meas):
        # a joint's load can vary even where the joint stands still; a vertical axis carries none
        chain = Chain(model, nominal_vector(model, n_setups=meas.n_setups), meas.joints, None, meas.labels)
        load = loads(chain, meas)
        span = np.ptp(load, axis=0)
        loaded = [j for j in range(n) if span[j] > 1e-6 * max(span.max(), 1e-300) and model.moving[j]]
        out += [JointCompliance((j,)) for j in loaded]
        if model.has_mass and meas.tau is None:
            # a vertical axis carries a load only when the base is not level: its spring under a tilted gravity
            across = np.max([np.ptp(loads(chain, meas, None, g), axis=0) for g in gravity_across(model.gravity)],
                            axis=0)
            out += [TiltedCompliance((j,)) for j in range(n) if model.moving[j] and not model.prismatic[j]
                    and j not in loaded and across[j] > TILT_LOADED * max(span.max(), 1e-300)]
        if len(loaded) > 1:
            out.append(JointCompliance(tuple(loaded)))
        big = np.abs(load).max(axis=0)
        out += [Backlash((j,), transition=float(Backlash.TRANSITION_SHARE * big[j])) for j in loaded]
        if model.has_mass:
            out += [LinkDeflection((k,)) for k in range(1, n)]
            # a telescopic stage's tube also turns in its guide: a rival form of its bending (held-out parsimony)
            out += [GuidedLinkDeflection((k,)) for k in range(1, n) if model.prismatic[k] and model.moving[k]]
            # every bearing tilting under its bending moment at once (vertical axes carry one too)
            bent = [j for j in range(n) if model.moving[j] and model.mass[model.descendants(j)].sum() > 0]
            if len(bent) > 1:
                out.append(LateralJointCompliance.for_data(tuple(bent), Context(model, chain, meas)))
            # the mount tilting under the robot's overturning moment (a pedestal, a mobile platform)
            out.append(MountCompliance.for_data(Context(model, chain, meas)))
        else:
            notes.append("the model has no masses: a link's bending needs mass data and is not tested; the joints' "
                         "lateral compliance (link_deflection) is tested with the load identified from the data, the "
                         "measured torques drive the joint causes")
    else:
        notes.append("the model has no masses: gravity loads are identified from the data (joint_compliance, "
                     "backlash, and the joints' lateral compliance as link_deflection); a link's bending needs mass "
                     "data and is not tested")
    out += [CyclicJointError((j,), h) for j in moving if not model.prismatic[j] for h in HARMONICS]
    out += [JointScale((j,)) for j in moving]
    out += [AxisStraightness((j,)) for j in moving if model.prismatic[j]]
    if meas.temperature is not None or meas.timestamp is not None:
        out.append(ThermalDrift.for_data(meas))
    if meas.temperature is not None and np.ptp(meas.temperature) > 0:
        # one link growing along its length (a motor or the sun warming it): links of a tenth of the longest or more
        lengths = [GEOMETRIC.index(p) for p in GEOMETRIC if p not in ANGULAR]
        length = np.linalg.norm(np.asarray(model.geometry, float)[:, lengths], axis=1)
        out += [LinkGrowth.for_link(meas, k) for k in range(n) if length[k] >= LINK_GROWTH_SHARE * length.max() > 0]
    else:
        notes.append("no timestamp or temperature column: thermal_drift cannot be tested")
    return out, notes


def on_joints(effect: Effect, joints) -> Effect:
    """The same form of a cause on some of its joints (a compliance of several joints on the ones that carry a share):
    each joint keeps what it has of its own (an identified load's mix)."""
    joints = tuple(joints)
    if isinstance(effect, LoadCompliance):
        mix = dict(zip(effect.joints, effect.load_mix))
        return dataclasses.replace(effect, joints=joints, load_mix=tuple(mix[j] for j in joints))
    return dataclasses.replace(effect, joints=joints)


def effect_state(effect: Effect, values: np.ndarray) -> dict:
    """JSON-able form of an identified effect."""
    d = dataclasses.asdict(effect)
    d["joints"] = list(d["joints"])
    return {"kind": effect.kind, "class": type(effect).__name__, **d, "values": [float(v) for v in values]}


def _frozen(v):
    """JSON lists back to the tuples a frozen effect holds."""
    return tuple(_frozen(x) for x in v) if isinstance(v, (list, tuple)) else v


def effect_from_state(state: dict) -> tuple[Effect, np.ndarray]:
    d = dict(state)
    kind = d.pop("kind")
    cls = CLASSES[d.pop("class")] if "class" in d else KINDS[kind]
    values = np.array(d.pop("values"), float)
    return cls(**{k: _frozen(v) for k, v in d.items()}), values


__all__ = ["effect_state", "on_joints", "effect_from_state", "CLASSES", "KINDS", "LateralCompliance", "LateralJointCompliance", "LoadCompliance", "Probe", "SessionStep", "TargetStep", "Basis", "Context", "Effect", "apply", "candidates", "AxisStraightness", "Backlash",
           "CyclicJointError", "JointCompliance", "JointScale", "LinkDeflection", "LinkGrowth", "ThermalDrift",
           "TiltedCompliance", "TiltedLinkDeflection", "GuidedLinkDeflection",
           "RootTurnLinkDeflection", "MountCompliance"]
