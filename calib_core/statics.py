"""Gravity and payload loads on every joint and link, vectorised over poses (what compliance models need).

Masses in kg, gravity in m/s^2 (given in the robot base frame), lengths in mm; torques come out in N*m
(forces on prismatic joints in N). Body j is the body moved by joint j, its COM given in joint frame j.
"""
from __future__ import annotations

import numpy as np

from .kinematics import Chain, _cross


def gravity_world(chain: Chain, g: np.ndarray | None = None) -> np.ndarray:
    """Gravity m/s^2 in the measurement frame: (3,), or (N, 3) per pose when the poses span several setups. `g` (3,)
    m/s^2 in the robot base frame replaces the model's (a direction identified from the data: the base frame the
    geometry defines is seldom exactly level)."""
    return chain.Rb @ (chain.model.gravity if g is None else np.asarray(g, float))


def com_world(chain: Chain) -> np.ndarray:
    """COM of every body in the measurement frame, (n, N, 3) mm."""
    return chain.o_beta + np.einsum("jnab,jb->jna", chain.R, chain.model.com)


def distal_loads(chain: Chain, payload_kg: np.ndarray, phi: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Mass (n, N) kg and first moment (n, N, 3) kg*mm of everything row j carries: its descendants in the tree
    and the payload at the measured target when j is on the way to it. `phi` ((n, 4): mass and first moment m*c in
    the body frame) replaces the model's mass data (mass data identified from the measurements)."""
    if phi is None:
        m = chain.model.mass
        first = m[:, None, None] * com_world(chain)
    else:
        m = phi[:, 0]
        first = m[:, None, None] * chain.o_beta + np.einsum("jnab,jb->jna", chain.R, phi[:, 1:])
    if chain.model.is_serial:
        M = np.cumsum(m[::-1])[::-1][:, None] + payload_kg[None, :]
        S = np.cumsum(first[::-1], axis=0)[::-1] + payload_kg[None, :, None] * chain.p[None]
        return M, S
    D = chain.model.ancestors().T.astype(float)  # [j, k]: row k is carried by row j (or is j)
    pay = chain.on_path * payload_kg[None, :]
    return (D @ m)[:, None] + pay, np.einsum("jk,kna->jna", D, first) + pay[..., None] * chain.p[None]


def gravity_moments(chain: Chain, payload_kg: np.ndarray, phi: np.ndarray | None = None,
                    g: np.ndarray | None = None) -> np.ndarray:
    """Moment (n, N, 3) N*m of the gravity of everything row j carries about row j's axis point (o_theta): its
    part along the axis loads a revolute joint, the part across it bends the bearing. `g`: see gravity_world."""
    return _moments(chain, *distal_loads(chain, payload_kg, _mass_data(chain, phi)), g)


def base_moment(chain: Chain, payload_kg: np.ndarray, phi: np.ndarray | None = None,
                g: np.ndarray | None = None) -> np.ndarray:
    """Moment (N, 3) N*m, measurement frame, of the gravity of everything the base carries (every body and the
    payload) about the base origin: what tips the robot on its mount. `phi`, `g`: see distal_loads, gravity_world."""
    M, S = distal_loads(chain, payload_kg, _mass_data(chain, phi))
    roots = chain.model.parents < 0
    return _moments(chain, M[roots].sum(0), S[roots].sum(0), g, about=chain.base_origin)


def _mass_data(chain: Chain, phi: np.ndarray | None) -> np.ndarray | None:
    """phi, or None for the model's mass data when it has some."""
    if phi is None and chain.model.mass is None:
        raise ValueError("the model has no masses and centres of mass: no gravity model is possible")
    return phi


def _moments(chain: Chain, M: np.ndarray, S: np.ndarray, g: np.ndarray | None = None,
             about: np.ndarray | None = None) -> np.ndarray:
    """(n, N, 3) N*m: the carried mass M at its centre S / M, about each row's axis point (or the points `about`)."""
    point = chain.o_theta if about is None else about
    return _cross(S - M[..., None] * point, np.broadcast_to(gravity_world(chain, g), S.shape)) / 1000.0


def joint_loads(chain: Chain, payload_kg: np.ndarray, phi: np.ndarray | None = None,
                g: np.ndarray | None = None) -> np.ndarray:
    """Gravity torque about each revolute axis (N*m) or force along each prismatic axis (N), shape (N, n), from
    the model's mass data or `phi` (see distal_loads), under the model's gravity or `g` (see gravity_world).

    Sign convention: the load a positive joint motion works against is negative.
    """
    M, S = distal_loads(chain, payload_kg, _mass_data(chain, phi))
    torque = np.einsum("jna,jna->jn", _moments(chain, M, S, g), chain.z_axis)
    force = M * (chain.z_axis * gravity_world(chain, g)).sum(-1)
    return np.where(chain.model.prismatic[:, None], force, torque).T


def segment(chain: Chain, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The link segment ending at row k (from its parent's origin): start (N, 3), end (N, 3) and length (N,) mm."""
    par = chain.model.parents[k]
    start = chain.o_beta[par] if par >= 0 else np.broadcast_to(chain.base_origin, chain.p.shape)
    end = chain.o_beta[k]
    return start, end, np.linalg.norm(end - start, axis=1)
