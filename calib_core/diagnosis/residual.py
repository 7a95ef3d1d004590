"""What the residual left by the named causes follows, the corrections tried for it (a smooth field, joint-driven
offsets, the targets' shared motion as pose noise) and the `unexplained` finding that reports it."""
from __future__ import annotations

import numpy as np

from .. import shared_motion
from ..effects import Context, Effect, JointCompliance, LoadCompliance, Probe, SessionStep, has_loads
from ..effects.residual import LENGTH_SCALES, ResidualField, field_prior_std
from ..effects.structure import ORDER_NAMES, probes, step_candidates, steps_near
from ..identify import Calibration, pose_folds
from ..io import Measurements
from .evidence import HOLDOUT_ALPHA, _better, _p, holdout_gain, model_error_mm
from .findings import _names
from .fitter import _Fitter
from .masses import _distributed
from .screening import (Candidate, _robust_sigma, _weighted_columns, _weighted_system, f_logsf, fold_predictions,
                        log_p_beyond, screen, weighted_misfit)
from .time_structure import _when


def _follows(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray, alpha: float,
             load_pool: dict[int, LoadCompliance], fit: _Fitter, chosen: list[Effect]) -> list[dict]:
    """What the residual left by `chosen` (fitted: cal) follows: time order (a step or a drift), one joint, the
    load, a workspace region, each a family tested with the same F-test; with several targets per pose, whether
    they move together (shared_motion's rank test); Bonferroni over the families."""
    model = cal.model
    fams = probes(model, meas)
    fams += _distributed(load_pool) if load_pool else []
    if has_loads(model, meas):
        loaded = [j for j in range(model.n_joints) if j in load_pool] or list(np.flatnonzero(model.moving))
        fams.append(JointCompliance(tuple(loaded)))
    # the whole robot shifted, or one joint's zero (a re-homing: a joint offset moves each pose differently, which
    # a rigid shift of the late poses hardly follows)
    moving = list(np.flatnonzero(model.moving))
    steps = step_candidates(meas, moving)
    ranked = screen(cal, meas, sigma, fams + steps, x_ref)
    shared = _shared_motion(cal, meas, sigma, x_ref)
    n_tests = len(fams) + 1 + (shared is not None)
    step_limit = np.log(alpha / n_tests / max(len(steps), 1))
    step = next((c for c in ranked if isinstance(c.effect, SessionStep) and c.log_p <= step_limit), None)
    if step is not None:  # placed exactly, then the simplest kind of step there that the data allow
        near = screen(cal, meas, sigma, steps_near(meas, moving, step.effect.at), x_ref)
        best = _simplest_step(near, step_limit, fit, chosen, cal, x_ref, sigma)
        ranked = sorted([c for c in ranked if not isinstance(c.effect, SessionStep)] + [best], key=lambda c: c.bic)
    together = next((s for s in shared or [] if s.p_value < alpha / n_tests), None)  # the largest significant
    out = []
    for c in ranked:
        is_step = isinstance(c.effect, SessionStep)  # one at most: the exactly placed one
        if c.log_p > (step_limit if is_step else np.log(alpha / n_tests)):
            continue
        if is_step:
            what = f"{ORDER_NAMES[c.effect.source]}: a step of {c.effect.stepped(model)} {_when(c.effect, meas)}"
            if c.effect.source == "row":
                what += "; were the rows measured in this order?"
        elif isinstance(c.effect, (LoadCompliance, JointCompliance)):
            what = "the gravity load on the joints"
        else:
            what = c.effect.describe(model)
        out.append({"what": what, "joints": _names(c.effect, model), "p_value": c.p_value,
                    "share_pct": 100.0 * c.explained, "effect": c.effect})
    if together is not None:
        entry = {"what": shared_motion.describe(together, model), "joints": [model.joint_names[j] for j in
                                                                       together.shared_joints],
                 "p_value": together.p_value, "share_pct": 100.0 * together.share, "shared_rms_mm": together.rms_mm,
                 "family": "shared_by_targets", "effect": together,
                 "effects": [s for s in shared if s.p_value < alpha / n_tests and s.size > 0]}
        out.insert(next((i for i, f in enumerate(out) if f["p_value"] > together.p_value), len(out)), entry)
    return out


def _simplest_step(near: list[Candidate], limit: float, fit: _Fitter, chosen: list[Effect], cal: Calibration,
                   x_ref: np.ndarray, sigma: np.ndarray) -> Candidate:
    """The step among `near` (screened, best first) with the fewest parameters at the best one's place unless the
    best explains more with its extra parameters at log p below `limit` (the bar a step has to pass at all). A large
    step is judged by fits, not tangents: a last joint's zero moves the target along a chord, which the target's
    offset on the flange fits exactly and the joint's tangent does not (arm6's A6 re-homed by 25x the noise: 0.25 %
    of the residual left by the tangent, 0.16 % by the target step)."""
    best = near[0]
    simpler = [c for c in near if c.effect.at == best.effect.at and c.dof < best.dof]
    if not simpler:
        return best
    small = min(simpler, key=lambda c: c.bic)
    if log_p_beyond(best, small) > limit:
        return small
    refit = fit.apart(lambda c: fit(tuple(chosen) + (c.effect,), x_ref, folds=1, model_error_mm=cal.model_error_mm))
    rss = [weighted_misfit(refit(c), sigma) for c in (small, best)]  # weighted as cal is: one solve each
    extra = best.dof - small.dof
    F = (max(rss[0] - rss[1], 0.0) / extra) / max(rss[1] / best.residual_dof, 1e-300)
    return small if f_logsf(F, extra, best.residual_dof) > limit else best


def _shared_motion(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray
                   ) -> list[shared_motion.SharedMotion] | None:
    """shared_motion.shared_motion on the calibration's residual (None with one target per pose)."""
    if not shared_motion.pose_groups(meas, cal.model):
        return None
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    return shared_motion.shared_motion(chain, meas, r.reshape(-1, 3) * sigma[:, None], sigma, Q)


def _with_pose_noise(current: Calibration, fit: _Fitter, meas: Measurements, found: list[shared_motion.SharedMotion]
                     ) -> tuple[Calibration, str] | None:
    """The motions the targets of a pose share (the significant ones, largest share first), weighted as noise of
    each pose in the fit (generalised least squares, identify's `pose_noise`): what no function of the joint values
    predicts then pulls the parameters less toward the poses it happened to hit. The refit and a sentence saying
    so, if held-out poses find it better; else None (Agile Justin: 0.03 mm held out, RESULTS 3.10)."""
    if not found:
        return None
    chain = current.robot.chain(meas.joints, meas)[0]
    noise = shared_motion.pose_noise(chain, meas, found)
    if noise is None:
        return None  # no size: nothing to weigh (and a prior std of 0)
    trial = fit(current.effects, current.x_basis, pose_noise=noise)
    p, _ = holdout_gain(current, trial)
    hb, ha = current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
    if not (_better(current, trial, HOLDOUT_ALPHA) and ha < hb):  # both: fewer outliers can raise the RMS shown
        return None
    sizes = ", ".join(f"{s.motion} {1e3 * s.size:.2f} mrad" if s.unit == "rad" else f"{s.motion} {s.size:.2f} mm"
                      for s in found if s.size > 0)
    return trial, (f"the fit weights it as noise of each pose ({sizes} RMS per pose; generalised least squares): "
                   f"held-out {hb:.3f} -> {ha:.3f} mm, paired {_p(p)}")


def _drive_field(fit, chosen, x_ref, follows) -> tuple[Calibration, Probe] | None:
    """The strongest joint-driven probe the residual follows (the other joints' offsets as harmonics of one joint:
    a cable it pulls), fitted with the geometry and the causes found, as a correction beside the smooth field."""
    probe = next((f["effect"] for f in follows if isinstance(f["effect"], Probe) and f["effect"].family == "drive"),
                 None)
    if probe is None:
        return None
    try:
        return fit(tuple(chosen) + (probe,), x_ref), probe
    except ValueError:
        return None


def _unexplained_finding(model, before, trial, floor, follows, basis, after: Calibration, weighted: str = ""
                         ) -> dict:
    """The `unexplained` entry: how far above the floor, what the residual follows, and which correction (if any)
    held-out poses confirmed: `correction` is "smooth_field", "joint_driven_offsets" or None. `after` is the model
    the entry leaves (the correction, then the shared motion weighted as noise of each pose, which `weighted` says;
    `weighted_as_pose_noise` flags it)."""
    hb = before.metrics()["holdout_rms_mm"]
    ha = trial[0].metrics()["holdout_rms_mm"] if trial else hb  # what the correction alone brings it to
    mb = model_error_mm(before, floor)
    if follows:
        what = "it follows " + "; ".join(f"{f['what']} (explains {f['share_pct']:.0f} %, {_p(f['p_value'])})"
                                         for f in follows[:3])
    elif basis == "repeats":
        what = ("it follows nothing we can test (not time order, no joint, not the load, no workspace region) while "
                "repeated poses agree with each other: look at the measurement setup (instrument, target seating, "
                "the frame between sessions)")
    else:
        what = ("it follows no single thing we can test (not time order, no one joint, not the load, no workspace "
                "region) but it is far too large to be noise: several causes together, or one outside our vocabulary")
    if trial and isinstance(trial[1], Probe):
        correction = "joint_driven_offsets"
        fix = f"offsets of the other joints following it ({trial[1].describe(model)}) bring it to {ha:.3f} mm"
    elif trial:
        correction = "smooth_field"
        fix = f"a smooth joint-space correction field ({trial[1].describe()}) fitted with the geometry brings it to " \
              f"{ha:.3f} mm"
    else:
        correction = None
        fix = "no smooth correction helps on held-out poses, so the model is not extended"
    if any(f.get("family") == "shared_by_targets" for f in follows):
        fix += ("; what the targets of a pose share and no correction of the joints predicts acts as noise of each "
                "pose (the shared joints landing a little differently at each visit, joint values commanded rather "
                "than measured, the base moving): a model of the robot cannot remove it, a reference target on the "
                "shared part measured at every pose or measured joint positions would")
    if weighted:
        fix += "; " + weighted
    hf = after.metrics()["holdout_rms_mm"]
    return {"kind": "unexplained", "form": "unexplained", "joints": [], "correction": correction,
            "weighted_as_pose_noise": bool(weighted), "holdout_rms_before_mm": hb, "holdout_rms_after_mm": hf,
            "gain_pct": 100.0 * (hb - hf) / hb,
            "model_error_before_mm": mb, "model_error_after_mm": model_error_mm(after, floor),
            "follows": [{k: v for k, v in f.items() if k not in ("effect", "effects")} for f in follows],
            "evidence": (f"after the named causes the held-out error ({hb:.3f} mm) is still {hb / floor:.1f}x the "
                         f"noise floor ({floor:.3f} mm) and no named cause explains it; {what}; {fix}"),
            "parameters": []}


def field_scale(current: Calibration, meas: Measurements, x_ref: np.ndarray, folds: int):
    """The length scale of the smooth correction field (effects.residual.LENGTH_SCALES) with the smallest k-fold
    held-out error at the current model's linearisation: the field is linear in its weights and the geometry and
    causes move little beside it, so each scale's folds are exact ridge solves of the weighted system (the current
    model's orthonormal basis free, the field's weights under their prior) on the same folds identify uses. Only the
    chosen scale is then fitted in full (four full fits with folds cost the Motoman 5 of its 10 s)."""
    sigma = _robust_sigma(current, current.sigma_mm)
    r, Q, chain = _weighted_system(current, meas, sigma, x_ref)
    ctx = Context.at(current.model, x_ref, meas, current.R0)
    Jq = chain.joint_jacobian()
    fold = np.repeat(pose_folds(meas, folds), 3)
    prior = field_prior_std(current)
    best = None
    for ls in LENGTH_SCALES:
        C = _weighted_columns(ResidualField((), length_scale=ls, prior_std=prior), ctx, Jq, sigma)[0]
        A = np.hstack([Q, C])
        ridge = np.r_[np.zeros(Q.shape[1]), np.full(C.shape[1], 1.0 / prior**2)]
        pred = fold_predictions(A, r, fold, folds, ridge)
        ms = float(np.mean((((r - pred).reshape(-1, 3) * sigma[:, None]) ** 2).sum(1)))
        if best is None or ms < best[0]:
            best = (ms, ls)
    return best[1]
