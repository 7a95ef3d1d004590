import numpy as np
import pytest

from calib_core import kinematics as K
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_core.twin import sample_uniform

from .chains import random_chain


def _fd_jacobian(model, x, q, R0, h=1e-3):
    """Fourth-order central differences: truncation error O(h^4), well below 1e-6 relative."""
    P = len(x)
    J = np.empty((len(q), 3, P))
    for k in range(P):
        e = np.zeros(P)
        e[k] = h
        f = lambda s: K.forward(model, x + s * e, q, R0)  # noqa: E731
        J[:, :, k] = (8 * (f(1) - f(-1)) - (f(2) - f(-2))) / (12 * h)
    return J


def _models(seed):
    rng = np.random.default_rng(seed)
    return [parse_model(spray7()), parse_model(arm6()), random_chain(rng), random_chain(rng)]


def test_analytic_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(seed)
    for model in _models(seed):
        q = sample_uniform(model, 25, rng)
        x = K.nominal_vector(model, np.r_[rng.uniform(-2000, 2000, 3), rng.uniform(-0.2, 0.2, 3)])
        x = x + rng.normal(0, 1e-2, len(x))
        R0 = K.base_rotation(np.r_[0, 0, 0, rng.uniform(-3, 3, 3)], np.eye(3))
        J = K.Chain(model, x, q, R0).jacobian()
        Jfd = _fd_jacobian(model, x, q, R0)
        scale = np.maximum(np.abs(Jfd).max(axis=(0, 1)), 1.0)
        rel = (np.abs(J - Jfd).max(axis=(0, 1)) / scale).max()
        assert rel < 1e-6, f"{model.name}: relative error {rel:.2e} (seed {seed})"


def test_joint_jacobian_matches_theta_and_d_columns(seed):
    model = _models(seed)[2]
    rng = np.random.default_rng(seed)
    q = sample_uniform(model, 10, rng)
    x = K.nominal_vector(model)
    h = 1e-6
    Jq = K.Chain(model, x, q).joint_jacobian()
    for j in range(model.n_joints):
        dq = np.zeros_like(q)
        dq[:, j] = h
        fd = (K.forward(model, x, q + dq) - K.forward(model, x, q - dq)) / (2 * h)
        assert np.allclose(Jq[:, :, j], fd, atol=1e-5 * max(1.0, np.abs(fd).max()))


def test_forward_is_vectorised_consistently(seed):
    """N poses at once give the same points as one pose at a time."""
    model = parse_model(spray7())
    q = sample_uniform(model, 40, np.random.default_rng(seed))
    x = K.nominal_vector(model)
    batch = K.forward(model, x, q)
    single = np.vstack([K.forward(model, x, qi[None]) for qi in q])
    assert np.abs(batch - single).max() < 1e-9


def test_prismatic_joint_moves_along_its_axis():
    model = parse_model(spray7())
    x = K.nominal_vector(model)
    q = sample_uniform(model, 1, np.random.default_rng(0))
    q2 = q.copy()
    q2[0, 0] += 100.0
    chain = K.Chain(model, x, q)
    assert np.allclose(K.forward(model, x, q2) - chain.p, 100.0 * chain.z_axis[0])


@pytest.mark.parametrize("n", [1, 3])
def test_rigid_fit_recovers_a_transform(n, seed):
    rng = np.random.default_rng(seed)
    src = rng.normal(0, 1000, (50, 3))
    R = K.base_rotation(np.r_[0, 0, 0, rng.uniform(-3, 3, 3)], np.eye(3))
    t = rng.normal(0, 1000, 3)
    R2, t2 = K.rigid_fit(src, src @ R.T + t)
    assert np.allclose(R2, R) and np.allclose(t2, t)
