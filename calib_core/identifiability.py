"""Which parameters the actual pose set can identify, which are redundant (and with what), which do nothing.

Column-normalised identification Jacobian, rank by SVD, then a greedy pivoted Gram-Schmidt in a
preference order: base pose first (always unknown), then tool, then a, alpha, d, theta of every joint
in chain order, then beta, so that beta enters only where it is needed, which is at
parallel axes (Hayati; Wang et al. 2023, section 4.2: beta instead of d), and the completing pair gamma, b
last (model.GEOMETRIC): a complete set per row, pruned here to a minimal one. A row given as xyz/rpy/axis (or
fixed) offers its six constants together in its own place instead (`model_order`).

`assess` adds what the pose set lacks: the parameters the model's structure can identify (on a rich random
pose set within the joint limits, cached per model geometry) but this pose set cannot, and the joints that
never moved.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

NONFUNCTIONAL_TOL = 1e-9
"""A column whose norm is below this fraction of the largest has no effect on the measured point."""
REDUNDANT_TOL = 1e-3
"""A normalised column whose part orthogonal to the kept ones is below this is redundant: the pose set
cannot tell it from the kept ones (their condition number would pass ~1e3)."""
FROZEN_SPAN = 1e-3
"""A joint whose values span less than this (rad or mm) never moved: its geometry cannot be identified."""
STRUCTURAL_POSES = 400
"""Size of the rich random pose set (seed 0, like the twin's identifiable_mask) that defines what the model's
structure can identify."""


@dataclass(frozen=True)
class Identifiability:
    names: list[str]
    identifiable: list[int]  # indices into the full vector, in selection order
    redundant: dict[int, list[int]]  # rejected index -> the kept indices it is confounded with
    nonfunctional: list[int]
    rank: int
    condition_number: float  # of the column-normalised Jacobian of the identifiable set
    observability_index: float  # Borm & Menq O1 = (prod sigma)^(1/p) / sqrt(m), normalised columns
    singular_values: np.ndarray
    unidentifiable: list[int] = field(default_factory=list)  # structurally identifiable, not by this pose set
    frozen_joints: list[str] = field(default_factory=list)  # joints whose values span < FROZEN_SPAN
    complete: bool = True  # the pose set identifies everything the model's structure can

    def warnings(self) -> list[str]:
        """Plain sentences on what this pose set cannot tell (empty when complete)."""
        out = []
        f = self.frozen_joints
        if f:
            who = ", ".join(f)
            out.append(f"{who} never moved: {'their' if len(f) > 1 else 'its'} geometry cannot be identified and "
                       "predictions are valid only near the measured poses")
        u = [self.names[i] for i in self.unidentifiable]
        if u:
            shown = ", ".join(u[:12]) + (f" and {len(u) - 12} more" if len(u) > 12 else "")
            out.append(f"{len(u)} parameter{'s' if len(u) > 1 else ''} cannot be identified from this pose set: "
                       f"{shown}; {'they are' if len(u) > 1 else 'it is'} left at nominal and predictions "
                       "away from the measured poses inherit the error; measure poses that move every joint "
                       "over its range")
        return out

    def to_dict(self) -> dict:
        n = self.names
        return {
            "rank": self.rank,
            "n_parameters": len(n),
            "identifiable": [n[i] for i in self.identifiable],
            "redundant": [{"name": n[i], "confounded_with": [n[k] for k in ks]} for i, ks in self.redundant.items()],
            "nonfunctional": [n[i] for i in self.nonfunctional],
            "condition_number": self.condition_number,
            "observability_index": self.observability_index,
            "unidentifiable": [n[i] for i in self.unidentifiable],
            "frozen_joints": list(self.frozen_joints),
            "complete": self.complete,
        }


def model_order(model, names: list[str]) -> list[int]:
    """preference_order, except that a row given as xyz/rpy/axis (or fixed) offers its six constants together, in
    its own row's place: the shifts across its axis (a, b), the turns (alpha, gamma, theta), and the shift along its
    axis (d) last, the one the next row most often says as well. They are the turns and shifts of one frame at its
    own origin, none more natural than another; with gamma and b late and d early, Talos's left arm kept d where b
    was needed a little off nominal, and a 0.3 mm shift of arm_left_2's origin left 0.1 mm that no fit removed."""
    if model.pre is None:
        return preference_order(names)
    general = {model.joint_names[j] for j in range(model.n_joints)
               if not np.array_equal(model.pre[j], np.eye(4)) or model.is_fixed[j]}
    order = preference_order(names)
    own = lambda i: names[i].rsplit(".", 1)  # noqa: E731
    rank = {"a": 0, "b": 1, "alpha": 2, "gamma": 3, "theta": 4, "d": 5}  # shifts across the axis, turns, then along
    out, held = [], {}
    for i in order:
        row, p = own(i)
        if row in general and p in rank:
            held.setdefault(row, []).append(i)
            if len(held[row]) == len(rank):
                out += sorted(held.pop(row), key=lambda k: rank[own(k)[1]])
        else:
            out.append(i)
    return out + [k for ks in held.values() for k in ks]


def preference_order(names: list[str]) -> list[int]:
    """Base(s), target point(s), then the classic MD-H parameters in row order, every beta after them and every
    gamma and b (the completing pair, model.GEOMETRIC) last: a plain MD-H chain keeps exactly its classic set, and
    the pair enters only where nothing before it can say the same (an xyz/rpy row, a tree's second branch)."""
    reg = ("base.", "base[", "tool.", "tool[")  # one base per setup, one point per target
    base = [i for i, s in enumerate(names) if s.startswith(reg[:2])]
    tool = [i for i, s in enumerate(names) if s.startswith(reg[2:])]
    rows = [i for i, s in enumerate(names) if not s.startswith(reg)]
    late = (".beta", ".gamma", ".b")
    joint = [i for i in rows if not names[i].endswith(late)]
    beta = [i for i in rows if names[i].endswith(".beta")]
    pair = [i for i in rows if names[i].endswith((".gamma", ".b"))]
    return base + tool + joint + beta + pair


def analyse(J: np.ndarray, names: list[str], order: list[int] | None = None) -> Identifiability:
    """Identifiability of the parameters from the stacked Jacobian J (m, P) of the real pose set."""
    m, P = J.shape
    norms = np.linalg.norm(J, axis=0)
    nonfunctional = [i for i in range(P) if norms[i] <= NONFUNCTIONAL_TOL * norms.max()]
    A = J / np.where(norms > 0, norms, 1.0)
    order = preference_order(names) if order is None else order
    basis = np.empty((m, P))
    kept: list[int] = []
    rejected: list[int] = []
    for i in order:
        if i in nonfunctional:
            continue
        Q = basis[:, : len(kept)]
        v = A[:, i]
        for _ in range(2):  # re-orthogonalise once: classical Gram-Schmidt twice is stable
            v = v - Q @ (Q.T @ v)
        norm = np.linalg.norm(v)
        if norm > REDUNDANT_TOL:
            basis[:, len(kept)] = v / norm
            kept.append(i)
        else:
            rejected.append(i)
    G = A.T @ A  # the small Gram matrix serves the rest: partners and singular values
    redundant = {}
    if rejected:
        coef = np.linalg.solve(G[np.ix_(kept, kept)], G[np.ix_(kept, rejected)])
        for k, i in enumerate(rejected):
            c = np.abs(coef[:, k])
            redundant[i] = [kept[j] for j in np.argsort(-c) if c[j] > 0.05 * c.max()]
    s = np.sqrt(np.clip(np.linalg.eigvalsh(G[np.ix_(kept, kept)])[::-1], 0.0, None)) if kept else np.zeros(0)
    return Identifiability(
        names=names, identifiable=kept, redundant=redundant, nonfunctional=nonfunctional, rank=len(kept),
        condition_number=float(s[0] / s[-1]) if len(s) and s[-1] > 0 else float("inf"),
        observability_index=float(np.exp(np.log(s).mean()) / np.sqrt(m)) if len(s) and s[-1] > 0 else 0.0,
        singular_values=s,
    )


_STRUCTURAL: dict[bytes, Identifiability] = {}


def _geometry_key(model, n_setups: int) -> bytes:
    parts = [model.geometry, model.prismatic.astype(float), model.limits, model.target_points, model.parents,
             model.is_fixed, model.target_rows] + ([model.pre] if model.pre is not None else [])
    return (b"|".join(np.ascontiguousarray(a, float).tobytes() for a in parts)
            + repr((model.joint_names, model.coupling, n_setups)).encode())


def structural(model, setups: tuple[str, ...] = ("",)) -> Identifiability:
    """What the model's structure can identify: the analysis on a rich random pose set within the limits, every
    target and setup in turn (cached per model geometry: the diagnosis identifies the same model dozens of times)."""
    key = _geometry_key(model, len(setups))
    hit = _STRUCTURAL.get(key)
    if hit is None:
        from . import kinematics as K
        from .twin import sample_uniform  # lazy: the twin imports this module

        N, S = STRUCTURAL_POSES * len(setups), len(setups)
        q = sample_uniform(model, N, np.random.default_rng(0))
        x = K.nominal_vector(model, n_setups=S)
        labels = K.Labels(np.arange(N) % model.n_targets, (np.arange(N) // model.n_targets) % S)
        J = K.Chain(model, x, q, np.broadcast_to(np.eye(3), (S, 3, 3)), labels).jacobian()
        names = K.parameter_names(model, setups)
        hit = analyse(J.reshape(-1, len(x)), names, model_order(model, names))
        if len(_STRUCTURAL) > 256:
            _STRUCTURAL.clear()
        _STRUCTURAL[key] = hit
    return hit


def frozen_joints(model, joints: np.ndarray) -> list[str]:
    """Names of the joints (actuated or coupled) whose values span less than FROZEN_SPAN (rad or mm) over the pose set."""
    q = np.atleast_2d(np.asarray(joints, float))
    span = q.max(0) - q.min(0) if len(q) else np.zeros(model.n_joints)
    return [model.joint_names[j] for j in np.flatnonzero((span < FROZEN_SPAN) & model.moving)]


def assess(model, joints: np.ndarray, J: np.ndarray, names: list[str], setups: tuple[str, ...] = ("",)
           ) -> Identifiability:
    """`analyse` of the real pose set (joints (N, n), Jacobian J (3N, P)) plus what it lacks against the
    model's structure: `unidentifiable`, `frozen_joints` and `complete`."""
    ident = analyse(J, names, model_order(model, names))
    ref = structural(model, setups)
    have = set(ident.identifiable)
    missing = [i for i in ref.identifiable if i not in have]
    frozen = frozen_joints(model, joints)
    return dataclasses.replace(ident, unidentifiable=missing, frozen_joints=frozen,
                               complete=not missing and not frozen)
