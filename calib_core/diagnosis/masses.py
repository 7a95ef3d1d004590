"""Loads and mass data: compliances under a gravity load identified from the data (per joint, spread, lateral),
and the bodies' masses and gravity's direction identified under the compliances found, with their doubt."""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy import special

from .. import kinematics as K
from ..effects import (Context, Effect, JointCompliance, LinkDeflection, LoadCompliance, MountCompliance,
                       TiltedCompliance)
from ..effects.gravity import (MAX_LATERAL_TERMS, LateralCompliance, LateralJointCompliance, _as_tuple, body_parameters,
                               lateral_axes, load_mix_for, mass_step, tilted)
from ..identify import Calibration, widened
from ..io import Measurements
from ..kinematics import _cross
from ..model import RobotModel
from ..parallel import pmap
from .evidence import REFINE_ALPHA, _p, holdout_gain
from .fitter import _Fitter
from .screening import _robust_sigma, _weighted_columns, _weighted_system, orthonormal_basis, weighted_misfit


def _load_pool(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray) -> dict[int, LoadCompliance]:
    """Per joint, the compliance under a gravity load identified from the data (see effects/gravity.py)."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    _, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ref = K.Chain(model, x_ref, meas.joints, cal.R0, meas.labels)
    Jq = chain.joint_jacobian()
    payload = meas.payload is not None and np.ptp(meas.payload) > 0
    out = {}
    for j in range(model.n_joints):
        M = load_mix_for(ref, j, Q, Jq, sigma)
        if M is not None:
            out[j] = LoadCompliance((j,), load_mix=(_as_tuple(M),), payload=payload)
    return out


def _lateral(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray) -> list[Effect]:
    """The lateral elasticity of every joint at once: bearings and links tilting under the bending moment."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    if model.n_joints < 2:
        return []
    _, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ref = K.Chain(model, x_ref, meas.joints, cal.R0, meas.labels)
    joints, mixes = [], []
    for j in range(model.n_joints):
        pair = []
        for axis in lateral_axes(ref, j):
            move = _cross(axis, chain.p - ref.o_beta[j]) * ref.on_path[j][:, None]
            M = load_mix_for(ref, j, Q, move, sigma, axis=axis, max_terms=MAX_LATERAL_TERMS)
            pair.append(() if M is None else _as_tuple(M))
        if any(pair):
            joints.append(j)
            mixes.append(tuple(pair))
    return [LateralCompliance(tuple(joints), load_mix=tuple(mixes))] if len(joints) > 1 else []


def _distributed(load_pool: dict[int, LoadCompliance]) -> list[Effect]:
    """Compliance of every loaded joint at once, load identified: elasticity spread over the whole arm."""
    if len(load_pool) < 2:
        return []
    js = sorted(load_pool)
    return [LoadCompliance(tuple(js), load_mix=tuple(load_pool[j].load_mix[0] for j in js),
                           payload=load_pool[js[0]].payload)]


MASS_STEPS = 12
"""At most this many Gauss-Newton steps of the mass data under the compliances found (each a joint fit of both).
A base 20-30 mrad off level, with first moments that trade with the tilt, took 9-12 on the test tree (8 left 0.55
of the tilt on one draw in 15); most stop after 2-5 (MASS_TOL, TILT_TOL_RAD)."""
MASS_TOL = 0.01
"""The steps stop when no body's mass moves by more than this share of the mean body mass..."""
TILT_TOL_RAD = 1e-4
"""...and gravity's direction by less than this."""
STEP_FTOL = 1e-6
"""LM's test for the fits along the path (each a step, its end fitted in full): the misfits it compares are then within
about 1e-6 of themselves (thousandths of a chi-square unit on Agile Justin), far below MASS_DROP; Justin's mass data
took 3.9 -> 2.8 s of its main process with it."""
MASS_DROP = float(2.0 * special.gammaincinv(0.5, 0.99))  # chi2.ppf(0.99, 1), scipy.stats' arithmetic
"""...or when two steps in a row each lower the weighted misfit (chi-square units) by less than one parameter could at
1 %: on Agile Justin the steps crawl along a valley where the tilt trades with the first moments, 2-4 units a step
for the last six of twelve (10 s of its 34; now 5-7 steps per start, held out the same: 3.553 -> 3.549 mm on split 0).
One small step alone is no stop: a test tree's base 29 mrad off level gained little for a step, then found the tilt
(0.036 mm against the truth where it stopped, 0.007 two steps on)."""


def _on_model_masses(e: Effect) -> Effect:
    """`e` on the model's mass data and gravity, if it carries identified ones."""
    return dataclasses.replace(e, masses=(), gravity=()) if _mass_driven(e) and e.masses else e


def _on_carried_masses(pool: list[Effect], chosen: list[Effect]) -> list[Effect]:
    """The pool's compliances driven by the model's mass data, on the mass data a chosen cause carries (identified
    from these poses) instead: a search that resumes on identified masses judges its candidates on the loads of the
    causes beside them (Agile Justin: the converter guessed T4c's body at 15 kg, 54 kg were identified)."""
    carried = next((e for e in chosen if _mass_driven(e) and e.masses), None)
    if carried is None:
        return pool
    return [dataclasses.replace(e, masses=carried.masses, gravity=carried.gravity)
            if _mass_driven(e) and not e.masses and not getattr(e, "load_coef", ()) else e for e in pool]


def _mass_driven(e: Effect) -> bool:
    """A linear compliance driven by mass data (the model's or identified; a tilted base's spring and a mount too):
    its load is bilinear in compliance and mass."""
    return isinstance(e, (LateralJointCompliance, TiltedCompliance, MountCompliance)) or (
        type(e) is JointCompliance and not e.stiffening)


MASS_NOTE = "the mass data were identified from the data under the compliances found"


def _gravity(e: Effect | None, model: RobotModel) -> np.ndarray:
    """Gravity (3,) m/s^2 in the base frame under which `e` deflects: the direction it carries, else the model's."""
    return np.asarray(e.gravity if e is not None and e.gravity else model.gravity, float)


def _with_mass_doubt(cal: Calibration, fit: _Fitter, model: RobotModel) -> None:
    """Give `cal` the doubt of the mass data its compliances and bent links carry (identified from these poses, or
    the model's, which may be 15 % off): one more mass step fitted beside the model, whose joint covariance and move
    the prediction std propagate (uncertainty.prediction_cov). Without it the std are conditional on the masses, and
    too small where the masses matter (the world's elastic bearings: prediction z 1.3-1.7)."""
    idx = [i for i, e in enumerate(cal.effects) if _mass_driven(e) or isinstance(e, LinkDeflection)]
    if not idx or not model.has_mass:  # identified masses need the model's (they start from them)
        return
    driven = next((cal.effects[i] for i in idx if _mass_driven(cal.effects[i])), None)
    step = mass_step([(cal.effects[i], cal.effect_values[i]) for i in idx], model, _gravity(driven, model))
    try:
        cal.mass_doubt = (step, *widened(cal, fit.meas, [step], fit.loss))
    except (ValueError, np.linalg.LinAlgError):
        return


def _identify_masses(current: Calibration, chosen: list[Effect], findings: list[dict], model: RobotModel,
                     meas: Measurements, fit: _Fitter, notes: list[str]) -> Calibration:
    """Identify the bodies' masses and first moments shared by every compliance found, and the direction of gravity
    in the base frame (deflection = compliance x load(mass, gravity) is bilinear: Gauss-Newton steps, each fitting
    the compliances with a mass-data step beside them, the step's prior 50 % of each model mass and 0.05 rad of
    tilt), from the mass data a cause already carries (a second search may add a cause on the model's), else the
    model's; kept only on 1 % held-out evidence. Mass data 15 % off, or guessed (an elastic humanoid), or a base
    frame that is not level, otherwise leave a load-shaped error behind."""
    idx = [i for i, e in enumerate(chosen) if _mass_driven(e)]
    if not idx or not model.has_mass or meas.tau is not None:
        return current
    phi_model = body_parameters(model)
    carried = next((chosen[i] for i in idx if chosen[i].masses), None)
    phi = phi_model.copy() if carried is None else np.asarray(carried.masses, float)
    g = _gravity(carried, model)
    effects, t = list(chosen), current
    if carried is not None and any((chosen[i].masses, chosen[i].gravity) != (carried.masses, carried.gravity)
                                   for i in idx):  # one set of mass data for all
        effects = [dataclasses.replace(e, masses=carried.masses, gravity=carried.gravity) if i in idx else e
                   for i, e in enumerate(chosen)]
        t = fit(effects, current.x, folds=0)

    def path(scan: bool) -> tuple:
        """The steps from the carried mass data, or (scan) from the best of a ring of tilts (_tilt_scan)."""
        if not scan:
            return _mass_steps(chosen, idx, effects, t, phi, g, phi_model, model, fit, False)
        g_scan = _tilt_scan(t, effects, idx, meas)
        t_scan, effects_scan = t, effects
        if g_scan is not None:
            effects_scan = [dataclasses.replace(e, gravity=tuple(float(v) for v in g_scan)) if i in idx else e
                            for i, e in enumerate(effects)]
            t_scan = fit(effects_scan, t.x, folds=0, model_error_mm=t.model_error_mm)
        return _mass_steps(chosen, idx, effects_scan, t_scan, phi, g if g_scan is None else g_scan, phi_model,
                           model, fit, True)

    try:  # two starts (apart, fit.workers): from a tilt that trades with the first moments the steps can stop in a
        # local minimum
        paths = pmap(fit.apart(path), [False, True], fit.workers, fit.shared)
    except ValueError:
        return current
    _, effects, x = min(paths, key=lambda p: p[0])
    phi, g = np.asarray(effects[idx[0]].masses, float), _gravity(effects[idx[0]], model)
    trial = fit(effects, x)
    p_gain, drop = holdout_gain(current, trial)
    if not (p_gain < REFINE_ALPHA and drop > 0):
        return current
    for i in idx:
        old, chosen[i] = chosen[i], effects[i]
        names = set(chosen[i].parameter_names(model))
        for f in findings:
            if f.get("form") == old.label(model):
                f["form"] = chosen[i].label(model)
                f["parameters"] = [p for p in trial.parameters() if "effect" in p and p["name"] in names]
    hb, ha = current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
    moved = [k for k in np.flatnonzero(phi_model[:, 0] > 0)
             if abs(phi[k, 0] - phi_model[k, 0]) > 0.1 * phi_model[k, 0]]
    shown = ", ".join(f"{model.joint_names[k]} {phi[k, 0]:.3g} kg (model {phi_model[k, 0]:.3g})" for k in moved[:8])
    g0 = np.asarray(model.gravity, float)
    norms = float(np.linalg.norm(g) * np.linalg.norm(g0))
    off_mrad = 1e3 * float(np.arccos(np.clip(g @ g0 / norms, -1.0, 1.0))) if norms > 0 else 0.0
    notes[:] = [n for n in notes if not n.startswith(MASS_NOTE)]  # a second identification replaces the first
    scale = "" if meas.payload is not None and np.ptp(meas.payload) > 0 else (
        " (positions tell masses only in proportion to each other here: no payload of known mass varies, and a "
        "heavier arm on softer joints bends the same, so their common scale is the model's)")
    notes.append(f"{MASS_NOTE} (held-out {hb:.3f} -> {ha:.3f} mm, paired {_p(p_gain)}): "
                 + (shown or "no mass moved by more than 10 %") + (scale if shown else "")
                 + f"; gravity {off_mrad:.1f} mrad off the model's base z (the base frame the geometry defines is not "
                 "exactly level); the compliances' std are conditional on these masses and this gravity (the "
                 "prediction std carry their doubt)")
    return trial


TILT_SCAN_RAD = 0.02
TILT_SCAN_DIRECTIONS = 8
"""The ring of tilts (TILT_SCAN_RAD about TILT_SCAN_DIRECTIONS horizontal axes) a mass identification's second start
is chosen from. A vertical axis carries no load under the model's gravity, so its compliance and a tilt are
bilinear at a saddle there: the Gauss-Newton step from a level base turned gravity by 0.9 mrad where the torso tree
was 25 mrad off level, and the steps stopped (a test world in about 20). The compliances are linear in gravity's
direction given the rest, so each tilt of the ring is judged by a linear solve at the current linearisation."""


def _tilt_scan(t: Calibration, effects: list[Effect], idx: list[int], meas: Measurements) -> np.ndarray | None:
    """Gravity (3,) m/s^2 of the tilt in the ring that leaves the least weighted misfit with the compliances `idx`
    of `effects` re-solved linearly beside the geometry and the other causes (t's linearisation), or None if no tilt
    of the ring beats the gravity they carry."""
    model = t.model
    g = _gravity(effects[idx[0]], model)
    sigma = _robust_sigma(t, t.sigma_mm)
    chain, dp = t.robot.chain(meas.joints, meas)
    ctx = Context.at(model, t.basis_x, meas, t.R0)
    Jq = chain.joint_jacobian()
    geometry = (chain.jacobian_columns(t.free) / sigma[:, None, None]).reshape(3 * len(sigma), -1)
    others = [_weighted_columns(e, ctx, Jq, sigma)[0] for i, e in enumerate(effects) if i not in idx]
    Q = orthonormal_basis(np.concatenate([geometry] + others, axis=1))

    def columns(gravity: np.ndarray) -> np.ndarray:
        B = np.concatenate([_weighted_columns(dataclasses.replace(effects[i], gravity=tuple(gravity)), ctx, Jq,
                                              sigma)[0] for i in idx], axis=1)
        return B - Q @ (Q.T @ B)

    here = columns(g)
    values = np.concatenate([np.asarray(t.effect_values[i], float) for i in idx])
    r = ((meas.points - chain.p - dp) / sigma[:, None]).ravel()
    r = r - Q @ (Q.T @ r) + here @ values  # the compliances' part put back

    def misfit(B: np.ndarray) -> float:
        v = np.linalg.lstsq(B, r, rcond=None)[0]
        return float(np.sum((r - B @ v) ** 2))

    turns = [TILT_SCAN_RAD * np.array([np.cos(a), np.sin(a)])
             for a in 2 * np.pi * np.arange(TILT_SCAN_DIRECTIONS) / TILT_SCAN_DIRECTIONS]
    scores = [misfit(columns(tilted(g, turn))) for turn in turns]
    best = int(np.argmin(scores))
    return tilted(g, turns[best]) if scores[best] < misfit(here) else None


def _mass_steps(chosen, idx, effects, t, phi, g, phi_model, model, fit, tilt_first: bool) -> tuple:
    """Gauss-Newton steps of the mass data and gravity's direction from (phi, g) under the compliances `idx` of
    `chosen`: (misfit, effects, x) of the step whose refit leaves the least on the calibration poses (a tilt that
    trades with the first moments can swing from step to step: Agile Justin). With `tilt_first` the first step
    moves gravity's direction alone (a base 25 mrad off level otherwise went into the first moments and stopped
    there: 0.090 mm against the truth where the noise gives 0.009, one test draw in about 30)."""
    phi, best, was_small = phi.copy(), None, False
    weighting = t.model_error_mm  # every step and refit on the start's weights: comparable misfits, one solve each
    for k in range(MASS_STEPS):
        values = t.effect_values  # the compliances where the step linearises (fitted at the last masses)
        step = mass_step([(effects[i], values[i]) for i in idx], model, g)
        if tilt_first and k == 0:
            step = dataclasses.replace(step, bodies=(), prior=step.prior[-2:])
        t = fit(effects + [step], t.x, folds=0, model_error_mm=weighting, ftol=STEP_FTOL)
        delta, tilt = t.effect_values[-1][:-2].reshape(-1, 4), t.effect_values[-1][-2:]
        phi[list(step.bodies)] += delta
        phi[:, 0] = np.maximum(phi[:, 0], 0.0)
        g = tilted(g, tilt)
        masses = tuple(tuple(float(v) for v in row) for row in phi)
        effects = [dataclasses.replace(e, masses=masses, gravity=tuple(float(v) for v in g)) if i in idx else e
                   for i, e in enumerate(chosen)]
        refit = fit(effects, t.x, folds=0, model_error_mm=weighting, ftol=STEP_FTOL)
        misfit = weighted_misfit(refit)
        small = best is not None and best[0] - misfit < MASS_DROP
        if best is None or misfit < best[0]:
            best = (misfit, effects, refit.x)
        if small and was_small:
            break
        was_small = small
        if step.bodies and np.abs(delta[:, 0]).max() < MASS_TOL * phi_model[list(step.bodies), 0].mean() and \
                np.abs(tilt).max() < TILT_TOL_RAD:
            break
    return best
