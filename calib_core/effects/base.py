"""The one shape of every effect: named parameters and a pose-dependent basis that is linear in them.

An effect adds joint offsets dq = Phi_q @ theta (N, n) and/or a Cartesian displacement
dp = Phi_p @ theta (N, 3, measurement frame, mm). Identification stacks J_q Phi_q + Phi_p beside the
geometric Jacobian (the rigid-flexible coupled Jacobian of Wang et al. 2023, section 5.2); the twin
uses the same objects with hidden values to make data; compensation includes whatever was found.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..io import Measurements
from ..kinematics import Chain
from ..model import RobotModel
from ..statics import joint_loads


@dataclass
class Context:
    """What an effect may look at: the model, the poses' kinematic chain and the measurement columns."""

    model: RobotModel
    chain: Chain
    meas: Measurements
    _bases: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def at(cls, model: RobotModel, x: np.ndarray, meas: Measurements, R0: np.ndarray | None = None) -> Context:
        """The context of these poses at geometry x, one object for the same model, poses, x and R0 among the last
        CONTEXTS asked (with the bases made in it): a diagnosis screens, fits and refits the same candidates at one
        reference geometry many times (Agile Justin: 3056 bases asked for, 1363 distinct)."""
        # the poses and the columns effects read by value too: a Measurements' arrays can be written in place (a
        # temperature changed between two predictions on one object gave the first prediction again)
        key = (np.asarray(x, float).tobytes(), None if R0 is None else np.asarray(R0, float).tobytes(),
               meas.joints.tobytes(), *(None if (a := getattr(meas, c)) is None else np.asarray(a).tobytes()
                                        for c in _READ_COLUMNS))
        with _CONTEXTS_LOCK:  # a service without compute processes predicts in several route threads
            for i, (m, q, k, ctx) in enumerate(_CONTEXTS):
                if m is model and q is meas and k == key:
                    _CONTEXTS.append(_CONTEXTS.pop(i))  # the most recently used last
                    return ctx
        ctx = cls(model, Chain(model, np.array(x, float), meas.joints, R0, meas.labels), meas)
        with _CONTEXTS_LOCK:
            _CONTEXTS.append((model, meas, key, ctx))
            del _CONTEXTS[:-CONTEXTS]
        return ctx

    def basis(self, e: Effect) -> Basis:
        """e.basis(self), made once per effect object (read-only: the same arrays are handed out again)."""
        hit = self.made(e)
        return hit if hit is not None else self.keep(e, e.basis(self))

    def made(self, e: Effect) -> Basis | None:
        """e's basis if this context has made it (or kept it), else None."""
        hit = self._bases.get(id(e))
        return hit[1] if hit is not None and hit[0] is e else None

    def keep(self, e: Effect, b: Basis) -> Basis:
        """Keep b as e's basis here (one made in a worker process, parallel.pmap), read-only."""
        for a in (b.joint, b.cart, b.regressor):
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
        self._bases[id(e)] = (e, b)
        return b

    @cached_property
    def loads(self) -> np.ndarray:
        """Load on every joint, (N, n), N*m or N: the measured torques where the CSV has tau_<joint>, else the
        gravity + payload load of the model's statics."""
        return loads(self.chain, self.meas)

    @cached_property
    def moves(self) -> np.ndarray:
        """(n, n) RobotModel.drive_motion: column j, the rows a unit motion of joint j's drive moves."""
        return self.model.drive_motion()


_READ_COLUMNS = ("temperature", "timestamp", "sequence", "payload", "tau", "target", "setup")
"""The per-pose columns besides the joints that effects or the chain read (Context.at keys on their values)."""
CONTEXTS = 4
"""Contexts kept by Context.at: a round's reference geometry, the one its revisits screen at, and two spare."""
_CONTEXTS: list[tuple] = []
_CONTEXTS_LOCK = threading.Lock()


def has_loads(model: RobotModel, meas: Measurements) -> bool:
    """Load-driven causes can be tested: the model has masses or the data carry measured joint torques."""
    return model.has_mass or meas.tau is not None


def loads(chain: Chain, meas: Measurements, phi: np.ndarray | None = None, g: np.ndarray | None = None) -> np.ndarray:
    """(N, n) N*m or N: the load on each joint's drive.  A measured joint torque tau (tau_<joint>, what the joint
    applies to hold the arm) is the gravity load's opposite, so the load is -tau; joints without a measured torque
    take the statics of the model's mass data or of `phi` (identified ones, see statics.distal_loads), under the
    model's gravity or `g` (identified, see statics.gravity_world); zero when there are none. The drive of an
    actuated joint that coupled rows follow carries their loads too, by their coefficients (virtual work:
    drive_motion' times the rows' loads): on Agile Justin's torso T2's drive holds T2's load minus T4c's."""
    model = chain.model
    out = (joint_loads(chain, meas.payload_kg(), phi, g) @ model.drive_motion() if model.has_mass or phi is not None
           else np.zeros((chain.N, model.n_joints)))
    if meas.tau is not None:
        given = ~np.isnan(meas.tau)
        out = np.where(given, -np.nan_to_num(meas.tau), out)
    return out


def rows_said(rows: np.ndarray) -> str:
    """How a note names a request's rows (0-based): "row 3", "rows 0, 2, 5", the first ten then "..."."""
    return f"row{'s' * (len(rows) > 1)} {', '.join(map(str, rows[:10]))}{' ...' if len(rows) > 10 else ''}"


def unloaded(model: RobotModel, effects, meas: Measurements) -> list[str]:
    """Sentences naming each identified cause that reads a joint's load (N*m or N) where the model has no masses
    and a row gives no tau_<joint>: there it acts as zero load (predict / compensate say so, never silently)."""
    if model.has_mass:
        return []
    out = []
    for e in effects:
        if e.needs != "mass" or getattr(e, "load_coef", ()) or getattr(e, "masses", ()):
            continue  # a cause that needs no load, or carries its own (identified load or masses)
        for j in e.joints:
            rows = np.arange(meas.n_poses) if meas.tau is None else np.flatnonzero(np.isnan(meas.tau[:, j]))
            if rows.size:
                name = model.joint_names[j]
                which = "every row" if rows.size == meas.n_poses else rows_said(rows)
                out.append(f"{e.label(model)} needs the load on {name}: the model has no masses and {which} gave no "
                           f"tau_{name}, so there it acts as zero load; give tau_{name} (N*m or N, as in the CSV)")
    return out


@dataclass(frozen=True)
class Basis:
    joint: np.ndarray | None  # (N, n, k) joint offset per unit parameter (rad or mm)
    cart: np.ndarray | None  # (N, 3, k) displacement per unit parameter, mm, measurement frame
    regressor: np.ndarray  # (N,) the per-pose quantity the effect follows (for evidence and plots)
    regressor_label: str

    def dense(self, n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(joint (N, n, k), cart (N, 3, k)): a part the effect does not have is zeros."""
        N = len(next(a for a in (self.joint, self.cart, self.regressor) if a is not None))
        return (np.zeros((N, n, k)) if self.joint is None else self.joint,
                np.zeros((N, 3, k)) if self.cart is None else self.cart)


@dataclass(frozen=True)
class Effect:
    """A candidate cause acting on `joints` (model joint indices); subclasses set kind and the basis."""

    joints: tuple[int, ...]
    harmonic: int | None = field(default=None)
    kind = "effect"
    needs = "nothing"
    bounded = True  # a real play, spring or bearing moves a joint by a fraction of a degree (findings._judge_sizes)
    fixed_columns = False  # its Jacobian's columns are its Cartesian basis alone, the same at every step of a fit

    def label(self, model: RobotModel) -> str:
        names = ",".join(model.joint_names[j] for j in self.joints) or "robot"
        return f"{self.kind}[{names}{'' if self.harmonic is None else f', h{self.harmonic}'}]"

    def parameter_names(self, model: RobotModel) -> list[str]:
        raise NotImplementedError

    def parameter_units(self, model: RobotModel) -> list[str]:
        raise NotImplementedError

    def prior_stds(self, model: RobotModel) -> np.ndarray | float:
        """Ridge prior std of the parameters toward zero, in their units (inf: none): `prior_std` where the effect
        carries one."""
        return getattr(self, "prior_std", np.inf)

    def basis(self, ctx: Context) -> Basis:
        raise NotImplementedError

    def explain(self, model: RobotModel) -> str:
        """One phrase a process engineer can read."""
        raise NotImplementedError

    def turns(self, ctx: Context, values: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """How far the effect turns (rad) or moves (mm, a prismatic joint) each joint it acts on at each pose:
        [(joint, (N,))]; joint -1 for the whole robot turning on its mount; [] for an effect that is not a joint's
        motion (a field, a step of the whole robot)."""
        b = self.basis(ctx)
        if b.joint is None:
            return []
        dq = b.joint @ values
        return [(j, dq[:, j]) for j in self.joints]


def joint_basis(n_poses: int, n_joints: int, j: int, columns: np.ndarray,
                moves: np.ndarray | None = None) -> np.ndarray:
    """(N, n, k) basis with the k columns (N, k) acting on joint j's drive: on row j only, or with `moves`
    (Context.moves) on every row that drive moves."""
    if moves is None:
        out = np.zeros((n_poses, n_joints, columns.shape[1]))
        out[:, j, :] = columns
        return out
    return moves[None, :, j, None] * columns[:, None, :]


def apply(effects: list[Effect], values: list[np.ndarray], ctx: Context) -> tuple[np.ndarray, np.ndarray]:
    """Total joint offsets (N, n) and displacement (N, 3) of effects with the given parameter values."""
    N, n = ctx.meas.joints.shape
    dq, dp = np.zeros((N, n)), np.zeros((N, 3))
    for e, v in zip(effects, values):
        b = ctx.basis(e)
        if b.joint is not None:
            dq += b.joint @ v
        if b.cart is not None:
            dp += b.cart @ v
    return dq, dp
