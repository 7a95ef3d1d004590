"""Which poses to measure: D-optimal poses for the geometry, T-optimal poses to tell look-alike causes apart.

Candidates are drawn within the joint limits (5 % of each range kept clear), half uniformly, half limit-biased
(every joint from the arcsine law over its range, `candidate_joints`: D-optimal designs want poses near the
limits), and kept only where the tracker can be expected to see the target (`visible_pool`). Then one greedy
pass picks poses one at a time with rank-one (here rank-three: a pose is three equations) updates, O(candidates x
parameters) per pick, starting from what a measured set already holds when one is given; a `geometric` plan then
runs Fedorov's exchange (each chosen pose swapped for the candidate that raises the criterion most, while one
does, at most EXCHANGE_PASSES sweeps):

- `geometric`: D-optimal. Each pick maximises log det of the information matrix M = sum_k A_k^T A_k of the
  structurally identifiable geometric parameters (`identifiability.structural`), rows weighted by the
  instrument's noise at the tracker distance, columns scaled by their RMS over the candidates. D-optimal
  because it minimises the volume of the parameters' confidence ellipsoid (all parameters at once, not the
  worst one like the condition number), because it does not depend on the units or scaling of the parameters
  (mm and rad mixed: det(D M D) = det(D)^2 det(M), so the chosen set is the same for any column scaling),
  and because adding pose i multiplies det(M) by det(I + A_i M^-1 A_i^T): one 3x3 determinant per
  candidate and pick. The observability index O1 of Borm & Menq is det(M)^(1/2p) / sqrt(m) on normalised
  columns, so D-optimal poses also raise O1. When the model has masses, LOAD_WEIGHT of the criterion goes to
  the information on a compliance per loaded joint (joint deflection = c x gravity load) left after the
  geometry: the loads then vary independently of the geometry too (load variety for the gravity causes).
- `diagnosis`: T-optimal (Atkinson & Fedorov 1975). For two rival models A and B (not `nested`), each fitted
  to the measured set, the criterion of a set of new poses is the increase of B's weighted residual sum of squares
  when the data follow A and B is refitted to the old and new poses together (linearised in B's parameters),
  and the same with the roles swapped; the greedy pass maximises the smaller of the two (maximin over every
  rival pair). The gain of pose i is r_i^T (I + S_i)^-1 r_i, with r_i the held-out difference at pose i
  between A's prediction and B refitted to the poses so far (in noise sigmas) and S_i = J_i M^-1 J_i^T the
  share of it that refitting with pose i absorbs: the expected held-out difference between the rivals.

Visibility (a documented simple rule, no occlusion by the robot's own links): the tracker stands at
`tracker_mm` in the robot base frame (default: 3 m from the centre of the candidates' target points, level
with it, across the thinnest horizontal extent of the workspace, on the side the arm reaches toward, or another
side if few targets face that one; `tracker_of` places it where a calibrated set was measured from), and a
target is visible when the angle between its outward direction and its line of sight to the tracker is at
most `max_incidence_deg` (default 60). A target's outward direction is from the origin of the frame it is fixed to
through the target (an SMR on a tool sticks out along the tool), or that frame's z axis for a target at the
origin.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kinematics as K
from .diagnosis import INDISTINGUISHABLE
from .effects import Effect, candidates as effect_candidates
from .identifiability import analyse, structural
from .identify import CalibratedRobot, Calibration, identify
from .instruments import instrument
from .io import Measurements
from .model import RobotModel
from .statics import joint_loads
from .twin import sample_uniform
from .uncertainty import prediction_jacobian

PURPOSES = ("geometric", "diagnosis")
CANDIDATES = 20000
"""Candidate poses drawn within the joint limits (before the visibility rule)."""
TRACKER_DISTANCE_MM = 3000.0
"""Default distance of the tracker from the centre of the workspace."""
MAX_INCIDENCE_DEG = 60.0
"""Default largest angle between a target's outward direction and its line of sight to the tracker."""
MIN_FACING = 0.1
"""The default tracker moves to another side of the workspace when fewer than this share of the targets face it."""
REPEATABILITY_MM = 0.02
"""Per-axis robot repeatability added to the instrument's noise when weighting poses (ISO 9283 RP, as the
diagnosis assumes without repeated poses)."""
LOAD_WEIGHT = 0.2
"""Share of the geometric plan's criterion given to the compliances of the loaded joints (load variety): on
spray7 it raises their information (1 / std, given the geometry) by about a quarter over geometry-only
D-optimal poses for a predicted loss of geometric accuracy under 1 % (measured on the independent world:
0 to 8 %, docs/RESULTS.md); plain D-optimal over both (weight 1) loses about 20 %."""
LOADED_SHARE = 0.05
"""A joint whose gravity load varies by less than this share of the most loaded joint's carries no compliance
column (a vertical axis)."""
RIDGE = 1e-6
"""Information every parameter starts with (scaled columns: a pose carries about 1 per parameter), so that the
first picks, before the set identifies everything, are defined."""
MAX_RIVAL_PAIRS = 4
EXTREME_SHARE = 0.5
"""Share of the candidates drawn limit-biased (`candidate_joints`): D-optimal designs want poses near the joint
limits, which uniform draws rarely give."""
MARGIN = 0.05
"""Share of each joint range kept clear at both ends by every candidate (as `twin.sample_uniform`)."""
EXCHANGE_PASSES = 3
"""Passes of the exchange step after the greedy pass (each tries to swap every chosen pose for a better
candidate); 0 turns it off."""
EXCHANGE_BUDGET = 300
"""At most this many chosen poses are tried for a swap in all (3 passes over 100 poses): a pass over 1000 poses costs
about what the greedy pass does (10 s on one core), and a plan that large is already near its optimum after the greedy
pass. `POST /robots/{id}/plan` answers synchronously: 1000 poses took 30 s before the budget, 12 s with it."""
EXCHANGE_TOL = 1e-6
"""A swap is made when it raises the criterion (log det, per the combined weights) by more than this."""


@dataclass
class Plan:
    """Poses to measure, in internal units, and what they are expected to identify."""

    joints: np.ndarray  # (n, n_act) rad / mm, the actuated joints in model order
    observability: dict
    target: np.ndarray | None = None  # (n,) index into model.target_names; None: one target
    payload: np.ndarray | None = None  # (n,) kg to carry at each pose (a diagnosis plan on a set with payloads)

    def model_units(self, model: RobotModel) -> np.ndarray:
        """The joints (n, n_act) in the model's units (deg or rad, mm or m), actuated joint order."""
        return self.joints / model.joint_scale()[model.actuated]


@dataclass
class Pool:
    """Visible candidate poses: row values (C, n) in internal units, target per pose, the nominal chain in the
    base frame, per-axis noise (C,) mm, the tracker position (3,) mm in the base frame, and which candidates
    were drawn uniformly (C,) (the others limit-biased)."""

    q: np.ndarray
    labels: K.Labels | None
    chain: K.Chain
    sigma: np.ndarray
    tracker_mm: np.ndarray
    uniform: np.ndarray | None = None

    def subset(self, idx) -> tuple[np.ndarray, K.Labels | None]:
        return self.q[idx], None if self.labels is None else self.labels[idx]


# ---------------------------------------------------------------------------------------------- candidates
def outward(model: RobotModel, chain: K.Chain) -> np.ndarray:
    """Unit outward direction (N, 3) of each pose's target: from its frame's origin through the target, or the
    frame's z axis for a target at the origin."""
    xyz = model.target_points[chain.target]  # (N, 3) in the row frame
    length = np.linalg.norm(xyz, axis=1)
    local = np.where(length[:, None] > 1e-9, xyz / np.maximum(length, 1e-300)[:, None], [0.0, 0.0, 1.0])
    return np.einsum("nab,nb->na", chain.R_end, local)


def facing(chain: K.Chain, out: np.ndarray, tracker: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """(N,) True where the target's outward direction `out` (N, 3) is within max_incidence_deg of its line of
    sight to the tracker."""
    sight = tracker - chain.p
    cos = (out * sight).sum(1) / np.maximum(np.linalg.norm(sight, axis=1), 1e-9)
    return cos >= np.cos(np.radians(max_incidence_deg)) - 1e-12


def default_tracker(model: RobotModel, chain: K.Chain, out: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """Tracker position (3,) mm in the base frame: TRACKER_DISTANCE_MM from the centre of the targets at the poses
    of `chain`, level with it, across their thinnest horizontal extent (a rail robot is seen from the side), on
    the side of the base they lie; unless fewer than MIN_FACING of the targets face it, then of that side, the
    opposite one, the two others and above, the one most of them face."""
    g = np.asarray(model.gravity, float)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    centre = chain.p.mean(0)
    H = (chain.p - centre) @ np.stack([e1, e2]).T
    _, V = np.linalg.eigh(H.T @ H)
    thin, wide = V[0, 0] * e1 + V[1, 0] * e2, V[0, 1] * e1 + V[1, 1] * e2
    thin = thin if thin @ centre >= 0 else -thin
    sides = [centre + TRACKER_DISTANCE_MM * d for d in (thin, -thin, wide, -wide, up)]
    share = [facing(chain, out, t, max_incidence_deg).mean() for t in sides]
    return sides[0] if share[0] >= MIN_FACING else sides[int(np.argmax(share))]


def candidate_joints(model: RobotModel, n: int, rng: np.random.Generator, extreme_share: float = EXTREME_SHARE
                     ) -> np.ndarray:
    """n row-value vectors (internal units) within the limits (MARGIN of each range kept clear): the first
    n - round(extreme_share n) uniform, the others limit-biased, every actuated joint drawn from the arcsine
    law Beta(0.5, 0.5) over its range (density highest at both limits; a quarter of the draws lie in the
    outer 15 % of the range at each end, against 7.5 % for uniform draws)."""
    k = int(round(extreme_share * n))
    q = sample_uniform(model, n - k, rng, margin=MARGIN)
    if k == 0:
        return q
    act = model.actuated
    lo, hi = model.limits[act, 0].copy(), model.limits[act, 1].copy()
    inf = ~np.isfinite(lo) | ~np.isfinite(hi)
    lo[inf], hi[inf] = -np.pi, np.pi
    u = rng.beta(0.5, 0.5, (k, len(act)))
    return np.vstack([q, model.expand_joints(lo + (hi - lo) * (MARGIN + (1 - 2 * MARGIN) * u))])


def visible_pool(model: RobotModel, n: int, rng: np.random.Generator, tracker_mm=None,
                 max_incidence_deg: float | None = None, instrument_name: str | None = None,
                 extreme_share: float = EXTREME_SHARE) -> Pool:
    """n candidates drawn within the limits (`candidate_joints`), pose i measuring target i mod T, kept where the
    target faces the tracker within max_incidence_deg (module docstring); sigma per pose is the instrument's
    noise at the tracker distance plus the robot's repeatability. `Pool.uniform` marks the uniform draws."""
    q = candidate_joints(model, n, rng, extreme_share)
    uniform = np.arange(n) < n - int(round(extreme_share * n))
    labels = K.Labels(np.arange(n) % model.n_targets, np.zeros(n, int)) if model.n_targets > 1 else None
    chain = K.Chain(model, K.nominal_vector(model), q, labels=labels)
    limit = MAX_INCIDENCE_DEG if max_incidence_deg is None else float(max_incidence_deg)
    out = outward(model, chain)
    tracker = default_tracker(model, chain, out, limit) if tracker_mm is None else np.asarray(tracker_mm, float)
    keep = facing(chain, out, tracker, limit)
    if labels is not None:
        labels = labels[keep]
    chain = K.Chain(model, K.nominal_vector(model), q[keep], labels=labels)
    sigma = np.hypot(instrument(instrument_name).sigma_mm(chain.p - tracker), REPEATABILITY_MM)
    return Pool(q[keep], labels, chain, sigma, tracker, uniform[keep])


# ---------------------------------------------------------------------------------------------- 3x3 algebra
# Per-candidate 3x3 matrices are stored component-major, (3, 3, C), and vectors (3, C): numpy's elementwise
# work over C candidates then runs on contiguous rows (5-25x faster than (C, 3, 3) batches).
def _det3(X: np.ndarray) -> np.ndarray:
    """Determinants (C,) of (3, 3, C) matrices, in closed form."""
    return (X[0, 0] * (X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1]) - X[0, 1] * (X[1, 0] * X[2, 2] - X[1, 2] * X[2, 0])
            + X[0, 2] * (X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0]))


def _adj3(X: np.ndarray) -> np.ndarray:
    """Adjugates (3, 3, C) of symmetric (3, 3, C) matrices: X^-1 = adj / det."""
    return np.array([[X[1, 1] * X[2, 2] - X[1, 2] ** 2, X[0, 2] * X[1, 2] - X[0, 1] * X[2, 2],
                      X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1]],
                     [X[0, 2] * X[1, 2] - X[0, 1] * X[2, 2], X[0, 0] * X[2, 2] - X[0, 2] ** 2,
                      X[0, 2] * X[0, 1] - X[0, 0] * X[1, 2]],
                     [X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1], X[0, 2] * X[0, 1] - X[0, 0] * X[1, 2],
                      X[0, 0] * X[1, 1] - X[0, 1] ** 2]])


def _quad3(X: np.ndarray, r: np.ndarray) -> np.ndarray:
    """r^T X^-1 r (C,) for symmetric (3, 3, C) matrices X and (3, C) vectors r, by the adjugate."""
    return np.einsum("jc,jc->c", np.einsum("ic,ijc->jc", r, _adj3(X)), r) / _det3(X)


_EYE3 = np.eye(3)[:, :, None]


class _Sequential:
    """Recursive least squares over candidate poses. A (C, 3, p) are the candidates' scaled, noise-weighted
    Jacobian blocks; M = M0 + sum of A_k^T A_k over the poses added; S_i = A_i M^-1 A_i^T. With a target
    difference d (C, 3) (and its least-squares fit theta on the poses so far), r_i = d_i - A_i theta is the
    held-out difference at candidate i and `lack_of_fit` the weighted residual sum of squares so far."""

    def __init__(self, A: np.ndarray, M0: np.ndarray, rhs: np.ndarray | None = None, d: np.ndarray | None = None):
        C, _, p = A.shape
        self.n = C
        self.A = np.ascontiguousarray(A.transpose(1, 0, 2))  # (3, C, p)
        self.flat = self.A.reshape(3 * C, p)
        self.Minv = np.linalg.inv(M0)
        self.S = np.einsum("icp,jcp->ijc", (self.flat @ self.Minv).reshape(3, C, p), self.A)
        self.theta = None if rhs is None else self.Minv @ rhs
        self.r = None if d is None else d.T - self.A @ self.theta  # (3, C)
        self.lack_of_fit = 0.0

    def d_gain(self) -> np.ndarray:
        """log det(M + A_i^T A_i) - log det(M) for every candidate."""
        return np.log(_det3(self.S + _EYE3))

    def t_gain(self) -> np.ndarray:
        """Increase of the lack of fit if candidate i is added: r_i^T (I + S_i)^-1 r_i."""
        return _quad3(self.S + _EYE3, self.r)

    def add(self, k: int) -> None:
        W = np.linalg.inv(np.eye(3) + self.S[:, :, k])
        G = self.Minv @ self.A[:, k].T  # (p, 3)
        if self.r is not None:
            rk = self.r[:, k].copy()
            self.lack_of_fit += float(rk @ W @ rk)
            step = G @ (W @ rk)
            self.theta = self.theta + step
            self.r -= self.A @ step
        self.S -= self._outer(G, W)
        self.Minv -= G @ W @ G.T

    def _outer(self, G: np.ndarray, W: np.ndarray) -> np.ndarray:
        """B_i W B_i^T (3, 3, C) for every candidate, B_i = A_i G (G (p, 3)), W symmetric. No factor of W: a pose
        that alone identifies a direction makes I - S_k nearly singular, and its inverse then is not positive
        definite in floating point."""
        B = np.ascontiguousarray((self.flat @ G).reshape(3, self.n, 3).transpose(0, 2, 1))  # (3, 3, C)
        BW = np.ascontiguousarray((self.flat @ (G @ W)).reshape(3, self.n, 3).transpose(0, 2, 1))
        return np.einsum("ikc,jkc->ijc", BW, B)

    def swap_gain(self, k: int) -> np.ndarray:
        """log det change of M for every candidate j if the chosen pose k is replaced by j (0 for j = k):
        log det(I + S_j) + log det(I - S_k + S_kj (I + S_j)^-1 S_jk), the Schur form of the rank-six lemma. Every
        term is bounded, so a pose that alone identifies a direction (I - S_k ~ 0) is scored as exactly as any;
        downdating M first would invert I - S_k."""
        X = self.S + _EYE3
        B = np.ascontiguousarray((self.flat @ (self.Minv @ self.A[:, k].T)).reshape(3, self.n, 3))  # S_jk (3,C,3)
        B = B.transpose(0, 2, 1)  # (3 of j, 3 of k, C)
        adj, det = _adj3(X), _det3(X)
        Q = np.einsum("bcC,cdC->bdC", np.einsum("abC,acC->bcC", B, adj), B) / det  # S_kj (I + S_j)^-1 S_jk
        # (two two-operand einsums: numpy runs a three-operand one as one 81-term loop, 1.7x slower here)
        D = (np.eye(3) - self.S[:, :, k])[:, :, None] + Q
        with np.errstate(divide="ignore", invalid="ignore"):  # det D <= 0 only by rounding: never a swap
            gain = np.log(det) + np.log(_det3(D))
        return np.where(np.isfinite(gain), gain, -np.inf)

    def remove(self, k: int) -> None:
        """Take a chosen pose k out of M (D-criterion states only: the fit `theta` is not downdated)."""
        W = np.linalg.inv(np.eye(3) - self.S[:, :, k])
        G = self.Minv @ self.A[:, k].T
        self.S += self._outer(G, W)
        self.Minv += G @ W @ G.T


def _greedy(states: list[_Sequential], n: int, gain, combine) -> list[int]:
    """n distinct candidates, each maximising combine(running totals + gain(state)) over the states."""
    taken = np.zeros(states[0].n, bool)
    totals = np.zeros(len(states))
    chosen = []
    for _ in range(n):
        gains = np.array([gain(s) for s in states])
        score = combine(totals[:, None] + gains)
        score[taken] = -np.inf
        k = int(np.argmax(score))
        totals += gains[:, k]
        for s in states:
            s.add(k)
        taken[k] = True
        chosen.append(k)
    return chosen


def _exchange(states: list[_Sequential], chosen: list[int], combine, passes: int) -> list[int]:
    """Fedorov's exchange after the greedy pass (D-criterion states): each chosen pose in turn is replaced by the
    candidate that raises combine(log det changes) most, while any swap gains; at most `passes` sweeps and
    EXCHANGE_BUDGET poses tried. Each swap is scored for every candidate with one rank-three downdate,
    O(candidates x parameters)."""
    chosen = list(chosen)
    taken = np.zeros(states[0].n, bool)
    taken[chosen] = True
    tried = 0
    for _ in range(passes):
        swapped = False
        for slot, k in enumerate(chosen):
            if tried == EXCHANGE_BUDGET:
                return chosen
            tried += 1
            score = combine(np.array([s.swap_gain(k) for s in states]))
            score[taken] = -np.inf
            j = int(np.argmax(score))
            if score[j] <= EXCHANGE_TOL:
                continue
            for s in states:
                s.remove(k)
                s.add(j)
            taken[k], taken[j] = False, True
            chosen[slot] = j
            swapped = True
        if not swapped:
            break
    return chosen


# ---------------------------------------------------------------------------------------------- geometric
def loaded_joints(model: RobotModel, chain: K.Chain) -> list[int]:
    """Joints whose gravity load varies by more than LOADED_SHARE of the most loaded joint's over these poses."""
    span = np.ptp(joint_loads(chain, np.zeros(chain.N)), axis=0)
    return [j for j in range(model.n_joints) if model.moving[j] and span[j] > LOADED_SHARE * span.max()]


def _information_blocks(chain: K.Chain, sigma: np.ndarray, loaded: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Noise-weighted geometric Jacobian (N, 3, P), and per loaded joint the displacement (N, 3, k) of a unit
    compliance (joint Jacobian column x gravity load)."""
    w = 1.0 / sigma[:, None, None]
    if not loaded:
        return chain.jacobian() * w, np.zeros((chain.N, 3, 0))
    tau = joint_loads(chain, np.zeros(chain.N))
    return chain.jacobian() * w, chain.joint_jacobian()[:, :, loaded] * tau[:, None, loaded] * w


def _scaled(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns scaled to unit RMS norm per pose over the rows given; returns the scaled blocks and the scale."""
    scale = np.sqrt((J**2).sum(axis=(0, 1)) / len(J))
    scale = np.where(scale > 0, scale, 1.0)
    return J / scale, scale


def observability(J: np.ndarray, scale: np.ndarray, ident: list[int], names: list[str]) -> dict:
    """Of a pose set's geometric Jacobian J (N, 3, P) (noise-weighted): log det of the information of the
    identifiable parameters with the fixed column `scale` (comparable between sets), and the condition number,
    observability index O1 and rank of the column-normalised Jacobian (as `identifiability.analyse` reports a
    measured set)."""
    A = J[:, :, ident] / scale
    sign, logdet = np.linalg.slogdet(np.einsum("nip,niq->pq", A, A))
    a = analyse(J[:, :, ident].reshape(-1, len(ident)), [names[i] for i in ident])
    return {"log_det": float(logdet) if sign > 0 else None, "condition_number": a.condition_number,
            "observability_index": a.observability_index, "rank": a.rank}


def _measured_blocks(model: RobotModel, meas: Measurements | None, loaded: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """`_information_blocks` of a measured set on the nominal model in the base frame (no rows without one)."""
    P = len(K.nominal_vector(model))
    if meas is None:
        return np.zeros((0, 3, P)), np.zeros((0, 3, len(loaded)))
    q = meas.joints
    labels = K.Labels(np.zeros(len(q), int) if meas.target is None else meas.target, np.zeros(len(q), int))
    chain = K.Chain(model, K.nominal_vector(model), q, labels=labels)
    return _information_blocks(chain, np.hypot(meas.noise_sigma_mm(), REPEATABILITY_MM), loaded)


def _geometric(model: RobotModel, n: int, pool: Pool, loads: bool, meas: Measurements | None,
               exchange: int = EXCHANGE_PASSES) -> tuple[np.ndarray, dict]:
    """D-optimal poses for the identifiable geometric parameters, added to the measured set `meas` if given; with
    `loads` and masses the compound criterion (1 - LOAD_WEIGHT) / p_g log det M_geo + LOAD_WEIGHT / p_c
    log det (information on the compliances left after the geometry), each part per parameter so that the few
    compliances do not outweigh the geometry."""
    ident = structural(model).identifiable
    loaded = loaded_joints(model, pool.chain) if loads and model.has_mass else []
    J, L = _information_blocks(pool.chain, pool.sigma, loaded)
    A, scale = _scaled(J[:, :, ident])
    C, lscale = _scaled(L)
    J_had, L_had = _measured_blocks(model, meas, loaded)
    B = np.concatenate([J_had[:, :, ident] / scale, L_had / lscale], axis=2)
    p, k = len(ident), len(loaded)
    M0 = RIDGE * np.eye(p + k) + np.einsum("nip,niq->pq", B, B)
    states = [_Sequential(A, M0[:p, :p])]
    combine = lambda T: T[0]  # noqa: E731
    if loaded:
        states.append(_Sequential(np.concatenate([A, C], axis=2), M0))
        w = LOAD_WEIGHT
        combine = lambda T: ((1 - w) / p - w / k) * T[0] + w / k * T[1]  # noqa: E731
    chosen = _greedy(states, n, _Sequential.d_gain, combine)
    chosen = np.array(_exchange(states, chosen, combine, exchange))
    what = (f" (weight {1 - LOAD_WEIGHT:g}) and of a compliance per loaded joint given the geometry (weight "
            f"{LOAD_WEIGHT:g}), each per parameter" if loaded else "")
    return chosen, {"criterion": "D-optimal: log det of the information matrix of the identifiable geometric "
                                 "parameters" + what, "loaded_joints": [model.joint_names[j] for j in loaded]}


def _report(model: RobotModel, pool: Pool, meas: Measurements | None, chosen: np.ndarray, random: np.ndarray) -> dict:
    """Observability of the geometry from the measured set (if any) with the planned poses and with the random
    ones, and the information gained per parameter, exp((log det planned - log det random) / p)."""
    ident = structural(model).identifiable
    names = K.parameter_names(model)
    J = _information_blocks(pool.chain, pool.sigma, [])[0]
    J_had = _measured_blocks(model, meas, [])[0]
    scale = _scaled(J[:, :, ident])[1]
    out = {"n_parameters": len(ident)}
    if meas is not None:
        out["measured"] = observability(J_had, scale, ident, names)
    for key, idx in (("planned", chosen), ("random", random)):
        out[key] = observability(np.concatenate([J_had, J[idx]]), scale, ident, names)
    if out["planned"]["log_det"] is not None and out["random"]["log_det"] is not None:
        out["information_gain_per_parameter"] = float(np.exp((out["planned"]["log_det"]
                                                              - out["random"]["log_det"]) / len(ident)))
    return out


# ---------------------------------------------------------------------------------------------- diagnosis
def nested(a: Effect, b: Effect) -> bool:
    """One cause is the other on more joints (a joint's compliance and the compliance of the whole arm): the
    richer one fits whatever the other fits, so no pose can split them; parsimony keeps the smaller. A cause on no
    joint (the whole robot against the tracker, the target) is not one on a joint on fewer joints."""
    return type(a) is type(b) and a.harmonic == b.harmonic and bool(a.joints) == bool(b.joints) and (
        set(a.joints) <= set(b.joints) or set(b.joints) <= set(a.joints))


def lookalike_pairs(model: RobotModel, meas: Measurements, effects, findings: list[dict]
                    ) -> list[tuple[Effect, Effect]]:
    """(found effect, look-alike effect) for every finding that lists `indistinguishable_from`: the found one from
    the calibration's `effects`, the look-alike from the diagnosis's candidates for this set matched on kind,
    joints and harmonic (a cyclic error of unnamed harmonic: the lowest), `nested` pairs left out; at most
    MAX_RIVAL_PAIRS."""
    out = []
    for rivals in _rebuilt(model, meas, effects, findings):
        for pair in rivals:
            if pair is not None and pair not in out:
                out.append(pair)
    return out[:MAX_RIVAL_PAIRS]


def plannable(model: RobotModel, meas: Measurements, effects, findings: list[dict]) -> list[list[bool]]:
    """Per finding, per entry of its `indistinguishable_from`: whether a diagnosis plan (`lookalike_pairs`) can
    split the two, i.e. whether the pair is rebuilt from the stored calibration and not `nested`. The calibration
    answer carries it, so a client asks for a plan only where one can be made: the Motoman's joint_scale[S1] ~
    link_deflection[...] (a lateral compliance on the load identified from the data, which the plan's candidates
    do not hold) was announced as a plan, and the plan answered 422 "nothing to split"."""
    return [[pair is not None for pair in rivals] for rivals in _rebuilt(model, meas, effects, findings)]


def _rebuilt(model: RobotModel, meas: Measurements, effects, findings: list[dict]
             ) -> list[list[tuple[Effect, Effect] | None]]:
    """Per finding, per look-alike: (found effect, look-alike effect), or None where either is not rebuilt or they
    are nested."""
    names = lambda e: [model.joint_names[j] for j in e.joints]  # noqa: E731
    pool = effect_candidates(model, meas)[0] if any(f.get("indistinguishable_from") for f in findings) else []
    # a cause without a named harmonic matches the lowest (the candidates list them in order)
    same = lambda e, d: (e.kind == d.get("kind") and names(e) == list(d.get("joints", []))  # noqa: E731
                         and d.get("harmonic", e.harmonic) == e.harmonic)
    out = []
    for f in findings:
        mine = next((e for e in effects if same(e, f)), None)
        rivals = []
        for a in f.get("indistinguishable_from") or []:
            rival = None if mine is None else next((e for e in pool if same(e, a) and e != mine), None)
            rivals.append((mine, rival) if rival is not None and not nested(mine, rival) else None)
        out.append(rivals)
    return out


def _columns_like(meas: Measurements, q: np.ndarray, labels: K.Labels | None, rng: np.random.Generator
                  ) -> Measurements:
    """Measurement columns for candidate poses: the set's mean time and temperature, a payload drawn from the
    ones the set used (so load-driven rivals can be separated by the payload too)."""
    N = len(q)
    mean = lambda a: None if a is None else np.full(N, float(np.mean(a)))  # noqa: E731
    payload = None if meas.payload is None else rng.choice(np.unique(meas.payload), N)
    return Measurements(joints=q, points=np.zeros((N, 3)), timestamp=mean(meas.timestamp),
                        temperature=mean(meas.temperature), payload=payload, instrument=meas.instrument,
                        target=None if labels is None else labels.target, setup=np.zeros(N, int),
                        setup_names=meas.setup_names)


def _discrimination(truth: Calibration, rival: Calibration, meas: Measurements, cols: Measurements,
                    sigma_c: np.ndarray) -> _Sequential:
    """T-criterion state: the data follow `truth`, `rival` is refitted (linearised) to the set and new poses."""
    sigma_e = np.hypot(meas.noise_sigma_mm(), REPEATABILITY_MM)[:, None]
    d_e = (truth.predict(meas.joints, meas) - rival.predict(meas.joints, meas)) / sigma_e
    d_c = (truth.predict(cols.joints, cols) - rival.predict(cols.joints, cols)) / sigma_c[:, None]
    J_e, scale = _scaled(prediction_jacobian(rival, meas.joints, meas) / sigma_e[..., None])
    J_c = prediction_jacobian(rival, cols.joints, cols) / sigma_c[:, None, None] / scale
    state = _Sequential(J_c, np.einsum("nip,niq->pq", J_e, J_e) + RIDGE * np.eye(len(scale)),
                        np.einsum("nip,ni->p", J_e, d_e), d_c)
    state.lack_of_fit = float(((d_e - J_e @ state.theta) ** 2).sum())
    return state


def _separation(state: _Sequential, idx) -> tuple[float, float]:
    """Added lack of fit (chi-square units) of the poses idx taken in turn, and their RMS held-out difference."""
    start, diffs = state.lack_of_fit, []
    for k in idx:
        diffs.append(float(np.sqrt((state.r[:, k] ** 2).sum())))
        state.add(k)
    return state.lack_of_fit - start, float(np.sqrt(np.mean(np.square(diffs))))


def _diagnosis(model: RobotModel, n: int, pool: Pool, cols: Measurements, meas: Measurements, effects, rivals,
               random: np.ndarray) -> tuple[np.ndarray, dict]:
    """T-optimal poses for the rival pairs (module docstring), and each pair's separation by them and by the
    `random` poses: the added lack of fit of the wrong model (chi-square units, the smaller of both directions)
    and the RMS held-out difference per pose and axis in noise sigmas. `separation_needed_chi2` is about what it
    takes for the diagnosis to tell them apart: it lists rivals whose held-out RMS is within INDISTINGUISHABLE
    (2 %) of the winner's, i.e. whose mean square is within (1.02^2 - 1) of the about 3 x poses chi-square
    units of the noise; `expected_to_split` when the planned separation T, less the noise of the measured
    increase (2 sqrt(T): the cross term of the difference with the noise), still exceeds it."""
    others = lambda e: tuple(x for x in effects if x != e)  # noqa: E731
    fits = {}
    for pair in rivals:
        for e in pair:
            if e not in fits:
                fits[e] = identify(model, meas, effects=others(pair[0]) + (e,), folds=0)
    make = lambda: [_discrimination(fits[a], fits[b], meas, cols, pool.sigma)  # noqa: E731
                    for pair in rivals for a, b in (pair, pair[::-1])]
    chosen = np.array(_greedy(make(), n, _Sequential.t_gain, lambda T: T.min(0)))
    report = []
    planned_states, random_states = make(), make()
    needed = (INDISTINGUISHABLE**2 - 1.0) * 3 * (meas.n_poses + n)
    for i, pair in enumerate(rivals):
        row = {"found": pair[0].label(model), "look_alike": pair[1].label(model), "separation_needed_chi2": needed}
        for key, states, idx in (("planned", planned_states, chosen), ("random", random_states, random)):
            sep = [_separation(states[2 * i + w], idx) for w in (0, 1)]
            row[key] = {"separation_chi2": min(s[0] for s in sep),
                        "held_out_difference_sigma": min(s[1] for s in sep) / np.sqrt(3)}
        T = row["planned"]["separation_chi2"]
        row["expected_to_split"] = bool(T - 2.0 * np.sqrt(max(T, 0.0)) > needed)
        report.append(row)
    return chosen, {"criterion": "T-optimal: the smaller, over the look-alike pairs and both directions, of the "
                                 "increase of the wrong model's weighted residual sum of squares when both are "
                                 "refitted to the measured set and the new poses", "rivals": report}


# ---------------------------------------------------------------------------------------------- front
def tracker_of(robot: CalibratedRobot) -> np.ndarray:
    """Where a calibrated set was measured from, (3,) mm in the robot base frame: the origin of the measurement
    frame (the tracker's own frame) seen from the identified base pose of the first setup."""
    b = robot.x[K.layout(robot.model, robot.x).base(0)]
    return -K.base_rotation(b, robot.R0 if robot.R0.ndim == 2 else robot.R0[0]).T @ b[:3]


def plan(model: RobotModel, n_poses: int, purpose: str = "geometric", *, seed: int = 0,
         candidates: int = CANDIDATES, tracker_mm=None, max_incidence_deg: float | None = None, loads: bool = True,
         meas: Measurements | None = None, effects=(), rivals=(), extreme_share: float = EXTREME_SHARE,
         exchange: int = EXCHANGE_PASSES) -> Plan:
    """n_poses poses (internal units) for `purpose` (module docstring), chosen among `candidates` poses drawn
    within the joint limits that the tracker can see (tracker_mm (3,) in the robot base frame, mm;
    max_incidence_deg; `tracker_of` gives where a calibrated set was measured from).

    geometric: D-optimal for the identifiable geometric parameters (and, with `loads` and masses, a compliance
    per loaded joint); with a measured set `meas`, the poses that add most to what it already identifies.
    diagnosis: T-optimal to tell each (found, look-alike) effect pair of `rivals` apart after the measured set
    `meas`, calibrated with `effects` (see `lookalike_pairs`). `observability` compares the chosen set with as
    many random visible poses drawn uniformly (seeded). extreme_share: share of limit-biased candidates;
    exchange: sweeps of the exchange step (geometric; 0: greedy only). Raises ValueError on a request that cannot be planned
    (unknown purpose, too few visible candidates, a diagnosis without its set or rivals)."""
    if purpose not in PURPOSES:
        raise ValueError(f"unknown purpose {purpose!r}; use one of {PURPOSES}")
    if purpose == "diagnosis" and (meas is None or not rivals):
        raise ValueError("a diagnosis plan needs the measured set and at least one pair of look-alike causes")
    if not 1 <= n_poses <= candidates:
        raise ValueError(f"n_poses must be between 1 and the number of candidates ({candidates}), got {n_poses}")
    rng = np.random.default_rng(seed)
    pool = visible_pool(model, candidates, rng, tracker_mm, max_incidence_deg,
                        None if meas is None else meas.instrument, extreme_share)
    if len(pool.q) < n_poses:
        raise ValueError(f"only {len(pool.q)} of {candidates} candidate poses face the tracker at "
                         f"{np.round(pool.tracker_mm).tolist()} mm within the incidence limit; move the tracker, "
                         "allow a larger incidence angle or ask for fewer poses")
    payload = None
    uniform = np.flatnonzero(pool.uniform)
    random = rng.choice(uniform, n_poses, replace=False) if len(uniform) >= n_poses else \
        rng.choice(len(pool.q), n_poses, replace=False)
    if purpose == "geometric":
        chosen, obs = _geometric(model, n_poses, pool, loads, meas, exchange)
    else:
        cols = _columns_like(meas, pool.q, pool.labels, rng)
        chosen, obs = _diagnosis(model, n_poses, pool, cols, meas, tuple(effects), list(rivals), random)
        payload = None if cols.payload is None else cols.payload[chosen]
    obs["geometry"] = _report(model, pool, meas, chosen, random)
    q, labels = pool.subset(chosen)
    obs.update({"purpose": purpose, "n_poses": int(n_poses), "candidates": int(candidates),
                "visible_candidates": int(len(pool.q)), "tracker_mm": pool.tracker_mm.tolist(),
                "max_incidence_deg": MAX_INCIDENCE_DEG if max_incidence_deg is None else float(max_incidence_deg),
                "seed": int(seed)})
    return Plan(q[:, model.actuated], obs, None if labels is None else labels.target, payload)
