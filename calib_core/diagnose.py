"""Find what the geometric model gets wrong, name the cause, extend the model, prove the gain held out.

Greedy and repeated: at the current model (geometry + effects found so far) every candidate cause is
scored by the linearised F-test of adding its columns to the coupled Jacobian (Bonferroni over the
candidates) and ranked by BIC; the best significant one whose unexplained size is at least the noise floor is refitted
jointly with everything else, kept if its k-fold held-out RMS improves, and the search looks again.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import stats

from . import kinematics as K
from .effects import Context, Effect, candidates
from .effects.residual import PRIOR_STD_MM, ResidualField, fit_residual_field
from .identify import Calibration, identify, tracker_sigma_mm
from .io import Measurements
from .model import RobotModel

ALPHA = 0.01
"""Family-wise false-alarm rate of one search round (Bonferroni over the candidates)."""
FLOOR_FACTOR = 1.0
"""A cause whose unexplained RMS, in the fit and on held-out poses (sqrt of the drop in mean square error),
is below FLOOR_FACTOR x noise floor is not a finding."""
DEFAULT_REPEATABILITY_MM = 0.02
"""Pose repeatability assumed when the data holds no repeated poses (ISO 9283 RP of an industrial robot)."""
MIN_EXCESS_FRACTION = 0.2
"""A named cause must remove at least this fraction of the held-out mean square error above the floor;
smaller shares are what a wrong cause picks up from a true one outside the vocabulary."""
NAMED_SHARE = 0.4
"""A named cause must explain at least this share of what a smooth joint-space field explains."""
LOOKALIKE = 0.8
MAX_LOOKALIKES = 4
INDISTINGUISHABLE = 1.02
"""Rivals explaining at least LOOKALIKE of the winner's share are refitted and judged on held-out poses."""
MAX_FINDINGS = 5
UNEXPLAINED_RATIO = 1.25
"""Held-out RMS above this multiple of the floor after the named causes means structure is left."""


def noise_floor_mm(meas: Measurements, sigma: np.ndarray, repeatability_mm: float | None = None) -> tuple[float, str]:
    """RMS 3-D distance a perfect model would leave: tracker sigma plus pose repeatability.

    Repeatability comes from repeated poses in the data when there are at least five, else the default."""
    how = "given"
    if repeatability_mm is None:
        rep = _repeatability_from_repeats(meas)
        repeatability_mm, how = (rep, "from repeated poses") if rep is not None else (DEFAULT_REPEATABILITY_MM, "assumed")
    floor = float(np.sqrt(3 * np.mean(sigma**2) + 3 * repeatability_mm**2))
    return floor, f"tracker sigma {np.sqrt(np.mean(sigma**2)) * 1000:.0f} um per axis, repeatability " \
                  f"{repeatability_mm * 1000:.0f} um per axis ({how})"


def _repeatability_from_repeats(meas: Measurements) -> float | None:
    q = np.round(meas.joints, 6)
    _, inv, counts = np.unique(q, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    groups = np.flatnonzero(counts > 1)
    if len(groups) < 5:
        return None
    dev = []
    for g in groups:
        pts = meas.points[inv == g]
        dev.append(pts - pts.mean(0))
    dev = np.vstack(dev)
    dof = sum(counts[g] - 1 for g in groups)
    var_tracker = 0.0  # the repeat spread already holds the tracker noise: subtract nothing, report total
    return float(np.sqrt(max((dev**2).sum() / (3 * dof) - var_tracker, 0.0)))


@dataclass
class Candidate:
    effect: Effect
    label: str
    p_value: float
    log_p: float
    F: float
    explained: float  # fraction of the weighted residual sum of squares it explains
    bic: float  # Bayesian information criterion of the model with it: ranks candidates past p underflow
    effect_rms_mm: float  # RMS of the part of its displacement the current model cannot absorb
    regressor: np.ndarray
    regressor_label: str
    projected_residual_mm: np.ndarray  # residual along the effect's direction, per pose
    fitted_mm: np.ndarray  # the effect's fitted displacement along the same direction


@dataclass
class Diagnosis:
    calibration: Calibration  # the final (extended) model
    geometric: Calibration
    nominal: Calibration  # the nominal model with only the tracker frame and tool registered
    noise_floor_mm: float
    noise_note: str
    findings: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    explanation: str = ""

    def to_dict(self) -> dict:
        g = self.geometric.metrics()
        return {
            "noise_floor_mm": self.noise_floor_mm,
            "noise_floor_basis": self.noise_note,
            "nominal": {k: self.nominal.metrics()[k] for k in ("rms_mm", "max_mm", "holdout_rms_mm", "holdout_max_mm")},
            "geometric": {"rms_mm": g["rms_mm"], "holdout_rms_mm": g["holdout_rms_mm"], "max_mm": g["max_mm"],
                          "holdout_max_mm": g["holdout_max_mm"]},
            "findings": self.findings,
            "not_findings": self.rejected,
            "notes": self.notes,
            "explanation": self.explanation,
            "per_pose": {
                "point": list(self.calibration.point_ids),
                "geometric_holdout_mm": self.geometric.holdout_residual_mm.tolist(),
                "final_holdout_mm": self.calibration.holdout_residual_mm.tolist(),
            },
        }


def _weighted_system(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray):
    """Weighted residual (m,), orthonormal basis of the current model's Jacobian (m, r), and the chain."""
    model = cal.model
    dq, dp = cal.robot.effect_offsets(meas.joints, meas) if cal.effects else (0.0, 0.0)
    chain = K.Chain(model, cal.x, meas.joints + dq, cal.R0)
    r = (meas.points - chain.p - dp) / sigma[:, None]
    cols = [chain.jacobian()[:, :, cal.free]]
    if cal.effects:
        from .identify import effect_bases

        Pq, Pp = effect_bases(model, meas, list(cal.effects), x_ref, cal.R0)
        cols.append(np.einsum("nij,njk->nik", chain.joint_jacobian(), Pq) + Pp)
    J = (np.concatenate(cols, axis=2) / sigma[:, None, None]).reshape(len(r.ravel()), -1)
    U, s, _ = np.linalg.svd(J, full_matrices=False)
    Q = U[:, s > s[0] * 1e-10]
    return r.ravel(), Q, chain


def _weighted_columns(e: Effect, ctx: Context, Jq: np.ndarray, sigma: np.ndarray):
    """The effect's columns of the coupled Jacobian, weighted, (m, k), and its basis."""
    b = e.basis(ctx)
    k = len(e.parameter_names(ctx.model))
    C = np.zeros((ctx.meas.n_poses, 3, k))
    if b.joint is not None:
        C += np.einsum("nij,njk->nik", Jq, b.joint)
    if b.cart is not None:
        C += b.cart
    return (C / sigma[:, None, None]).reshape(-1, k), b


def screen(cal: Calibration, meas: Measurements, sigma: np.ndarray, pool: list[Effect], x_ref: np.ndarray,
           alpha: float) -> tuple[list[Candidate], float]:
    """Score every candidate by the F-test of adding it to the current model (linearised at its solution).

    Also returns the share of the residual a smooth joint-space field (ridge) explains: a named cause
    that explains far less than the field is only picking up part of a broader structure."""
    model = cal.model
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ctx = Context(model, K.Chain(model, x_ref, meas.joints, cal.R0), meas)
    Jq = chain.joint_jacobian()
    m, p = len(r), Q.shape[1]
    rss = float(r @ r)
    out = []
    for e in pool:
        Cw, b = _weighted_columns(e, ctx, Jq, sigma)
        k = Cw.shape[1]
        Cp = Cw - Q @ (Q.T @ Cw)
        sv = np.linalg.svd(Cp, compute_uv=False)
        if sv[0] <= 1e-6 * np.linalg.norm(Cw) or np.any(sv < 1e-6 * sv[0]):
            continue  # the current model absorbs (part of) it: not testable as a separate cause
        theta, *_ = np.linalg.lstsq(Cp, r, rcond=None)
        fit = Cp @ theta
        drss = float(fit @ fit)
        dof2 = m - p - k
        F = (drss / k) / max((rss - drss) / dof2, 1e-300)
        log_p = float(stats.f.logsf(F, k, dof2))
        disp = fit.reshape(-1, 3) * sigma[:, None]  # mm
        direction = disp / np.maximum(np.linalg.norm(disp, axis=1, keepdims=True), 1e-300)
        res_mm = r.reshape(-1, 3) * sigma[:, None]
        out.append(Candidate(
            effect=e, label=e.label(model), p_value=float(np.exp(log_p)), log_p=log_p, F=float(F),
            explained=drss / rss, bic=m * np.log(max(rss - drss, 1e-300) / m) + k * np.log(m),
            effect_rms_mm=float(np.sqrt(np.mean((disp**2).sum(1)))),
            regressor=b.regressor, regressor_label=b.regressor_label,
            projected_residual_mm=(res_mm * direction).sum(1), fitted_mm=(disp * direction).sum(1)))
    field = ResidualField((), length_scale=1.0, prior_std=max(PRIOR_STD_MM, 2.0 * cal.metrics()["holdout_rms_mm"]))
    Cw, _ = _weighted_columns(field, ctx, Jq, sigma)
    Cp = Cw - Q @ (Q.T @ Cw)
    ridge = np.eye(Cp.shape[1]) / field.prior_std**2
    fit = Cp @ np.linalg.solve(Cp.T @ Cp + ridge, Cp.T @ r)
    return sorted(out, key=lambda c: c.bic), float(fit @ fit) / rss


def _best_of_lookalikes(c, trial, ranked, threshold, model, meas, chosen, loss, folds, x_ref, share=None):
    """Some causes look alike over a limited range (a scale error and a first harmonic, a short link's
    bending and the compliance of the joint before it): among the significant candidates that explain
    nearly as much as the winner, keep the best on held-out poses and name the ones it cannot beat."""
    tried = [(c, trial)]
    share = LOOKALIKE if share is None else share
    rivals = [a for a in ranked if a is not c and a.log_p <= threshold and a.explained >= share * c.explained]
    for alt in rivals[:MAX_LOOKALIKES]:
        tried.append((alt, identify(model, meas, effects=tuple(chosen + [alt.effect]), loss=loss, folds=folds,
                                    x_ref=x_ref)))
    tried.sort(key=lambda t: t[1].metrics()["holdout_rms_mm"])
    best = tried[0][1].metrics()["holdout_rms_mm"]
    alike = [{"kind": a.effect.kind, "joints": [model.joint_names[j] for j in a.effect.joints],
              "holdout_rms_after_mm": t.metrics()["holdout_rms_mm"]}
             for a, t in tried[1:] if t.metrics()["holdout_rms_mm"] <= INDISTINGUISHABLE * best]
    return tried[0][0], tried[0][1], alike


def _revisit(findings, chosen, current, pool, model, meas, sigma, alpha, loss, folds, floor):
    """Greedy order can mislead when causes overlap: test each finding again against its look-alikes with
    every other finding in the model; swap it for a better one, or name the ones it cannot beat."""
    for k in range(len(chosen)):
        others = chosen[:k] + chosen[k + 1:]
        base = identify(model, meas, effects=tuple(others), loss=loss, folds=folds, x_ref=current.x)
        ranked, _ = screen(base, meas, sigma, [e for e in pool if e not in others], current.x, alpha)
        mine = next((c for c in ranked if c.effect == chosen[k]), None)
        if mine is None:
            continue
        threshold = np.log(alpha / max(len(pool), 1))
        c, trial, alike = _best_of_lookalikes(mine, current, ranked, threshold, model, meas, others, loss, folds,
                                              current.x, share=0.5)
        if c is not mine:
            chosen[k] = c.effect
            current = identify(model, meas, effects=tuple(chosen), loss=loss, folds=folds, x_ref=current.x)
        findings[k] = _finding(c, model, base, current, floor, alike)
    return current


def _finding(c: Candidate, model: RobotModel, before: Calibration, after: Calibration, floor: float,
             alike: list[dict]) -> dict:
    hb, ha = before.metrics()["holdout_rms_mm"], after.metrics()["holdout_rms_mm"]
    e = c.effect
    params = [p for p in after.parameters() if p.get("effect") == e.kind
              and p["name"] in e.parameter_names(model)]
    shown = ", ".join(f"{p['name']} = {p['value']:.4g} +/- {p['std']:.2g} {p['unit']}" for p in params[:4])
    evidence = (f"{e.explain(model)}: it explains {100 * c.explained:.0f} % of the remaining residual "
                f"(R = {np.sqrt(c.explained):.2f}, F = {c.F:.1f}, p = {c.p_value:.1e}); its unexplained size is "
                f"{c.effect_rms_mm:.3f} mm RMS against a noise floor of {floor:.3f} mm; {shown}")
    out = {"kind": e.kind, "joints": [model.joint_names[j] for j in e.joints],
           "holdout_rms_before_mm": hb, "holdout_rms_after_mm": ha, "gain_pct": 100.0 * (hb - ha) / hb,
           "evidence": evidence, "effect_rms_mm": c.effect_rms_mm, "p_value": c.p_value, "parameters": params,
           "plot": {"x": c.regressor.tolist(), "x_label": c.regressor_label,
                    "residual_mm": c.projected_residual_mm.tolist(), "fit_mm": c.fitted_mm.tolist()}}
    if e.harmonic is not None:
        out["harmonic"] = e.harmonic
    if alike:
        out["indistinguishable_from"] = alike
        out["evidence"] += ("; on this pose set it cannot be told apart from " +
                            ", ".join(f"{a['kind']} {','.join(a['joints'])}".strip() for a in alike) +
                            " (held-out within 2 %): measure poses that separate them to be sure")
    return out


def diagnose(model: RobotModel, meas: Measurements, *, alpha: float = ALPHA, repeatability_mm: float | None = None,
             loss: str | None = None, folds: int = 5, unexplained: bool = True,
             progress: Callable[[float, str], None] | None = None) -> Diagnosis:
    """Geometric fit, then the greedy search for causes; returns the extended calibration and the findings."""
    report = progress or (lambda f, msg: None)
    sigma = meas.sigma if meas.sigma is not None else tracker_sigma_mm(meas.points)
    report(0.05, "identifying the geometric model")
    geo = identify(model, meas, loss=loss, folds=folds)
    floor, note = noise_floor_mm(meas, sigma, repeatability_mm)
    sigma = geo.sigma_mm  # screen with the weights of the fit: noise plus what the geometry leaves
    pool, notes = candidates(model, meas)
    x_ref = geo.x
    current, chosen = geo, []
    findings, rejected = [], []
    for round_ in range(MAX_FINDINGS):
        report(0.1 + 0.7 * round_ / MAX_FINDINGS, f"testing {len(pool)} candidate causes")
        ranked, field_share = screen(current, meas, sigma, pool, x_ref, alpha)
        threshold = np.log(alpha / max(len(pool), 1))
        accepted = False
        for c in ranked:
            if c.log_p > threshold:
                continue
            if c.effect_rms_mm < FLOOR_FACTOR * floor:
                rejected.append({"kind": c.effect.kind, "joints": [model.joint_names[j] for j in c.effect.joints],
                                 "why": f"significant (p = {c.p_value:.1e}) but {c.effect_rms_mm:.3f} mm RMS is "
                                        f"below the noise floor {floor:.3f} mm"})
                continue
            if c.explained < NAMED_SHARE * field_share:
                rejected.append({"kind": c.effect.kind, "joints": [model.joint_names[j] for j in c.effect.joints],
                                 "why": f"explains {100 * c.explained:.0f} % of the residual where a smooth field "
                                        f"explains {100 * field_share:.0f} %: part of a broader structure"})
                continue
            trial = identify(model, meas, effects=tuple(chosen + [c.effect]), loss=loss, folds=folds, x_ref=x_ref)
            hb, ha = current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
            drop = hb**2 - ha**2
            if drop < (FLOOR_FACTOR * floor) ** 2 or drop < MIN_EXCESS_FRACTION * (hb**2 - floor**2):
                rejected.append({"kind": c.effect.kind, "joints": [model.joint_names[j] for j in c.effect.joints],
                                 "why": f"significant in the fit, but on held-out poses it removes too little "
                                        f"({hb:.3f} -> {ha:.3f} mm, noise floor {floor:.3f} mm)"})
                continue
            c, trial, alike = _best_of_lookalikes(c, trial, ranked, threshold, model, meas, chosen, loss, folds,
                                                  x_ref)
            findings.append(_finding(c, model, current, trial, floor, alike))
            chosen.append(c.effect)
            pool = [e for e in pool if e != c.effect]
            current, accepted = trial, True
            x_ref = trial.x  # later bases (loads, frames) on the better geometry
            break
        if not accepted:
            break
    for _ in range(3 if len(chosen) > 1 else 0):
        report(0.8, "revisiting each finding with the others in the model")
        before = list(chosen)
        current = _revisit(findings, chosen, current, candidates(model, meas)[0], model, meas, sigma, alpha,
                           loss, folds, floor)
        if chosen == before:
            break
    if unexplained and current.metrics()["holdout_rms_mm"] > UNEXPLAINED_RATIO * floor:
        report(0.85, "looking for structure no named cause explains")
        field_effect = fit_residual_field(model, meas, current, chosen, x_ref, loss=loss, folds=folds)
        if field_effect is not None:
            trial, rf = field_effect
            if trial.metrics()["holdout_rms_mm"] < 0.9 * current.metrics()["holdout_rms_mm"]:
                findings.append(_unexplained_finding(model, current, trial, rf, floor))
                current = trial
    if chosen:  # one last joint fit with every basis on the final geometry
        current = identify(model, meas, effects=current.effects, loss=loss, folds=folds, x_ref=current.x)
    nominal = identify(model, meas, free=("base", "tool"), loss=loss, folds=folds)
    d = Diagnosis(calibration=current, geometric=geo, nominal=nominal, noise_floor_mm=floor, noise_note=note, findings=findings,
                  rejected=rejected, notes=notes)
    d.explanation = explain(d, model)
    report(1.0, "diagnosis done")
    return d


def _unexplained_finding(model, before, after, rf: ResidualField, floor) -> dict:
    hb, ha = before.metrics()["holdout_rms_mm"], after.metrics()["holdout_rms_mm"]
    return {"kind": "unexplained", "joints": [], "holdout_rms_before_mm": hb, "holdout_rms_after_mm": ha,
            "gain_pct": 100.0 * (hb - ha) / hb,
            "evidence": (f"after the named causes the held-out error ({hb:.3f} mm) is still "
                         f"{hb / floor:.1f}x the noise floor ({floor:.3f} mm) and no named cause explains it; "
                         f"a smooth joint-space correction field ({rf.describe()}) fitted jointly with the "
                         f"geometry brings it to {ha:.3f} mm"),
            "parameters": []}


def explain(d: Diagnosis, model: RobotModel) -> str:
    """One paragraph a process engineer can read."""
    g = d.geometric.metrics()
    head = (f"After the geometric calibration the robot's held-out error is {g['holdout_rms_mm']:.3f} mm RMS "
            f"against a noise floor of {d.noise_floor_mm:.3f} mm (what a perfect model would leave: {d.noise_note}).")
    if not d.findings:
        ratio = g["holdout_rms_mm"] / d.noise_floor_mm
        tail = (" No cause was found: the residual is at the noise floor, so the geometric model is complete."
                if ratio < UNEXPLAINED_RATIO else
                f" It is {ratio:.1f}x the floor, but no cause could be named and no smooth correction helped on "
                "held-out poses; look at the measurement setup (tracker, SMR seating) before the robot.")
        return head + tail
    parts = []
    for f in d.findings:
        who = f" on {', '.join(f['joints'])}" if f["joints"] else ""
        parts.append(f"{f['kind'].replace('_', ' ')}{who} (held-out {f['holdout_rms_before_mm']:.3f} -> "
                     f"{f['holdout_rms_after_mm']:.3f} mm, {f['gain_pct']:.0f} % better)")
    final = d.calibration.metrics()["holdout_rms_mm"]
    return (head + " The residual still had structure. Found, in order: " + "; ".join(parts) +
            f". With these in the model the held-out error is {final:.3f} mm, "
            f"{final / d.noise_floor_mm:.2f}x the noise floor." + (" " + " ".join(d.notes) if d.notes else ""))
