"""Effects: the physical causes the diagnosis can name, each a plug-in with one shape (see base.py)."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..io import Measurements
from ..kinematics import Chain, nominal_vector
from ..statics import joint_loads
from ..model import RobotModel
from .base import Basis, Context, Effect, apply
from .cartesian_effects import AxisStraightness, LinkDeflection, ThermalDrift
from .joint_effects import Backlash, CyclicJointError, JointCompliance, JointScale
from .residual import ResidualField

KINDS = {c.kind: c for c in (JointCompliance, LinkDeflection, CyclicJointError, Backlash, JointScale,
                             AxisStraightness, ThermalDrift, ResidualField)}
HARMONICS = (1, 2, 3)


def candidates(model: RobotModel, meas: Measurements) -> tuple[list[Effect], list[str]]:
    """Every candidate the data can test, one per kind and joint (and harmonic), plus notes on what can't be."""
    out: list[Effect] = []
    notes: list[str] = []
    n = model.n_joints
    moving = [j for j in range(n) if np.ptp(meas.joints[:, j]) > 1e-3]  # rad or mm: a joint that moves
    if model.has_mass:
        # a joint's load can vary even where the joint stands still; a vertical axis carries none
        load = joint_loads(Chain(model, nominal_vector(model), meas.joints), meas.payload_kg())
        span = np.ptp(load, axis=0)
        loaded = [j for j in range(n) if span[j] > 1e-6 * max(span.max(), 1e-300)]
        out += [JointCompliance((j,)) for j in loaded]
        big = np.abs(load).max(axis=0)
        out += [Backlash((j,), transition=float(Backlash.TRANSITION_SHARE * big[j])) for j in loaded]
        out += [LinkDeflection((k,)) for k in range(1, n)]
    else:
        notes.append("the model has no masses: joint_compliance, backlash and link_deflection cannot be tested")
    out += [CyclicJointError((j,), h) for j in moving if not model.prismatic[j] for h in HARMONICS]
    out += [JointScale((j,)) for j in moving]
    out += [AxisStraightness((j,)) for j in moving if model.prismatic[j]]
    if meas.temperature is not None or meas.timestamp is not None:
        out.append(ThermalDrift.for_data(meas))
    else:
        notes.append("no timestamp or temperature column: thermal_drift cannot be tested")
    return out, notes


def effect_state(effect: Effect, values: np.ndarray) -> dict:
    """JSON-able form of an identified effect."""
    d = dataclasses.asdict(effect)
    d["joints"] = list(d["joints"])
    return {"kind": effect.kind, **d, "values": [float(v) for v in values]}


def effect_from_state(state: dict) -> tuple[Effect, np.ndarray]:
    d = dict(state)
    cls = KINDS[d.pop("kind")]
    values = np.array(d.pop("values"), float)
    d["joints"] = tuple(d["joints"])
    return cls(**d), values


__all__ = ["effect_state", "effect_from_state", "KINDS", "Basis", "Context", "Effect", "apply", "candidates", "AxisStraightness", "Backlash",
           "CyclicJointError", "JointCompliance", "JointScale", "LinkDeflection", "ThermalDrift"]
