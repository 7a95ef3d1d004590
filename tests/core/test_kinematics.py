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


def _reference_points(model, x, q, R0s, labels):
    """Each pose's target by a product of 4x4 transforms, one pose at a time (the MD-H definition written out:
    pre . Rx(alpha) Tx(a) Rz(theta + q) Tz(d) Ry(beta) per row, from the setup's base along the target's rows)."""
    def rot(axis, t):
        c, s = np.cos(t), np.sin(t)
        R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
             "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
        T = np.eye(4)
        T[:3, :3] = R
        return T

    def trans(v):
        T = np.eye(4)
        T[:3, 3] = v
        return T

    lay = K.layout(model, x)
    g = x[lay.geometry].reshape(model.n_joints, K.G)
    out = np.empty((len(q), 3))
    for i in range(len(q)):
        s, t = (0, 0) if labels is None else (labels.setup[i], labels.target[i])
        b = x[lay.base(s)]
        T = trans(b[:3])
        T[:3, :3] = R0s[s] @ rot("z", b[5])[:3, :3] @ rot("y", b[4])[:3, :3] @ rot("x", b[3])[:3, :3]
        path, j = [], int(model.target_rows[t])
        while j >= 0:
            path.append(j)
            j = int(model.parents[j])
        for j in reversed(path):
            a, alpha, d, theta, beta, gamma, b_ = g[j]
            moves = not model.is_fixed[j]
            th = theta + (q[i, j] if moves and not model.prismatic[j] else 0.0)
            dd = d + (q[i, j] if moves and model.prismatic[j] else 0.0)
            if model.pre is not None:
                T = T @ model.pre[j]
            T = (T @ rot("x", alpha) @ trans([a, 0, 0]) @ rot("y", gamma) @ trans([0, b_, 0]) @ rot("z", th)
                 @ trans([0, 0, dd]) @ rot("y", beta))
        out[i] = (T @ np.r_[x[lay.tool(t)], 1.0])[:3]
    return out


def test_chain_matches_a_product_of_transforms_on_chains_trees_and_setups(seed):
    """Chain (axes written out column by column, zero angles skipped) against the textbook 4x4 product, on serial
    chains with beta, prismatic joints, and the tree with fixed rows, xyz/rpy rows, a coupled joint, two targets
    and three setups; every stored frame agrees with the points it makes."""
    from .test_tree import torso_two_arms

    rng = np.random.default_rng(seed)
    for model in _models(seed) + [parse_model(torso_two_arms())]:
        S = 1 if model.n_targets == 1 else 3
        lay = K.layout(model, S)
        x = K.nominal_vector(model, np.c_[rng.uniform(-2000, 2000, (S, 3)), rng.uniform(-0.3, 0.3, (S, 3))], S)
        x = x + rng.normal(0, 1e-2, len(x))
        x[lay.geometry.start + 4: lay.geometry.stop: K.G] += rng.normal(0, 0.01, model.n_joints)  # beta != 0
        q = sample_uniform(model, 12, rng)
        labels = None
        R0 = K.base_rotation(np.r_[0, 0, 0, rng.uniform(-3, 3, 3)], np.eye(3))
        R0s = np.broadcast_to(R0, (S, 3, 3))
        if S > 1:
            labels = K.Labels(rng.integers(0, model.n_targets, 12), np.arange(12) % S)
            R0s = np.stack([K.base_rotation(np.r_[0, 0, 0, rng.uniform(-3, 3, 3)], np.eye(3)) for _ in range(S)])
        chain = K.Chain(model, x, q, R0 if S == 1 else R0s, labels)
        ref = _reference_points(model, x, q, R0s, labels)
        assert np.abs(chain.p - ref).max() < 1e-9 * max(1.0, np.abs(ref).max()), model.name
        target = np.zeros(12, int) if labels is None else labels.target
        tools = x[lay.tools].reshape(-1, 3)[target]
        idx = np.arange(12)
        again = chain.o_beta[chain.end_row, idx] + np.einsum("nab,nb->na", chain.R[chain.end_row, idx], tools)
        assert np.abs(again - ref).max() < 1e-9 * max(1.0, np.abs(ref).max())
        assert np.allclose(np.einsum("rnab,rnac->rnbc", chain.R, chain.R), np.eye(3), atol=1e-12)  # rotations


def test_the_columns_asked_for_are_the_full_jacobians_to_the_bit(seed):
    """Chain.jacobian_columns (a fit's free parameters only) against jacobian()[:, :, idx]: the same bits, on serial
    chains and on the tree with fixed rows, a coupled joint, two targets and three setups, for drawn subsets (each
    kind of row parameter, bases, tools), and into a given buffer."""
    from .test_tree import torso_two_arms

    rng = np.random.default_rng(seed)
    for model in _models(seed) + [parse_model(torso_two_arms())]:
        S = 1 if model.n_targets == 1 else 3
        x = K.nominal_vector(model, np.c_[rng.uniform(-2000, 2000, (S, 3)), rng.uniform(-0.3, 0.3, (S, 3))], S)
        x = x + rng.normal(0, 1e-2, len(x))
        q = sample_uniform(model, 40, rng)
        labels = K.Labels(rng.integers(0, model.n_targets, 40), np.arange(40) % S) if S > 1 else None
        chain = K.Chain(model, x, q, None, labels)
        full = chain.jacobian()
        for share in (0.1, 0.5, 1.0):
            idx = np.flatnonzero(rng.random(len(x)) < share)
            got = chain.jacobian_columns(idx)
            assert got.shape == (40, 3, len(idx))
            assert np.array_equal(got.view(np.uint64), np.ascontiguousarray(full[:, :, idx]).view(np.uint64))
        buf = np.full((len(idx), 40, 3), np.nan)
        assert chain.jacobian_columns(idx, out=buf).base is buf and np.array_equal(buf.transpose(1, 2, 0),
                                                                                  full[:, :, idx])
