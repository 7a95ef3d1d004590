"""The robot's mount tilting under its overturning moment (effects.MountCompliance) against the independent world's
BaseTilt (its own statics and rotation), its mass-data columns against finite differences, and blind."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calib_core.diagnosis import diagnose
from calib_core.effects import Context, MountCompliance
from calib_core.effects.gravity import body_parameters
from calib_core.identify import identify
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_world import World, hide
from calib_world.mechanics import BaseTilt


def _exact_world(doc, seed):
    """A noise-free world whose masses, gravity and geometry are the model's: only the mount differs."""
    model = parse_model(doc())
    world = World(model, seed, geometry_error=0.0, mass_error=0.0, level_error_rad=0.0, noise=False)
    q = world.sample_joints(120, np.random.default_rng((seed, 1)))
    return model, world, q


@pytest.mark.parametrize("doc", [spray7, arm6])
def test_the_form_is_the_worlds_anisotropic_mount(doc, seed):
    """The world turns its base about the gravity-horizontal axes by a drawn 2 x 2 compliance (soft axis at a drawn
    angle, 1-6x stiffer across it) times its own overturning moment (0.3-3 mrad at most). The form's three compliances, fitted beside a
    constant tilt, reproduce the displacement to 1 % and the compliance's two principal values to 2 %."""
    rng = np.random.default_rng((seed, 2))
    model, world, q = _exact_world(doc, seed)
    cal = identify(model, world.measure(q), folds=0)  # the tracker frame: noise-free, the nominal geometry
    meas = world.measure(q)
    ctx = Context.at(model, cal.x, meas, cal.R0)
    e = MountCompliance.for_data(ctx)
    # a tilt of 0.3-3 mrad at the largest moment (a real mount's; the form is its first order)
    c = float(rng.uniform(3e-4, 3e-3)) / np.abs(e.moment(ctx)).max()
    ratio = float(rng.uniform(1.0, 6.0))
    d = world.displacement(BaseTilt(c, ratio, float(rng.uniform(0.0, 180.0))), q, world.columns(q))
    ux, uy = e._swings(ctx)
    A = np.concatenate([ctx.basis(e).cart, ux[:, :, None], uy[:, :, None]], axis=2).reshape(-1, 5)
    v, *_ = np.linalg.lstsq(A, d.ravel(), rcond=None)
    left = d.ravel() - A @ v
    assert np.sqrt(np.mean(left**2)) < 0.01 * np.sqrt(np.mean(d**2)), (seed, c, ratio)
    C = np.array([[v[0], v[2]], [v[2], v[1]]])
    assert np.allclose(np.sort(np.linalg.eigvalsh(C)), np.sort([c / ratio, c]), rtol=0.02, atol=0.0), (seed, C, c, ratio)


def test_the_mass_columns_are_the_derivative_of_the_tilt(seed):
    """MassStep's columns for the mount: the displacement per unit of a drawn body's mass and first moment equals the
    finite difference of the form on the changed mass data (the moment is linear in them)."""
    rng = np.random.default_rng(seed)
    model, world, q = _exact_world(arm6, seed)
    meas = world.measure(q)
    ctx = Context.at(model, identify(model, meas, folds=0).x, meas)
    v = rng.uniform(1e-7, 1e-6, 3) * np.array([1, 1, 0.3])
    phi = body_parameters(model)
    k = int(rng.choice(np.flatnonzero(phi[:, 0] > 0)))
    base = dataclasses.replace(MountCompliance(), masses=tuple(map(tuple, phi)))
    cols = base.mass_columns(ctx, v, (k,), np.asarray(model.gravity))
    for c, h in enumerate((1e-2, 10.0, 10.0, 10.0)):
        moved = phi.copy()
        moved[k, c] += h
        fd = (dataclasses.replace(base, masses=tuple(map(tuple, moved))).basis(ctx).cart @ v
              - base.basis(ctx).cart @ v) / h
        assert np.allclose(cols[:, :, c], fd, rtol=1e-6, atol=1e-6 * np.abs(cols).max()), (seed, k, c)


def test_a_soft_mount_is_named_blind_and_nothing_on_a_stiff_one(seed):
    """arm6 on a mount 1-6x stiffer one way than the other, the tilt's unabsorbable part 3-8x the noise: the answer
    names base_compliance, and its model predicts fresh poses within 0.6x the noise; the same setting with no tilt
    names nothing of the kind."""
    rng = np.random.default_rng(seed)
    model = parse_model(arm6())
    size = float(np.exp(rng.uniform(np.log(3.0), np.log(8.0))))
    for hidden in (size, 0.0):
        world = World(model, seed)
        info = hide(world, "mount_compliance", hidden, rng)
        d = diagnose(model, world.measure(info["q"]))
        kinds = [f["kind"] for f in d.findings]
        if hidden == 0.0:
            assert "base_compliance" not in kinds, (seed, kinds)
            continue
        assert "base_compliance" in kinds, (seed, size, info["cause"], kinds, d.explanation)
        fresh = world.sample_joints(100, rng)
        err = np.linalg.norm(d.calibration.predict(fresh) - world.true_points(fresh), axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.6 * world.noise_rms_mm(fresh), (seed, size, info["cause"])


def test_a_mount_tilting_beyond_a_real_one_is_said_to_be_a_correction(seed):
    """The mount's compliance fitted on a world with a soft mount, then set to a drawn multiple of the plausible turn at
    the largest moment: up to the limit the finding is physical, beyond it the answer says the robot would turn on
    its mount by more than a real mount gives, and reads it as a correction."""
    from calib_core.diagnosis import PLAUSIBLE_TURN_RAD
    from calib_core.diagnosis.findings import _judge_sizes

    rng = np.random.default_rng(seed)
    model = parse_model(arm6())
    world = World(model, seed)
    info = hide(world, "mount_compliance", float(rng.uniform(3.0, 8.0)), rng)
    meas = world.measure(info["q"])
    cal = identify(model, meas, effects=(MountCompliance(),), folds=0)
    m = MountCompliance().moment(Context.at(model, cal.basis_x, meas, cal.R0))
    for factor, physical in ((rng.uniform(0.05, 0.9), True), (rng.uniform(1.1, 20.0), False)):
        cal.solution.x[-3:] = factor * PLAUSIBLE_TURN_RAD / np.linalg.norm(m, axis=1).max() * np.array([1.0, 1.0, 0.0])
        finding = {"kind": "base_compliance", "joints": [], "evidence": "a mount",
                   "parameters": [{"name": n} for n in MountCompliance().parameter_names(model)]}
        _judge_sizes(cal, [finding], meas)
        where = f"the mount at {factor:.2f}x the plausible turn, seed {seed}: {finding}"
        assert finding.get("physical", True) is physical, where
        assert ("the robot on its mount by up to" in finding["evidence"]) is (not physical), where
