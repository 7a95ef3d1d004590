import numpy as np
import pytest
from scipy import stats

from calib_core import kinematics as K
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
        if K.G * n + 3 <= i < K.G * n + 6:
            continue
        z[cal.names[i]] = (cal.x[i] - twin.x_true[i]) / cal.solution.std[k]
    return z


@pytest.mark.parametrize("robot", ROBOTS)
def test_exact_recovery_on_noise_free_twin(robot, seed):
    model = parse_model(ROBOTS[robot]())
    twin = Twin(model, seed, repeatability_mm=0.0, tracker_noise=False)
    cal = identify(model, twin.measure(n=150), regularize=False, folds=0)
    n = model.n_joints
    assert np.abs(cal.x[: K.G * n] - twin.x_true[: K.G * n]).max() < 1e-7, f"seed {seed}"
    assert np.abs(cal.x[K.G * n + 6:] - twin.x_true[K.G * n + 6:]).max() < 1e-7  # tool point
    Rb, pb = cal.base_pose()
    assert np.abs(Rb - twin.R0).max() < 1e-10 and np.abs(pb - twin.x_true[K.G * n: K.G * n + 3]).max() < 1e-7
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
    # each parameter within 4.5 reported std: P(|z| > 4.5) = 6.8e-6, a false alarm in 1e4 runs over ~25 parameters.
    # (A rule "at most two past 3" failed a CI run, seed 1381796579 on arm6: A3.theta 4.31 and A4.a 4.21, correlated
    # 0.94, one event counted twice, beside base.x 3.26. Over 200 seeds the largest |z| of a run has the quantiles of
    # 24 independent normals, 3.56 at the 99th percentile: the std is honest.)
    assert np.abs(zs).max() < 4.5, (seed, zs.round(2))
    # and the whole error vector is consistent with the reported covariance: chi-square with p dof
    keep = [k for k, i in enumerate(cal.free) if cal.names[i] in z]
    err = np.array([cal.x[cal.free[k]] - twin.x_true[cal.free[k]] for k in keep])
    chi2 = err @ np.linalg.solve(cal.solution.cov[np.ix_(keep, keep)], err)
    assert chi2 < stats.chi2.ppf(0.9999, len(keep)), (seed, chi2, len(keep))
    m = cal.metrics()
    # sigma0 after the model-error re-weighting is 1 by construction (it could never fail a 0.8..1.6 check);
    # what can fail is sigma0 under the tracker model alone against the twin's real noise (tracker + repeatability)
    assert abs(m["sigma0"] - 1.0) < 0.02 or (m["model_error_mm"] == 0.0 and m["sigma0"] <= 1.0)
    st = cal.sigma_mm if m["model_error_mm"] == 0.0 else np.sqrt(cal.sigma_mm**2 - m["model_error_mm"] ** 2)
    expected = np.sqrt(np.mean((st**2 + twin.repeatability_mm**2) / st**2))
    assert abs(m["sigma0_measurement"] / expected - 1) < 0.15, (seed, m["sigma0_measurement"], expected)
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
    # an RMS over 50 twins has a relative sd of about 1/sqrt(100) = 0.1: every parameter within 5 sd (a factor 1.65
    # either way; a std off by 2x fails), and together within 0.15. Over 100 seeds the worst parameter was 0.66
    # (seed 1728530160, which failed the former "90 % within 0.3"), the RMS 0.97-1.04 on 40 of them.
    assert np.abs(np.log(ratio)).max() < 0.5 and abs(np.sqrt(np.mean(ratio**2)) - 1) < 0.15, (seed, ratio.round(2))


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
    assert np.allclose(parse_model(d["calibrated_model"]).geometry[3], cal.x[3 * K.G: 4 * K.G])


# --- honest uncertainty for every model: unit-invariant, never NaN, never falsely tiny -----------------

def _linear_problem(rng, N=60, p=6):
    """A linear point problem r = y - A x, noise 0.05 per axis: A (N, 3, p), y (N, 3), sigma (N,)."""
    A = rng.normal(size=(N, 3, p))
    sigma = np.full(N, 0.05)
    y = A @ rng.normal(size=p) + rng.normal(0, 0.05, (N, 3))
    return A, y, sigma


def _solve(A, y, sigma, **kw):
    from calib_core.solve import least_squares

    return least_squares(lambda x: (y - A @ x, A), np.zeros(A.shape[2]), sigma, **kw)


@pytest.mark.parametrize("with_prior", [False, True])
def test_rescaling_a_parameter_unit_changes_only_its_std(seed, with_prior):
    """Multiply one Jacobian column by 1e11 (the parameter in a unit 1e11 smaller, like an effect in
    1/(N*mm^2)): that parameter's value and std scale by 1e-11, every other std stays the same."""
    rng = np.random.default_rng(seed)
    A, y, sigma = _linear_problem(rng)
    c = 1e11
    B = A.copy()
    B[:, :, 2] *= c
    prior_std = np.array([np.inf, 10.0, 0.3, np.inf, 5.0, 1.0])
    kw_a = dict(prior=np.zeros(6), prior_std=prior_std) if with_prior else {}
    kw_b = dict(prior=np.zeros(6), prior_std=prior_std * np.r_[1, 1, 1 / c, 1, 1, 1]) if with_prior else {}
    a, b = _solve(A, y, sigma, **kw_a), _solve(B, y, sigma, **kw_b)
    assert np.all(np.isfinite(a.std)) and np.all(np.isfinite(b.std))
    scale = np.r_[1, 1, c, 1, 1, 1]
    np.testing.assert_allclose(b.x * scale, a.x, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(b.std * scale, a.std, rtol=1e-6)


def test_std_covers_the_error_where_a_prior_holds_the_parameter(seed):
    """Weakly seen parameters under a ridge prior, the truth drawn within that prior: the std is the posterior's, so
    (estimate - truth) / std has RMS ~ 1 on them too. The regularised estimator's sandwich covariance (its spread
    alone, without the pull toward the prior) gives RMS z 1.7-3.7 on the two least seen."""
    rng = np.random.default_rng(seed)
    prior_std = np.array([np.inf, np.inf, np.inf, 1.0, 1.0, 1.0])
    z = []
    for _ in range(150):
        A = rng.normal(size=(20, 3, 6)) * np.r_[1.0, 1.0, 1.0, 0.002, 0.005, 0.01]  # the last three barely seen
        x = np.r_[rng.normal(size=3), rng.normal(size=3) * prior_std[3:]]
        y = A @ x + rng.normal(0, 0.05, (20, 3))
        sol = _solve(A, y, np.full(20, 0.05), prior=np.zeros(6), prior_std=prior_std)
        z.append((sol.x - x) / sol.std)
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.8) & (rms < 1.25)), rms


def test_undetermined_direction_is_flagged_not_nan(seed):
    """Two identical columns and no prior: both parameters undetermined (inf std, flagged), the others exact."""
    rng = np.random.default_rng(seed)
    A, y, sigma = _linear_problem(rng)
    A[:, :, 4] = A[:, :, 1]
    sol = _solve(A, y, sigma)
    assert not np.isnan(sol.std).any() and not np.isnan(sol.cov).any()
    assert list(np.flatnonzero(~np.isfinite(sol.std))) == [1, 4] and list(np.flatnonzero(sol.undetermined)) == [1, 4]
    ref = _solve(np.delete(A, 4, axis=2), y, sigma)  # the same problem without the duplicate
    np.testing.assert_allclose(sol.std[[0, 2, 3, 5]], ref.std[[0, 2, 3, 4]], rtol=1e-6)


def test_ridge_prior_on_many_columns_gives_no_nan_std(seed):
    """More parameters than equations, most under a ridge prior (a big smoothing field): every std finite."""
    rng = np.random.default_rng(seed)
    A, y, sigma = _linear_problem(rng, N=15, p=80)
    A[:, :, 3:] *= rng.choice([1e-8, 1.0, 1e6], 77)  # wildly different column scales
    prior_std = np.r_[np.inf, np.inf, np.inf, np.full(77, 0.5)]
    sol = _solve(A, y, sigma, prior=np.zeros(80), prior_std=prior_std)
    assert np.all(np.isfinite(sol.std)) and np.all(sol.std > 0), sol.std


def test_effect_in_tiny_units_keeps_the_geometric_std(seed):
    """Link bending (1/(N*mm^2), ~1e-11) in the model: the geometric std stay those of the geometric fit
    (they collapsed to ~1e-20 mm with an unscaled pseudo-inverse); a ridge field gives no NaN."""
    from calib_core.effects.cartesian_effects import LinkDeflection
    from calib_core.effects.residual import ResidualField

    model = parse_model(spray7())
    meas = Twin(model, seed).measure(n=150)
    geo = identify(model, meas, folds=0)
    g = {p["name"]: p["std"] for p in geo.parameters()}
    for k in (3, 4):
        cal = identify(model, meas, effects=(LinkDeflection((k,)),), folds=0, x_ref=geo.x)
        p = {q["name"]: q["std"] for q in cal.parameters()}
        for name, s in g.items():
            assert p[name] > 0.5 * s, (seed, k, name, p[name], s)
        assert 0 < p[f"J{k + 1}.link_compliance"] < 1e-9
        m = cal.metrics()
        k_eff = len(LinkDeflection((k,)).parameter_names(model))  # carried load and own weight
        assert m["n_parameters"] == m["n_geometric_parameters"] + k_eff == len(cal.free) + k_eff
    field = identify(model, meas, effects=(ResidualField((), length_scale=1.0, prior_std=50.0),), folds=0,
                     x_ref=geo.x)
    assert np.all(np.isfinite(field.solution.std)), (seed, np.isnan(field.solution.std).sum())
    assert all(p["std"] is not None and np.isfinite(p["std"]) for p in field.parameters())


def test_sigma0_checks_the_noise_model(seed):
    """sigma0 of the fit weighted by the tracker model alone is ~1 when the twin's noise is the tracker's,
    and grows when the robot adds repeatability the model does not know; the fitted model error then
    recovers that repeatability and the final sigma0 is 1."""
    model = parse_model(spray7())
    clean = Twin(model, seed, repeatability_mm=0.0).measure(n=150)
    ok = identify(model, clean, folds=0).metrics()
    assert 0.85 < ok["sigma0_measurement"] < 1.15, (seed, ok)
    # s^2 / sigma^2 estimates chi2/dof - 1 (sd sqrt(2/423) = 0.07 here): under 0.25 is 3.6 sd; a fixed 0.015 mm
    # was 1.3 sd for a tracker 5 m away (sigma 0.049 mm: failed at seed 1278205971 with 0.0155)
    noise = float(np.sqrt(np.mean(clean.noise_sigma_mm() ** 2)))
    assert ok["model_error_mm"] < 0.5 * noise, (seed, noise, ok)
    bad = identify(model, Twin(model, seed, repeatability_mm=0.1).measure(n=150), folds=0).metrics()
    assert bad["sigma0_measurement"] > 1.8, (seed, bad)
    assert 0.08 < bad["model_error_mm"] < 0.12, (seed, bad)
    assert abs(bad["sigma0"] - 1.0) < 0.02


def test_answer_says_std_are_conditional_and_counts_all_parameters(seed):
    from calib_core.effects.joint_effects import JointCompliance

    model = parse_model(spray7())
    meas = Twin(model, seed).measure(n=100, payload_kg=[0.0, 20.0])
    d = identify(model, meas, effects=(JointCompliance((2,)), JointCompliance((3,))), folds=0).to_dict()
    assert d["uncertainty"]["conditional_on_model"] is True and d["uncertainty"]["note"]
    assert d["metrics"]["n_parameters"] == d["metrics"]["n_geometric_parameters"] + 2 == len(d["parameters"])
    assert d["warnings"] == [] and d["identifiability"]["complete"] is True


def test_prior_scale_pulls_toward_nominal(seed):
    model = parse_model(spray7())
    meas = Twin(model, seed).measure(n=20)
    default = identify(model, meas, folds=0)
    same = identify(model, meas, folds=0, prior_scale=1.0)
    strong = identify(model, meas, folds=0, prior_scale=1e10)  # prior std 1 um, 1 urad
    np.testing.assert_array_equal(default.x, same.x)
    n = model.n_joints
    nominal = model.geometry.ravel()
    assert np.abs(strong.x[: K.G * n] - nominal).max() < 0.2 * np.abs(default.x[: K.G * n] - nominal).max()


# --- refuse what cannot be calibrated, say what a poor pose set cannot tell -------------------------------

def test_identical_poses_are_refused_by_name(seed):
    model = parse_model(spray7())
    twin = Twin(model, seed)
    q = np.repeat(twin.sample_joints(1), 40, axis=0)
    with pytest.raises(ValueError, match="all 40 poses are the same joint configuration"):
        identify(model, twin.measure(q))
    q[:20] = twin.sample_joints(1)  # two configurations are still not a calibration
    with pytest.raises(ValueError, match="only 2 distinct joint configurations"):
        identify(model, twin.measure(q))


def test_only_the_rail_moving_is_flagged(seed):
    model = parse_model(spray7())
    twin = Twin(model, seed)
    q = np.repeat(twin.sample_joints(1), 100, axis=0)
    q[:, 0] = twin.sample_joints(100)[:, 0]
    cal = identify(model, twin.measure(q))
    ident = cal.to_dict()["identifiability"]
    assert ident["complete"] is False and len(ident["unidentifiable"]) >= 10
    assert ident["frozen_joints"] == ["J2", "J3", "J4", "J5", "J6", "J7"]
    w = cal.to_dict()["warnings"]
    assert any(s.startswith("J2, J3, J4, J5, J6, J7 never moved") for s in w), w
    assert any(f"{len(ident['unidentifiable'])} parameters cannot be identified" in s for s in w), w


@pytest.mark.parametrize("robot,joint", [("spray7", 2), ("spray7", 5), ("arm6", 1)])
def test_a_frozen_joint_is_named(seed, robot, joint):
    model = parse_model(ROBOTS[robot]())
    twin = Twin(model, seed)
    q = twin.sample_joints(150)
    q[:, joint] = q[0, joint]
    cal = identify(model, twin.measure(q))
    ident = cal.identifiability.to_dict()
    name = model.joint_names[joint]
    assert ident["frozen_joints"] == [name] and ident["complete"] is False
    assert ident["unidentifiable"], ident
    assert any(s.startswith(f"{name} never moved") for s in cal.warnings), cal.warnings


def test_rich_pose_set_is_complete_and_silent(seed):
    model = parse_model(arm6())
    cal = identify(model, Twin(model, seed).measure(n=150))
    ident = cal.to_dict()["identifiability"]
    assert ident["complete"] is True and ident["unidentifiable"] == [] and ident["frozen_joints"] == []
    assert cal.to_dict()["warnings"] == []


def test_a_first_fit_stopped_early_gives_the_same_answer(seed):
    """The diagnosis stops each fit's first solve (weighted by the noise alone, for the model error it leaves) at a
    loose test (diagnosis.fitter.MODEL_ERROR_FTOL): where the model error is many times the noise and the weights are
    uneven (a tenth of the readings 20x more precise), that solve converges only linearly. The model error and the
    answer solved from there must be the fully converged ones to well within their own spread: the model error to
    5e-3 of itself (2e-3 at worst over 30 seeds; at a test of 1e-2, 9e-3), every parameter to 1e-3 std, held out to
    1e-5."""
    import dataclasses

    from calib_core.diagnosis.fitter import MODEL_ERROR_FTOL
    from calib_core.effects import JointCompliance

    model = parse_model(spray7())
    meas = Twin(model, seed).measure(n=120)
    rng = np.random.default_rng(seed)
    q = meas.joints
    phase = rng.uniform(0.0, 2 * np.pi, 3)
    smooth = 0.9 * np.column_stack([np.sin(2 * q[:, 1] + phase[0]), np.cos(3 * q[:, 2] + phase[1]),
                                    np.sin(q[:, 1] + q[:, 3] + phase[2])])  # mm: no parameter of the model takes it
    precise = np.where(rng.random(meas.n_poses) < 0.1, 0.05, 1.0)
    meas = dataclasses.replace(meas, points=meas.points + smooth, sigma=meas.noise_sigma_mm() * precise)
    effects = (JointCompliance((1, 2)),)
    full = identify(model, meas, effects=effects)
    early = identify(model, meas, effects=effects, first_ftol=MODEL_ERROR_FTOL)
    assert full.model_error_mm > 10 * float(np.median(meas.noise_sigma_mm())), "the large-residual case this is about"
    assert early.model_error_mm == pytest.approx(full.model_error_mm, rel=5e-3), f"seed {seed}"
    solved = np.r_[full.x[full.free], np.concatenate(full.effect_values)]
    solved_early = np.r_[early.x[early.free], np.concatenate(early.effect_values)]
    assert np.all(np.abs(solved_early - solved) <= 1e-3 * full.solution.std), f"seed {seed}"
    assert early.metrics()["holdout_rms_mm"] == pytest.approx(full.metrics()["holdout_rms_mm"], rel=1e-5)


@pytest.mark.parametrize("loss", [None, "huber"])
def test_a_fields_block_made_once_gives_the_same_fit(seed, monkeypatch, loss):
    """A smooth field's weights move no joint, so their columns of the Jacobian are its bases' own and their block of
    the normal matrix is made once per LM run (and again when a robust loss changes the weights). Drawn seed, a
    bending link beside the field, a tenth of the readings 5 mm off under Huber: the fit and its covariance are those
    of the whole normal matrix made at every step, to rounding."""
    import importlib

    from calib_core.effects.cartesian_effects import LinkDeflection
    from calib_core.effects.residual import ResidualField

    model = parse_model(spray7())
    meas = Twin(model, seed).measure(n=120)
    if loss:
        rng = np.random.default_rng(seed)
        bad = rng.choice(meas.n_poses, meas.n_poses // 10, replace=False)
        meas.points[bad] += rng.normal(0.0, 5.0, (len(bad), 3))
    effects = (LinkDeflection((3,)), ResidualField((), length_scale=None, prior_std=0.5))  # 81 weights
    once = identify(model, meas, effects=effects, folds=3, loss=loss)
    monkeypatch.setattr(importlib.import_module("calib_core.identify"), "CONSTANT_COLUMNS", 10**9)  # whole, each step
    every = identify(model, meas, effects=effects, folds=3, loss=loss)
    assert once.solution.iterations == every.solution.iterations, seed
    np.testing.assert_allclose(once.x, every.x, rtol=1e-9, atol=1e-9, err_msg=str(seed))
    np.testing.assert_allclose(once.solution.std, every.solution.std, rtol=1e-6, err_msg=str(seed))
    np.testing.assert_allclose(once.solution.cov, every.solution.cov, rtol=0,
                               atol=1e-9 * np.abs(every.solution.cov).max(), err_msg=str(seed))
    np.testing.assert_allclose(once.holdout_residual_mm, every.holdout_residual_mm, rtol=1e-9, atol=1e-9)
