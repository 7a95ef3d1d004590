import numpy as np
import pytest
from scipy import stats

from calib_core.identify import evaluate, identify
from calib_core.model import parse_model
from calib_core.robots import arm6, spray7
from calib_core.twin import Twin

ROBOTS = {"spray7": spray7, "arm6": arm6}


def _compare(cal, twin):
    """(estimate - truth) / std for every solved parameter that has a direct truth (not base angles)."""
    n = cal.model.n_joints
    z = {}
    for k, i in enumerate(cal.free):
        if 5 * n + 3 <= i < 5 * n + 6:
            continue
        z[cal.names[i]] = (cal.x[i] - twin.x_true[i]) / cal.solution.std[k]
    return z


@pytest.mark.parametrize("robot", ROBOTS)
def test_exact_recovery_on_noise_free_twin(robot, seed):
    model = parse_model(ROBOTS[robot]())
    twin = Twin(model, seed, repeatability_mm=0.0, tracker_noise=False)
    cal = identify(model, twin.measure(n=150), regularize=False, folds=0)
    n = model.n_joints
    assert np.abs(cal.x[: 5 * n] - twin.x_true[: 5 * n]).max() < 1e-7, f"seed {seed}"
    assert np.abs(cal.x[5 * n + 6:] - twin.x_true[5 * n + 6:]).max() < 1e-7  # tool point
    Rb, pb = cal.base_pose()
    assert np.abs(Rb - twin.R0).max() < 1e-10 and np.abs(pb - twin.x_true[5 * n: 5 * n + 3]).max() < 1e-7
    held_out = twin.measure(n=100)
    assert evaluate(cal, held_out)["max_mm"] < 1e-6


def test_redundant_errors_are_absorbed_exactly(seed):
    """Errors on every parameter (redundant ones too): values differ, predictions still exact."""
    model = parse_model(spray7())
    twin = Twin(model, seed, repeatability_mm=0.0, tracker_noise=False, all_parameters=True)
    cal = identify(model, twin.measure(n=150), regularize=False, folds=0)
    assert evaluate(cal, twin.measure(n=100))["max_mm"] < 1e-6, f"seed {seed}"


@pytest.mark.parametrize("robot", ROBOTS)
def test_noisy_estimates_lie_within_reported_uncertainty(robot, seed):
    model = parse_model(ROBOTS[robot]())
    twin = Twin(model, seed)
    meas = twin.measure(n=150)
    cal = identify(model, meas, folds=5)
    z = _compare(cal, twin)
    zs = np.array(list(z.values()))
    # each parameter within its reported 3-sigma (with ~25 correlated parameters allow two past 3, none past 4.5)
    assert (np.abs(zs) > 3).sum() <= 2 and np.abs(zs).max() < 4.5, (seed, zs.round(2))
    # and the whole error vector is consistent with the reported covariance: chi-square with p dof
    keep = [k for k, i in enumerate(cal.free) if cal.names[i] in z]
    err = np.array([cal.x[cal.free[k]] - twin.x_true[cal.free[k]] for k in keep])
    chi2 = err @ np.linalg.solve(cal.solution.cov[np.ix_(keep, keep)], err)
    assert chi2 < stats.chi2.ppf(0.9999, len(keep)), (seed, chi2, len(keep))
    m = cal.metrics()
    assert 0.8 < m["sigma0"] < 1.6  # the noise model (tracker + repeatability) is about right
    assert m["rms_mm"] <= m["holdout_rms_mm"] < 1.5 * twin.noise_rms_mm(meas.points)


@pytest.mark.slow
def test_reported_std_matches_spread_over_50_noisy_twins(seed):
    model = parse_model(spray7())
    twin = Twin(model, seed)
    q = twin.sample_joints(150)
    errors, stds = [], []
    for _ in range(50):
        cal = identify(model, twin.measure(q), folds=0)
        z = _compare(cal, twin)
        errors.append([z[k] * s for k, s in zip(z, cal.solution.std)])
        stds.append(cal.solution.std[: len(z)])
    errors, stds = np.array(errors), np.array(stds)
    ratio = np.sqrt((errors**2).mean(0)) / stds.mean(0)  # observed spread / reported std, per parameter
    assert np.all(np.abs(ratio - 1) < 0.3) or (np.mean(np.abs(ratio - 1) < 0.3) >= 0.9
                                               and abs(np.sqrt(np.mean(ratio**2)) - 1) < 0.15), (seed, ratio.round(2))


def test_robust_loss_names_the_outliers_and_ignores_them(seed):
    model = parse_model(spray7())
    twin = Twin(model, seed)
    meas = twin.measure(n=150)
    rng = np.random.default_rng(seed)
    bad = rng.choice(150, 6, replace=False)
    meas.points[bad] += rng.normal(0, 1, (6, 3)) * 3.0 + 2.0  # gross errors of a few mm (beam break, wrong SMR)
    plain = identify(model, meas, folds=0)
    robust = identify(model, meas, loss="huber", folds=0)
    cauchy = identify(model, meas, loss="cauchy", folds=0)
    truth = {meas.point_ids[i] for i in bad}
    for fit in (robust, cauchy):  # every planted outlier is named; at most one 5-sigma false alarm
        named = set(fit.metrics()["outliers"])
        assert truth <= named and len(named - truth) <= 1, (seed, sorted(named), sorted(truth))
    clean = twin.measure(n=200)
    assert evaluate(robust, clean)["rms_mm"] < 0.6 * evaluate(plain, clean)["rms_mm"]


def test_sigma_column_weights_the_fit(seed):
    model = parse_model(spray7())
    twin = Twin(model, seed)
    meas = twin.measure(n=150)
    rng = np.random.default_rng(seed)
    noisy = rng.random(150) < 0.5
    meas.points[noisy] += rng.normal(0, 1.0, (noisy.sum(), 3))  # half the poses 1 mm worse
    unweighted = identify(model, meas, folds=0)
    meas.sigma = np.where(noisy, 1.0, 0.03)
    weighted = identify(model, meas, folds=0)
    clean = twin.measure(n=200)
    assert evaluate(weighted, clean)["rms_mm"] < 0.7 * evaluate(unweighted, clean)["rms_mm"]


def test_too_few_poses_is_a_clear_error():
    model = parse_model(spray7())
    with pytest.raises(ValueError, match="more poses"):
        identify(model, Twin(model, 0).measure(n=8))


def test_restricting_free_parameters(seed):
    model = parse_model(spray7())
    cal = identify(model, Twin(model, seed).measure(n=60), free=("base", "tool"), folds=0)
    assert sorted(cal.names[i].split(".")[0] for i in cal.free) == ["base"] * 6 + ["tool"] * 3


def test_answer_has_units_and_values_in_model_units(seed):
    model = parse_model(spray7())
    cal = identify(model, Twin(model, seed).measure(n=100))
    d = cal.to_dict()
    p = {e["name"]: e for e in d["parameters"]}
    assert p["J4.a"]["unit"] == "mm" and abs(p["J4.a"]["value"] - 1350) < 60
    assert p["J3.alpha"]["unit"] == "deg" and abs(p["J3.alpha"]["value"] + 90) < 3
    assert set(d["metrics"]) >= {"n_poses", "rms_mm", "max_mm", "holdout_rms_mm"}
    assert np.allclose(parse_model(d["calibrated_model"]).geometry[3], cal.x[15:20])
