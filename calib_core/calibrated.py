"""What a calibration leaves behind for prediction and compensation (CalibratedRobot) and how its stored state is
read back: today's parameter layout from older states, and states whose causes would now predict otherwise refused."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from . import kinematics as K
from .effects import (Backlash, Context, CyclicJointError, Effect, JointCompliance, JointScale, LoadCompliance, apply,
                      effect_from_state, effect_state)
from .effects.base import unloaded
from .effects.cartesian_effects import held_at_edge
from .io import Measurements
from .model import MDH, RobotModel

ON_DRIVES = "joint_causes_on_drives"
"""Marker of a state saved since a joint-space cause on a coupled mechanism acts on its drive (docs/REAL_CELLS.md)."""
COMPLETE_ROWS = "geometry_per_row"
"""Key of a state's geometric parameters per row (len(GEOMETRIC)); a state without it was saved with the 5 classic
MD-H parameters per row, before gamma and b: restored with those two at 0, it predicts exactly as before."""


def state_vector(model: RobotModel, state: dict, key: str = "x") -> np.ndarray | None:
    """A stored state's parameter vector (`x` or `x_basis`) in today's layout: a state saved with 5 parameters per
    row (no COMPLETE_ROWS key; its length says so, its setups being known) gets gamma = b = 0 inserted (the same
    kinematics, to the bit)."""
    v = state.get(key)
    if v is None:
        return None
    v = np.array(v, float)
    n, S = model.n_joints, len(state.get("setup_names", ("",)))
    per_row = int(state.get(COMPLETE_ROWS, (len(v) - 6 * S - 3 * model.n_targets) // n))
    if per_row == len(MDH):
        g = np.zeros((n, K.G))
        g[:, :per_row] = v[: per_row * n].reshape(n, per_row)
        v = np.concatenate([g.ravel(), v[per_row * n:]])
    return v


class StaleState(ValueError):
    """A stored calibration whose causes would now predict differently than when they were identified."""


def _stale(model: RobotModel, effects: list[Effect]) -> str | None:
    """The rows whose joint-space cause, saved before it acted on the drive, would now turn coupled rows too."""
    rows = sorted({j for e in effects if isinstance(e, (JointCompliance, Backlash, CyclicJointError, JointScale,
                                                        LoadCompliance))
                   for j in e.joints if len(model.followers(j))})
    return ", ".join(model.joint_names[j] for j in rows) or None


@dataclass(frozen=True, eq=False)
class CalibratedRobot:
    """What a calibration leaves behind for prediction and compensation: model, parameters, effects."""

    model: RobotModel
    x: np.ndarray  # full geometric parameter vector, mm / rad
    R0: np.ndarray  # base reference rotation
    effects: tuple[Effect, ...] = ()
    effect_values: tuple[np.ndarray, ...] = ()
    x_basis: np.ndarray | None = None  # the geometry the effect bases were fitted on (default: x)
    setup_names: tuple[str, ...] = ("",)  # one base pose per setup, in this order

    @property
    def basis_x(self) -> np.ndarray:
        """The geometry the effect bases were evaluated on: x_basis where there is one, else x (mm, rad)."""
        return self.x if self.x_basis is None else self.x_basis

    def effect_offsets(self, joints: np.ndarray, columns: Measurements | None = None):
        """Joint offsets (N, n) and displacements (N, 3) mm of the identified effects at these joints, with
        the bases on the geometry they were fitted on (so a prediction is the fitted model, exactly)."""
        meas = columns if columns is not None and joints is columns.joints else _columns(joints, columns)
        ctx = Context.at(self.model, self.basis_x, meas, self.R0)
        return apply(list(self.effects), list(self.effect_values), ctx)

    def chain(self, joints: np.ndarray, columns: Measurements | None = None) -> tuple[K.Chain, np.ndarray | float]:
        """The chain a prediction runs on (the calibrated geometry at the joints plus the effects' offsets) and the
        effects' displacements (N, 3) mm (0 without effects): chain.p + dp is `predict`, and its Jacobians are the
        derivatives of the prediction."""
        labels = None if columns is None else columns.labels
        dq, dp = self.effect_offsets(joints, columns) if self.effects else (0.0, 0.0)
        return K.Chain(self.model, self.x, joints + dq, self.R0, labels), dp

    def predict(self, joints: np.ndarray, columns: Measurements | None = None) -> np.ndarray:
        """Measured point (N, 3) mm in the measurement frame for row values (N, n) in internal units.

        `columns` carries each pose's target and setup (model.expand_joints makes rows of actuated joints) and payload / temperature / timestamp where effects need them (else nominal: 0 kg,
        the calibration's mean temperature and time)."""
        joints = np.atleast_2d(np.asarray(joints, float))
        labels = None if columns is None else columns.labels
        if not self.effects:
            return K.forward(self.model, self.x, joints, self.R0, labels)
        dq, dp = self.effect_offsets(joints, columns)
        return K.forward(self.model, self.x, joints + dq, self.R0, labels) + dp

    def notes(self, columns: Measurements) -> list[str]:
        """What a prediction at these rows cannot take into account, in sentences (predict and compensate answer
        them): a load-driven cause without a load, a thermal drift beyond the temperatures or times it was fitted on."""
        return unloaded(self.model, self.effects, columns) + held_at_edge(self.effects, columns)

    def to_state(self) -> dict:
        """JSON-able state; `from_state(model, state)` restores it exactly."""
        out = {"x": self.x.tolist(), "R0": self.R0.tolist(),
               "effects": [effect_state(e, v) for e, v in zip(self.effects, self.effect_values)], ON_DRIVES: True,
               COMPLETE_ROWS: K.G}
        if self.x_basis is not None:
            out["x_basis"] = self.x_basis.tolist()
        if len(self.setup_names) > 1:
            out["setup_names"] = list(self.setup_names)
        return out

    @classmethod
    def from_state(cls, model: RobotModel, state: dict) -> "CalibratedRobot":
        """Raises StaleState for a state saved before a cause on a coupled mechanism acted on its drive, whose
        causes sit on such a drive: restored now, it would predict otherwise than it was fitted."""
        effects = [effect_from_state(d) for d in state.get("effects", [])]
        stale = None if state.get(ON_DRIVES) else _stale(model, [e for e, _ in effects])
        if stale:
            raise StaleState(f"this calibration was identified before a cause on a coupled mechanism acted on its "
                             f"drive; its causes on {stale} would now also turn the coupled rows and predict "
                             "otherwise than they were fitted: run the calibration job again")
        return cls(model, state_vector(model, state), np.array(state["R0"], float),
                   tuple(e for e, _ in effects), tuple(v for _, v in effects),
                   state_vector(model, state, "x_basis"), tuple(state.get("setup_names", ("",))))


def _columns(joints: np.ndarray, columns: Measurements | None) -> Measurements:
    """The measurement columns effects may need (payload, temperature, time), at these joints."""
    if columns is not None:
        return dataclasses.replace(columns, joints=joints)
    return Measurements(joints=joints, points=np.zeros((len(joints), 3)))
