"""effects.Context.at and Context.basis: one context per model, poses, geometry and R0 among the last few asked, each
effect's basis made once in it and handed out read-only, the same numbers as a fresh context's; and screening's F
tail (screening.f_logsf) against scipy.stats.f.logsf."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from calib_core import kinematics as K
from calib_core.diagnosis.screening import f_logsf
from calib_core.effects import Context, candidates
from calib_core.effects.base import CONTEXTS
from calib_core.model import parse_model
from calib_core.robots import spray7
from calib_world import World


@pytest.fixture(scope="module")
def setting():
    model = parse_model(spray7())
    world = World(model, 3)
    q = world.sample_joints(40, np.random.default_rng(3))
    meas = world.measure(q, payload_kg=np.resize([0.0, 10.0], 40))
    return model, meas, K.nominal_vector(model)


def test_one_context_per_model_poses_geometry_and_frame(setting):
    model, meas, x = setting
    ctx = Context.at(model, x, meas)
    assert Context.at(model, x.copy(), meas) is ctx  # equal values, another array
    moved = x.copy()
    moved[0] += 1e-9
    assert Context.at(model, moved, meas) is not ctx
    assert Context.at(model, x, meas, np.eye(3)) is not ctx
    other = meas.subset(np.arange(meas.n_poses))  # the same values, other poses object
    assert Context.at(model, x, other) is not ctx
    written = meas.subset(np.arange(meas.n_poses))
    again = Context.at(model, x, written)
    written.joints[0, 0] += 0.1  # the same object, its poses written in place
    assert Context.at(model, x, written) is not again
    again = Context.at(model, x, written)
    written.payload[1] += 5.0  # ... or a column an effect reads (a load, a temperature)
    assert Context.at(model, x, written) is not again
    for k in range(CONTEXTS):  # the oldest goes once CONTEXTS others were asked since
        bent = x.copy()
        bent[1] += 1e-6 * (k + 1)
        Context.at(model, bent, meas)
    assert Context.at(model, x, meas) is not ctx


def test_a_prediction_follows_a_column_written_in_place():
    """A calibrated drift, and the temperature of the same Measurements object written in place between two
    predictions: the second follows the new temperature (it gave the first prediction again: the context and its
    bases were kept by the object and the joints alone)."""
    from calib_core.calibrated import CalibratedRobot
    from calib_core.effects.cartesian_effects import ThermalDrift
    from calib_core.io import Measurements

    model = parse_model(spray7())
    drift = ThermalDrift((), source="temperature", ref=20.0, lo=18.0, hi=24.0)
    robot = CalibratedRobot(model, K.nominal_vector(model), np.eye(3), (drift,), (np.array([0.1, 0.0, 0.0, 0.0]),))
    q = World(model, 5).sample_joints(10, np.random.default_rng(5))
    cols = Measurements(joints=q, points=np.zeros((10, 3)), temperature=np.full(10, 20.0))
    first = robot.predict(q, cols)
    cols.temperature[:] = 22.0
    assert np.allclose(robot.predict(q, cols) - first, [0.2, 0.0, 0.0])


def test_a_basis_is_made_once_read_only_and_equals_a_fresh_one(setting):
    model, meas, x = setting
    ctx = Context.at(model, x, meas)
    fresh = Context(model, K.Chain(model, x, meas.joints, None, meas.labels), meas)
    named, _ = candidates(model, meas)
    assert named
    for e in named:
        b = ctx.basis(e)
        assert ctx.basis(e) is b and ctx.made(e) is b
        ref = e.basis(fresh)
        for got, want in ((b.joint, ref.joint), (b.cart, ref.cart), (b.regressor, ref.regressor)):
            assert (got is None) == (want is None), e
            if got is not None:
                assert np.array_equal(got, want), e
                assert not got.flags.writeable, e
                with pytest.raises(ValueError):
                    got[...] = 0.0
    # an equal effect that is another object gets its own entry (the search tells candidates apart by identity)
    twin = type(named[0])(**{f: getattr(named[0], f) for f in named[0].__dataclass_fields__})
    assert ctx.made(twin) is None


def test_the_f_tail_is_scipys():
    """Drawn degrees of freedom and statistics, from 0 to far in the tail (where the log p underflows to -inf)."""
    seed = int(np.random.default_rng().integers(2**31))
    rng = np.random.default_rng(seed)
    for _ in range(2000):
        dfn, dfd = int(rng.integers(1, 80)), int(rng.integers(1, 5000))
        F = 0.0 if rng.random() < 0.02 else float(np.exp(rng.uniform(-10.0, 12.0)))
        want, got = float(stats.f.logsf(F, dfn, dfd)), f_logsf(F, dfn, dfd)
        assert got == want or (np.isinf(want) and got == want), (seed, F, dfn, dfd, want, got)


def test_contexts_asked_from_several_threads_at_once(setting):
    """A service without compute processes predicts in several route threads: Context.at from eight threads at once
    never fails and always gives a context of the geometry asked for."""
    from concurrent.futures import ThreadPoolExecutor

    model, meas, x = setting

    def ask(i: int) -> bool:
        xi = x.copy()
        xi[0] += 1e-6 * (i % 6)
        return all(np.array_equal(Context.at(model, xi, meas).chain.x, xi) for _ in range(30))

    with ThreadPoolExecutor(8) as pool:
        assert all(pool.map(ask, range(48)))
