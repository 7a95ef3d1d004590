"""k-fold refits as one Gauss-Newton step from the full-data optimum (calib_core/fold_steps.py) against an LM run per
fold, the reference it replaces; and the search's shortcuts that decide a candidate without a full fit."""
import importlib

import numpy as np
import pytest

from calib_core.effects import JointCompliance
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_world import World
from calib_world.scenarios import hide

identify_module = importlib.import_module("calib_core.identify")


def _spring_world(seed: int, sizes: tuple[float, float]):
    """A drawn robot (arm6 or spray7), 80-200 drawn poses, a spring hidden at a size drawn in `sizes` x the noise
    (with wrong mass data): the model, its measurements and the generator that drew them."""
    rng = np.random.default_rng(seed)
    model = parse_model((arm6 if seed % 2 else spray7)())
    world = World(model, seed)
    q = world.sample_joints(int(rng.integers(80, 200)), rng)
    hide(world, "joint_spring", float(rng.uniform(*sizes)), rng, q=q)
    return model, world.measure(q), rng


@pytest.mark.parametrize("loss", [None, "huber"])
def test_one_step_folds_give_the_lm_folds_held_out_distances(loss, seed, monkeypatch):
    """A drawn robot, a drawn spring at a drawn size (with wrong mass data), bad readings for the robust loss: the
    per-pose held-out distances of the one-step folds agree with the LM folds' to a small share of the noise."""
    model, meas, rng = _spring_world(seed, (1.0, 8.0))
    if loss:  # a few readings far off: the fold's own robust weights matter
        bad = rng.choice(meas.n_poses, 3, replace=False)
        meas.points[bad] += rng.normal(0.0, 2.0, (3, 3))
    j = int(rng.integers(1, model.n_joints))
    effects = (JointCompliance((j,)),)
    out = {}
    for one_step in (False, True):
        monkeypatch.setattr(identify_module, "FOLD_STEPS", one_step)
        out[one_step] = identify_module.identify(model, meas, effects=effects, loss=loss, folds=5)
    lm, step = out[False].holdout_residual_mm, out[True].holdout_residual_mm
    noise = float(np.median(out[False].sigma_mm))
    where = f"seed {seed}, {model.joint_names[j]}, loss {loss}"
    assert np.abs(step - lm).max() < 0.05 * noise, (float(np.abs(step - lm).max()), noise, where)
    assert abs(np.sqrt(np.mean(step**2)) / np.sqrt(np.mean(lm**2)) - 1.0) < 1e-3, where


def test_candidates_adding_the_same_displacement_share_one_decision():
    """_same_columns: the same fitted displacement (to 1e-3 of its norm) and F; a different one is not."""
    from calib_core.diagnosis.screening import Candidate
    from calib_core.diagnosis.search import _same_columns

    rng = np.random.default_rng(0)
    fitted, projected = rng.normal(size=50), rng.normal(size=50)

    def cand(f, p, F, effect):
        return Candidate(effect=effect, label="", p_value=0.0, log_p=0.0, F=F, explained=0.1, beyond_chance=0.1,
                         bic=0.0, dof=1, residual_dof=40, effect_rms_mm=1.0, regressor=None, regressor_label="", projected_residual_mm=p,
                         fitted_mm=f)
    a = cand(fitted, projected, 40.0, JointCompliance((1,)))
    assert _same_columns(a, cand(fitted * (1 + 1e-5), projected, 40.0001, JointCompliance((2,))))
    assert not _same_columns(a, cand(fitted + 0.01 * rng.normal(size=50), projected, 40.0, JointCompliance((2,))))
    assert not _same_columns(a, cand(fitted, projected, 44.0, JointCompliance((2,))))


def test_a_given_model_error_is_the_second_fit_in_one_solve(seed):
    """identify(model_error_mm=s): one solve weighted by the noise plus s. Given the model error the two-solve fit
    estimated, it lands on that fit's optimum (the mass steps' shortcut); given another, on another optimum."""
    model, meas, rng = _spring_world(seed, (3.0, 8.0))
    effects = (JointCompliance((int(rng.integers(1, model.n_joints)),)),)
    two = identify_module.identify(model, meas, effects=effects, folds=0)
    assert two.model_error_mm > 0.0, f"seed {seed}: the wrong mass data leave no model error"
    one = identify_module.identify(model, meas, effects=effects, folds=0, model_error_mm=two.model_error_mm)
    std = two.solution.std
    assert np.all(np.abs(one.solution.x - two.solution.x) <= 1e-3 * std + 1e-12), f"seed {seed}"
    assert one.model_error_mm == two.model_error_mm and np.allclose(one.sigma_mm, two.sigma_mm)
    other = identify_module.identify(model, meas, effects=effects, folds=0, model_error_mm=0.0)
    assert np.allclose(other.sigma_mm, meas.noise_sigma_mm()) and not np.allclose(other.solution.x, two.solution.x)
