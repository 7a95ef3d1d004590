"""Find what the geometric model gets wrong, name the cause, extend the model, prove the gain held out.

Greedy and repeated: at the current model (geometry + effects found so far) every candidate cause is
scored by the linearised F-test of adding its columns to the coupled Jacobian (Bonferroni within its
family: named causes, steps in time order) and ranked by BIC; the best significant one is refitted jointly
with everything else and kept on evidence, not on its size against one measurement: its k-fold held-out
error must drop significantly (paired test over poses) and lower the de-noised model error (held-out mean
square minus the noise variance). Load-driven causes are also tried with the gravity load identified from
the data, so wrong or missing mass data do not hide them; the mass data shared by the compliances found are
then identified (bilinear, Gauss-Newton) and kept on held-out evidence. When the residual left is significantly above
the floor, the answer says what it follows (time order, a joint, the load, a workspace region): never silent.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable

import numpy as np
from scipy import optimize, special, stats

from . import kinematics as K
from .effects import (Backlash, Context, Effect, JointCompliance, LinkDeflection, LoadCompliance, Probe, SessionStep,
                      candidates, has_loads, loads)
from .effects.gravity import (MAX_LATERAL_TERMS, LateralCompliance, LateralJointCompliance, _as_tuple,
                              body_parameters, carried_columns, drive_payload_load, drive_regressor, lateral_axes,
                              load_mix_for, mass_step, tilted)
from .effects.joint_effects import LOAD_DOUBT
from .kinematics import _cross
from .effects.residual import PRIOR_STD_MM, ResidualField, fit_residual_field
from .effects.structure import at_gap, probes, session_clock, step_candidates
from .identify import Calibration, _rms, effect_bases, identify, widened
from . import shared_motion
from .select import select_geometry
from .solve import OUTLIER_U
from .io import Measurements
from .model import RobotModel

ALPHA = 0.01
"""Family-wise false-alarm rate of one search round (Bonferroni within each family of candidates)."""
TIME_SHARE = 0.2
"""Share of ALPHA spent on steps in time order; the rest on the named causes."""
HOLDOUT_ALPHA = 0.05
"""A cause is kept only if the per-pose held-out errors drop with this one-sided significance (on top of
the Bonferroni F-test in the fit, which carries the false-alarm control)."""
DEFAULT_REPEATABILITY_MM = 0.02
"""Pose repeatability assumed when the data holds no repeated poses (ISO 9283 RP of an industrial robot)."""
MIN_EXCESS_FRACTION = 0.1
"""A named cause must remove at least this fraction of the held-out mean square error above the floor;
smaller shares are what a wrong cause picks up from a true one outside the vocabulary."""
NAMED_SHARE = 0.4
"""A named cause must explain at least this share of what a smooth joint-space field explains, both counted
beyond what their degrees of freedom explain of pure noise."""
LOOKALIKE = 0.8
MAX_LOOKALIKES = 4
INDISTINGUISHABLE = 1.02
"""Rivals explaining at least LOOKALIKE of the winner's share are refitted and judged on held-out poses."""
MAX_FINDINGS = 6
MAX_SPARSE = 3
"""A cause spread over several joints is named only if this many single-joint causes, found by the same search,
do no better on held-out poses (two causes on two joints can look like compliance everywhere)."""
NOISE_LIKE = 3.0
"""A residual that follows nothing is taken for noise (the floor re-estimated) only below this multiple of
the assumed floor; beyond it, it is reported as unexplained."""
ABSORBED = 1e-3
"""A candidate's unit column keeping less than this norm outside the current model's span is absorbed by it."""


def noise_floor_mm(meas: Measurements, sigma: np.ndarray, repeatability_mm: float | None = None
                   ) -> tuple[float, str, str]:
    """RMS 3-D distance a perfect model would leave: instrument sigma plus the robot's pose repeatability.

    Repeatability comes from repeated poses when there are at least five: their spread already holds the
    instrument noise at those poses, which is taken out once (not counted twice). Returns the floor, a
    sentence on its basis and the basis itself ('given', 'repeats' or 'assumed')."""
    how = "given"
    if repeatability_mm is None:
        rep = _repeatability_from_repeats(meas, sigma)
        repeatability_mm, how = (rep, "repeats") if rep is not None else (DEFAULT_REPEATABILITY_MM, "assumed")
    floor = float(np.sqrt(3 * np.mean(sigma**2) + 3 * repeatability_mm**2))
    said = {"given": "given", "repeats": "from repeated poses", "assumed": "assumed"}[how]
    rep = (f"robot repeatability {repeatability_mm * 1000:.0f} um per axis ({said})"
           if how != "repeats" or repeatability_mm >= 0.0005 else
           "robot repeatability below what the instrument resolves (the repeated poses spread no more than its "
           "noise)")
    return floor, (f"instrument sigma {np.sqrt(np.mean(sigma**2)) * 1000:.0f} um per axis (from "
                   f"{meas.noise_source()}), {rep}"), how


def _repeatability_from_repeats(meas: Measurements, sigma: np.ndarray) -> float | None:
    """Per-axis robot repeatability (mm) from poses measured more than once, instrument noise removed. A repeat is
    the same joint values, target, setup and payload: the same joints with another marker (a payload run with its
    own target) measure another point (the iiwa's runs gave a floor of 86 mm)."""
    same = [meas.joints, meas.payload_kg()[:, None]] + [v[:, None] for v in (meas.target, meas.setup) if v is not None]
    q = np.round(np.hstack(same).astype(float), 6)
    _, inv, counts = np.unique(q, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    groups = np.flatnonzero(counts > 1)
    if len(groups) < 5:
        return None
    in_group = np.isin(inv, groups)
    means = np.zeros((len(counts), 3))
    np.add.at(means, inv, meas.points)
    means /= counts[:, None]
    dev = (meas.points - means[inv])[in_group]
    dof = int((counts[groups] - 1).sum())
    total = (dev**2).sum() / (3 * dof)
    instrument = float(np.mean(sigma[in_group] ** 2))
    return float(np.sqrt(max(total - instrument, 0.0)))


@dataclass
class Candidate:
    effect: Effect
    label: str
    p_value: float
    log_p: float
    F: float
    explained: float  # fraction of the weighted residual sum of squares it explains
    beyond_chance: float  # the same less the share its degrees of freedom would explain of pure noise
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
    floor_basis: str = "assumed"  # 'given', 'repeats', 'assumed' or 'residual' (re-estimated, no structure)
    findings: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    explanation: str = ""
    loss: str | None = None
    selection: dict = field(default_factory=dict)  # how the geometric model's size was chosen (held out)
    noise_model: str = ""  # which noise model weighted the fit: the CSV's sigma or an instrument preset
    untested: str | None = None  # what the search left untested when its time budget ran out (None: it finished)

    def model_error_mm(self, cal: Calibration) -> float:
        """De-noised model error: the root of held-out mean square distance minus the floor's (mm)."""
        return model_error_mm(cal, self.noise_floor_mm)

    def gaps(self) -> list[str]:
        """Parameters the model's structure identifies but this pose set cannot."""
        ident = self.geometric.identifiability
        return [ident.names[i] if isinstance(i, (int, np.integer)) else i
                for i in getattr(ident, "unidentifiable", [])]

    def verdict(self) -> str:
        """The diagnosis in a few words, for a headline: the same judgement as the explanation and the JSON."""
        if self.untested:
            n = sum(f["kind"] != "unexplained" for f in self.findings)
            return (f"search stopped at its time budget: {n or 'no'} cause(s) confirmed so far, not a complete "
                    f"answer" + ("; structure left" if len(self.findings) > n else ""))
        if self.findings:
            kinds = [f["kind"] for f in self.findings]
            named = sum(k not in ("unexplained", "correction") for k in kinds)
            parts = (["causes found"] if named else [])
            if "correction" in kinds:  # a form whose size no real joint has: it corrects, it does not name
                parts.append(f"{kinds.count('correction')} correction(s) of no physical size")
            if "unexplained" in kinds:
                parts.append("structure left that no named cause explains")
            return "; ".join(parts) if named else "no physical cause named: " + "; ".join(parts)
        gaps = self.gaps()
        if gaps:
            return f"none found, but this pose set cannot identify {len(gaps)} parameter(s): valid only near it"
        if self.floor_basis == "residual":
            return "none: the residual follows nothing (noise above the assumed floor)"
        return "none: at the noise floor, the geometric model is complete"

    def to_dict(self) -> dict:
        g, f = self.geometric.metrics(), self.calibration.metrics()
        return {
            "verdict": self.verdict(),
            "noise_floor_mm": self.noise_floor_mm,
            "noise_floor_basis": self.noise_note,
            "noise_floor_source": self.floor_basis,
            "noise_model": self.noise_model,
            "search_complete": self.untested is None,
            "nominal": {k: self.nominal.metrics()[k] for k in ("rms_mm", "max_mm", "holdout_rms_mm", "holdout_max_mm")},
            "geometric": {"rms_mm": g["rms_mm"], "holdout_rms_mm": g["holdout_rms_mm"], "max_mm": g["max_mm"],
                          "holdout_max_mm": g["holdout_max_mm"], "model_error_mm": self.model_error_mm(self.geometric)},
            "final": {"holdout_rms_mm": f["holdout_rms_mm"], "holdout_max_mm": f["holdout_max_mm"],
                      "model_error_mm": self.model_error_mm(self.calibration)},
            "findings": self.findings,
            "not_findings": self.rejected,
            "notes": self.notes,
            "explanation": self.explanation,
            "robust_loss": self.loss,
            "model_selection": self.selection,
            "per_pose": {
                "point": list(self.calibration.point_ids),
                "geometric_holdout_mm": self.geometric.holdout_residual_mm.tolist(),
                "final_holdout_mm": self.calibration.holdout_residual_mm.tolist(),
                "geometric_outlier": (~self.geometric.inliers()).tolist(),  # left out of the held-out figures
                "final_outlier": (~self.calibration.inliers()).tolist(),
            },
        }


@dataclass(frozen=True)
class _Fitter:
    """identify() on the diagnosis's data with one set of options: the geometry chosen on held-out evidence
    (free parameters, prior strength), the loss and the folds."""

    model: RobotModel
    meas: Measurements
    loss: str | None
    folds: int
    free: tuple[str, ...] | None
    prior_scale: float

    def __call__(self, effects=(), x_ref=None, folds: int | None = None, pose_noise=None) -> Calibration:
        refold = None
        if any(_identified_play(e) for e in effects):
            refold = lambda cal: _refold_plays(self.meas, cal)  # noqa: E731
        return identify(self.model, self.meas, effects=tuple(effects), loss=self.loss, x_ref=x_ref, free=self.free,
                        prior_scale=self.prior_scale, folds=self.folds if folds is None else folds, refold=refold,
                        pose_noise=pose_noise)


def _robust_sigma(cal: Calibration, sigma: np.ndarray) -> np.ndarray:
    """Per-pose sigma with the fit's robust weights folded in: a pose the loss down-weighted as an outlier
    counts as little in the tests as it did in the fit."""
    return sigma / np.sqrt(np.maximum(cal.solution.weights, 1e-6))


def holdout_ms(cal: Calibration) -> float:
    """Mean square held-out distance (mm^2) over the poses that are not outliers."""
    return float(np.mean(cal.holdout_residual_mm[cal.inliers()] ** 2))


def model_error_mm(cal: Calibration, floor: float) -> float:
    """De-noised model error (mm): the root of the held-out mean square distance minus the floor's."""
    return float(np.sqrt(max(holdout_ms(cal) - floor**2, 0.0)))


def _weighted_system(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray):
    """Weighted residual (m,), orthonormal basis of the current model's Jacobian (m, r), and the chain."""
    model = cal.model
    chain, dp = cal.robot.chain(meas.joints, meas)
    r = (meas.points - chain.p - dp) / sigma[:, None]
    cols = [chain.jacobian()[:, :, cal.free]]
    if cal.effects:
        Pq, Pp = effect_bases(model, meas, list(cal.effects), x_ref if cal.x_basis is None else cal.x_basis, cal.R0)
        cols.append(np.einsum("nij,njk->nik", chain.joint_jacobian(), Pq) + Pp)
    J = (np.concatenate(cols, axis=2) / sigma[:, None, None]).reshape(len(r.ravel()), -1)
    norms = np.linalg.norm(J, axis=0)
    U, s, _ = np.linalg.svd(J / np.where(norms > 0, norms, 1.0), full_matrices=False)  # unit-free rank
    Q = U[:, s > s[0] * 1e-8]
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

    Also returns the share of the residual a smooth joint-space field (ridge) explains beyond chance (less the
    share it fits of pure noise, trace(H^2) / dof of its hat matrix H): a named cause that explains far less
    than the field beyond chance is only picking up part of a broader structure. Without the correction a field
    of a few hundred effective parameters "explains" 75 % of a residual that is mostly noise, and a real cause
    half the noise's size is thrown away."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    ctx = Context(model, K.Chain(model, x_ref, meas.joints, cal.R0, meas.labels), meas)
    Jq = chain.joint_jacobian()
    m, p = len(r), Q.shape[1]
    rss = float(r @ r)
    out = []
    for e in pool:
        Cw, b = _weighted_columns(e, ctx, Jq, sigma)
        norms = np.linalg.norm(Cw, axis=0)
        if not np.all(norms > 0):
            continue
        Cp = Cw / norms - Q @ (Q.T @ (Cw / norms))
        U, sv, _ = np.linalg.svd(Cp, full_matrices=False)
        k = int((sv > ABSORBED).sum())  # the directions the current model cannot absorb
        if k == 0:
            continue
        fit = U[:, :k] @ (U[:, :k].T @ r)
        drss = float(fit @ fit)
        k_test = k + int(getattr(e, "search_dof", 0))
        dof2 = m - p - k_test
        if dof2 <= 0:
            continue
        F = (drss / k_test) / max((rss - drss) / dof2, 1e-300)
        log_p = float(stats.f.logsf(F, k_test, dof2))
        disp = fit.reshape(-1, 3) * sigma[:, None]  # mm
        direction = disp / np.maximum(np.linalg.norm(disp, axis=1, keepdims=True), 1e-300)
        res_mm = r.reshape(-1, 3) * sigma[:, None]
        out.append(Candidate(
            effect=e, label=e.label(model), p_value=float(np.exp(log_p)), log_p=log_p, F=float(F),
            explained=drss / rss, beyond_chance=drss / rss - k_test / (m - p),
            bic=m * np.log(max(rss - drss, 1e-300) / m) + k_test * np.log(m),
            effect_rms_mm=float(np.sqrt(np.mean((disp**2).sum(1)))),
            regressor=b.regressor, regressor_label=b.regressor_label,
            projected_residual_mm=(res_mm * direction).sum(1), fitted_mm=(disp * direction).sum(1)))
    field = ResidualField((), length_scale=1.0, prior_std=max(PRIOR_STD_MM, 2.0 * cal.metrics()["holdout_rms_mm"]))
    Cw, _ = _weighted_columns(field, ctx, Jq, sigma)
    Cp = Cw - Q @ (Q.T @ Cw)
    ridge = np.eye(Cp.shape[1]) / field.prior_std**2
    fit = Cp @ np.linalg.solve(Cp.T @ Cp + ridge, Cp.T @ r)
    s2 = np.linalg.svd(Cp, compute_uv=False) ** 2
    chance = float(np.sum((s2 / (s2 + 1.0 / field.prior_std**2)) ** 2))  # E|H e|^2 / sigma^2 = trace(H^2)
    return sorted(out, key=lambda c: c.bic), float(fit @ fit) / rss - chance / (m - p)


def _names(e: Effect, model: RobotModel) -> list[str]:
    """The joints a cause acts on, by their model names."""
    return [model.joint_names[j] for j in e.joints]


def _who(e: Effect, model: RobotModel) -> dict:
    """A cause as the answer names it: kind, joint names, form and (a cyclic error's) harmonic."""
    out = {"kind": e.kind, "joints": _names(e, model), "form": e.label(model)}
    if e.harmonic is not None:
        out["harmonic"] = e.harmonic
    return out


def _said(a: dict) -> str:
    """A cause in prose: kind, joints and harmonic ('cyclic_joint_error L1 h2')."""
    return " ".join([a["kind"], ",".join(a["joints"])] + ([f"h{a['harmonic']}"] if "harmonic" in a else [])).strip()


def _thresholds(pool: list[Effect], alpha: float) -> dict[int, float]:
    """Log Bonferroni threshold per candidate: ALPHA split between the named causes and the time steps."""
    steps = [e for e in pool if isinstance(e, SessionStep)]
    named = len(pool) - len(steps)
    a_named = alpha * (1.0 - TIME_SHARE) if steps else alpha
    return {id(e): np.log((alpha * TIME_SHARE / len(steps)) if isinstance(e, SessionStep) else a_named / max(named, 1))
            for e in pool}


def holdout_gain(before: Calibration, after: Calibration) -> tuple[float, float]:
    """One-sided paired test over poses that the k-fold held-out error dropped: (p-value, mean drop of the squared
    held-out distance in mm^2). Two tests of the per-pose drops, Bonferroni for both: a t-test (a gain on a few
    poses, as a play's switch gives) and a Wilcoxon signed-rank test (a gain on most poses while one pose the old
    model missed by 15 mm swells the t-test's variance: the iiwa's upright pose). A pose counts unless both fits
    name it an outlier: one the cause brings back from the outliers is where the cause shows (a bent link and a
    scale error at 5x the noise had a sixth of the poses flagged by the geometric fit, and the gain on them hidden).
    The targets measured at one pose count as one in the tests (their drops summed): they share the pose's errors."""
    keep = before.inliers() | after.inliers()
    d = before.holdout_residual_mm[keep] ** 2 - after.holdout_residual_mm[keep] ** 2
    drop = float(d.mean())
    if before.pose_index is not None:  # the targets of one pose are one unit: they share its errors (shared_motion)
        d = np.bincount(before.pose_index[keep], d)[np.unique(before.pose_index[keep])]
    sd = float(d.std(ddof=1)) if len(d) > 1 else 0.0
    if sd <= 0.0:
        return (0.0 if drop > 0 else 1.0), drop
    p_mean = float(stats.t.sf(d.mean() / (sd / np.sqrt(len(d))), len(d) - 1))
    p_rank = float(stats.wilcoxon(d, alternative="greater").pvalue)
    return min(1.0, 2.0 * min(p_mean, p_rank)), drop


def _better(before: Calibration, after: Calibration, alpha: float) -> bool:
    """Held-out poses show `after` better: the paired test significant at alpha and the mean square lower (the rank
    test alone can favour a model that wins a little on most poses and loses much on a few)."""
    p, drop = holdout_gain(before, after)
    return p < alpha and drop > 0


def _best_of_lookalikes(c, trial, ranked, thresholds, model, fit, chosen, x_ref, share=None):
    """Some causes look alike over a limited range (a scale error and a first harmonic, a short link's
    bending and the compliance of the joint before it): among the significant candidates that explain
    nearly as much as the winner, keep the best on held-out poses and name the ones it cannot beat."""
    tried = [(c, trial)]
    share = LOOKALIKE if share is None else share
    rivals = [a for a in ranked if a is not c and a.log_p <= thresholds.get(id(a.effect), -np.inf)
              and a.explained >= share * c.explained]
    for alt in rivals[:MAX_LOOKALIKES]:
        tried.append((alt, fit(chosen + [alt.effect], x_ref)))
    tried.sort(key=lambda t: t[1].metrics()["holdout_rms_mm"])
    best_fit = tried[0][1]
    # parsimony: the simplest form that held-out poses cannot show to be worse than the best one
    by_size = sorted(tried, key=lambda t: (len(t[0].effect.parameter_names(model)), t[1].metrics()["holdout_rms_mm"]))
    pick = next(t for t in by_size if t is tried[0] or not _better(t[1], best_fit, 0.05))
    tried.remove(pick)
    tried.insert(0, pick)
    best = tried[0][1].metrics()["holdout_rms_mm"]
    same = lambda e: (e.kind, e.joints, e.harmonic)  # noqa: E731
    alike = [{**_who(a.effect, model), "holdout_rms_after_mm": t.metrics()["holdout_rms_mm"]}
             for a, t in tried[1:] if t.metrics()["holdout_rms_mm"] <= INDISTINGUISHABLE * best
             and same(a.effect) != same(tried[0][0].effect)]
    return tried[0][0], tried[0][1], alike


PLAY_PASSES = 6
"""Times the play's switch is classified again on the residual with the fitted play put back."""
PLAY_SETTLED = 0.002
"""The switch has settled when no calibration pose's flank factor (-1 .. 1) moved by more than this in a pass:
fitting it again would give back nearly the same fit, so the passes stop there. On 80 drawn spray7 plays it fits
46 % fewer models than every pass, and the plays found fit the poses within 0.2 % of theirs (0.01 saved 56 % but
was 5 % worse on one draw: the soft play's search starts from the sharp one's switch)."""
SATURATES = 1.5
"""A play with fitted softness must reach tanh(1.5) = 0.9 of its flanks somewhere, else it is a spring."""
STIFFENING = (0.5, 1.5, 4.0, 12.0, 30.0)
"""Stiffening ratios (cubic over linear stiffness at the largest load) tried for a found spring."""
REFINE_ALPHA = 0.01
"""A richer form replaces an accepted cause only on this stronger held-out evidence (it is more flexible)."""
STEP_WINDOW = 8
"""Poses either side of a found step among which its exact place is sought."""
SOFT_PLAY = (0.002, 0.07, 0.15, 0.3, 0.5)
"""Transitions (share of the largest model load) of a sharper or a soft gear play, tried when a play on the
model's statics is found (the default is 0.02); a play on the identified load has its softness fitted."""


def _refinements(e: Effect, load_pool: dict[int, LoadCompliance], play_pool: dict[int, list[Backlash]],
                 ctx: Context) -> list[Effect]:
    """Richer forms of an accepted cause, kept only if held-out poses prefer them: a stiffening spring, the
    load identified from the data instead of the mass data, a play whose switch follows the identified load,
    a soft play (the joint moves through its play elastically near zero load). ctx: the poses at the reference."""
    if len(e.joints) != 1:
        return []
    j = e.joints[0]
    out: list[Effect] = []
    spring_or_play = isinstance(e, (JointCompliance, Backlash)) and not getattr(e, "stiffening", 0)
    if spring_or_play and has_loads(ctx.model, ctx.meas):
        # a soft play and a stiffening spring both deflect less and less as the load grows: try both
        big = float(np.abs(ctx.loads[:, j]).max())
        out += [JointCompliance(e.joints, stiffening=r, load_scale=big) for r in STIFFENING]
    if isinstance(e, Backlash) and e.load_coef:
        # ...also on the load the play found: the model's masses may be off or absent (a spring of 7.8x the noise
        # on J4 was taken for a soft play on its identified load, 1.8x the noise off the truth; seed 1808188314)
        big = float(np.abs(e.load(ctx)).max())
        out += [JointCompliance(e.joints, stiffening=r, load_scale=big, load_coef=e.load_coef,
                                fitted_softness=e.fitted_softness) for r in STIFFENING]
    if isinstance(e, JointCompliance) and j in load_pool:
        out.append(load_pool[j])
    if isinstance(e, Backlash):
        share = Backlash.TRANSITION_SHARE
        if not e.load_coef:
            out += [dataclasses.replace(e, transition=e.transition / share * t) for t in SOFT_PLAY]
    if isinstance(e, (Backlash, JointCompliance, LoadCompliance)):
        out += [p for p in play_pool.get(j, []) if p != e]
    return out


def _merge_alike(alike: list[dict], more: list[dict]) -> list[dict]:
    """Look-alikes `alike` and those of `more` naming another cause (kind and joints)."""
    seen = {(a["kind"], tuple(a["joints"])) for a in alike}
    return alike + [a for a in more if (a["kind"], tuple(a["joints"])) not in seen]


def _refine(c, trial, chosen, load_pool, play_pool, model, fit, x_ref):
    """Swap the accepted cause for a richer form of it when held-out poses say so: among the forms that are
    significantly better than it (paired test), the best on held-out poses; the other forms within 2 % of it,
    or not significantly worse, are look-alikes (a stiffening spring and a soft play both bend less and less
    as the load grows)."""
    better = []
    ctx = Context(model, K.Chain(model, x_ref, fit.meas.joints, None, fit.meas.labels), fit.meas)
    tried = []
    for alt in _refinements(c.effect, load_pool, play_pool, ctx):
        try:  # a form of a cause already found replaces it (a play refined into the spring found before)
            t = fit([e for e in chosen if _cause(e) != _cause(alt)] + [alt], x_ref)
        except ValueError:
            continue
        tried.append((alt, t))
        if _better(trial, t, REFINE_ALPHA):
            better.append((alt, t))
    best, t = min(better, key=lambda at: at[1].metrics()["holdout_rms_mm"]) if better else (c.effect, trial)
    h = t.metrics()["holdout_rms_mm"]
    alike = [{**_who(a, model), "holdout_rms_after_mm": ta.metrics()["holdout_rms_mm"]}
             for a, ta in tried if a is not best and a.kind != best.kind
             and (ta.metrics()["holdout_rms_mm"] <= INDISTINGUISHABLE * h or not _better(ta, t, 0.05))]
    alike = list({(a["kind"], tuple(a["joints"]), a.get("harmonic")): a for a in alike}.values())  # one per cause
    if best is c.effect:
        return c, trial, alike
    return Candidate(**{**c.__dict__, "effect": best, "label": best.label(model)}), t, alike


def _holdout_rms_every_pose(cal: Calibration) -> float:
    """Held-out RMS (mm) over every pose, the robust fit's outliers included: a step placed a few poses late makes
    the poses between outliers, which the inliers' RMS leaves out, so it looked better than the right place (a
    re-homing of J5 at P0090 placed after P0097, 7 poses flagged, fresh poses there 1 mm off: z 10.8)."""
    return _rms(cal.holdout_residual_mm)


def _refine_step(c, trial, chosen, model, meas, fit, x_ref):
    """Place an accepted step exactly: every gap between consecutive poses in time order near the searched
    one is tried (a fit each), the best by its residual is kept if held-out poses do not object."""
    clock, _ = session_clock(meas)
    order = np.sort(clock)
    k = int(np.searchsorted(order, c.effect.at))
    gaps = range(max(k - STEP_WINDOW, 1), min(k + STEP_WINDOW, len(order) - 1) + 1)
    best = None
    for i in gaps:
        e = dataclasses.replace(c.effect, **at_gap(order, i, c.effect.source))
        rss = float(np.sum(fit(chosen + [e], x_ref, folds=0).solution.residual ** 2))
        if best is None or rss < best[0]:
            best = (rss, e)
    if best is None or best[1] == c.effect:
        return c, trial
    t = fit(chosen + [best[1]], x_ref)
    if _holdout_rms_every_pose(t) > _holdout_rms_every_pose(trial):
        return c, trial
    return Candidate(**{**c.__dict__, "effect": best[1], "label": best[1].label(model)}), t


def _revisit(findings, chosen, current, pool, model, meas, sigma, alpha, fit, floor, rejected, load_pool):
    """Greedy order can mislead when causes overlap: test each finding again against its look-alikes with
    every other finding in the model; swap it for a better one, or name the ones it cannot beat. A form swapped in
    gets its richer forms tried (_refine), as a form the search accepted does. A finding the others explain goes to
    `rejected`, with the figures."""
    k = 0
    while k < len(chosen):
        others = chosen[:k] + chosen[k + 1:]
        base = fit(others, current.x)
        if not _better(base, current, HOLDOUT_ALPHA):  # the others explain what it did: it goes
            p, _ = holdout_gain(base, current)
            hb, hc = base.metrics()["holdout_rms_mm"], current.metrics()["holdout_rms_mm"]
            rejected.append({**_who(chosen[k], model), "why": f"found earlier, but with the other findings in the "
                             f"model held-out poses no longer confirm it ({hb:.3f} mm without it, {hc:.3f} mm with "
                             f"it, paired p = {p:.1e})"})
            del chosen[k], findings[k]
            current = base
            continue
        k += 1
        taken = {_cause(e) for e in others}  # one form per cause (_cause)
        rest = [e for e in pool if _cause(e) not in taken]
        if chosen[k - 1] not in rest:
            rest.append(chosen[k - 1])
        ranked, _ = screen(base, meas, sigma, rest, current.x, alpha)
        mine = next((c for c in ranked if c.effect == chosen[k - 1]), None)
        if mine is None:
            continue
        thresholds = _thresholds(rest, alpha)
        c, _, alike = _best_of_lookalikes(mine, current, ranked, thresholds, model, fit, others, current.x,
                                          share=0.5)
        if c is not mine:
            chosen[k - 1] = c.effect
            current = fit(chosen, current.x)
            # never refined when the search took the spread form instead (a stiffening spring on J3 found as the
            # compliance of J3-J7, then J3's linear one here: 0.83x the noise off the truth, 0.30x stiffening)
            c, _, forms = _refine(c, current, others, load_pool, {}, model, fit, current.x)
            alike = _merge_alike(alike, forms)
            if c.effect != chosen[k - 1]:
                chosen[k - 1] = c.effect
                current = fit(chosen, current.x)
        else:  # it stays: so do the forms _refine could not tell from it
            alike = _merge_alike(alike, findings[k - 1].get("indistinguishable_from", []))
        findings[k - 1] = _finding(c, model, base, current, floor, alike, meas)
    return current


def _when(e: Effect, meas: Measurements) -> str:
    """Where a step sits in the session, for people: the time and the poses on either side."""
    if not isinstance(e, SessionStep):
        return ""
    if e.source == "time":
        order = np.argsort(meas.timestamp)
        t = np.asarray(meas.timestamp)[order]
        k = int(np.searchsorted(t, e.at))
        stamp = datetime.fromtimestamp(e.at, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    else:
        order, k, stamp = np.arange(meas.n_poses), int(e.at), f"row {int(e.at) + 1}"
    ids = meas.point_ids or [str(i + 1) for i in range(meas.n_poses)]
    before, after = ids[order[max(k - 1, 0)]], ids[order[min(k, len(order) - 1)]]
    return f"in time order between {before} and {after} ({stamp})"


def _finding(c: Candidate, model: RobotModel, before: Calibration, after: Calibration, floor: float,
             alike: list[dict], meas: Measurements | None = None) -> dict:
    hb, ha = before.metrics()["holdout_rms_mm"], after.metrics()["holdout_rms_mm"]
    e = c.effect
    names = set(e.parameter_names(model))
    params = [p for p in after.parameters() if "effect" in p and p["name"] in names]
    when = _when(e, meas) if meas is not None else ""
    p_gain, _ = holdout_gain(before, after)
    mb, ma = model_error_mm(before, floor), model_error_mm(after, floor)
    evidence = f"{e.explain(model)}{' ' + when if when else ''}: screened at F = {c.F:.1f} ({_p(c.p_value)})"
    out = {"kind": e.kind, "joints": _names(e, model),
           "holdout_rms_before_mm": hb, "holdout_rms_after_mm": ha, "gain_pct": 100.0 * (hb - ha) / hb,
           "model_error_before_mm": mb, "model_error_after_mm": ma, "holdout_p_value": p_gain,
           "evidence": evidence, "effect_rms_mm": c.effect_rms_mm, "p_value": c.p_value, "parameters": params,
           "form": e.label(model),
           "plot": {"x": c.regressor.tolist(), "x_label": c.regressor_label,
                    "residual_mm": c.projected_residual_mm.tolist(), "fit_mm": c.fitted_mm.tolist()}}
    if e.harmonic is not None:
        out["harmonic"] = e.harmonic
    if isinstance(e, SessionStep):
        out["follows"] = [{"what": "time order", "detail": when, "joints": _names(e, model), "p_value": c.p_value}]
    if alike:
        out["indistinguishable_from"] = alike
        out["evidence"] += ("; on this pose set it cannot be told apart from " +
                            ", ".join(_said(a) for a in alike) +
                            " (held-out within 2 %): measure poses that separate them to be sure")
    return out


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


@dataclass(frozen=True)
class _LoadFeatures:
    """Joint j's identified-load regressor F (N, k): gravity regressor and payload columns, as Backlash.load_coef
    weighs them; Z (N, rank) the same span as unit-RMS orthogonal features, load = F @ (to_coef @ beta)."""

    F: np.ndarray
    Z: np.ndarray
    to_coef: np.ndarray  # (k, rank)

    @classmethod
    def of(cls, ref: K.Chain, meas: Measurements, j: int) -> "_LoadFeatures | None":
        F = np.column_stack([drive_regressor(ref, j), drive_payload_load(ref, meas.payload_kg(), j)])
        scale = np.linalg.norm(F, axis=0)
        keep = carried_columns(F)
        if not keep.any():
            return None
        U, s, Vt = np.linalg.svd(F[:, keep] / scale[keep], full_matrices=False)
        rank = int((s > 1e-6 * s[0]).sum())
        root_n = np.sqrt(len(U))
        to_coef = np.zeros((F.shape[1], rank))
        to_coef[keep] = root_n * (Vt[:rank].T / s[:rank]) / scale[keep][:, None]
        return cls(F, U[:, :rank] * root_n, to_coef)

    def beta(self, load: np.ndarray) -> np.ndarray:
        return np.linalg.lstsq(self.Z, load, rcond=None)[0]

    def play(self, j: int, beta: np.ndarray, soft: bool) -> Backlash | None:
        """The play whose switch is Z beta (None if that load never changes sign); a soft one keeps beta's scale."""
        coef = self.to_coef @ beta
        load = self.F @ coef
        if not np.any(load > 0) or not np.any(load < 0):
            return None
        rank = self.Z.shape[1]
        if soft:
            return Backlash((j,), transition=1.0, search_dof=rank + 1, fitted_softness=True,
                            load_coef=tuple(float(v) for v in coef))
        return Backlash((j,), transition=Backlash.TRANSITION_SHARE, search_dof=rank,
                        load_coef=tuple(float(v) for v in coef / np.abs(load).max()))


def _joint_columns(cal: Calibration, meas: Measurements) -> np.ndarray:
    """How the measured point moves per unit of each joint's drive (N, 3, n), on cal's geometry with its effects
    (a drive that coupled rows follow moves them too)."""
    return cal.robot.chain(meas.joints, meas)[0].joint_jacobian() @ cal.model.drive_motion()


def _joint_offsets(col: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A residual (N, 3) mm read as an offset of the joint whose motion is col (N, 3), per pose (least squares
    along its motion), and the weight of each pose's reading (1 / variance)."""
    w = (col**2).sum(1)
    return (col * residual).sum(1) / np.maximum(w, 1e-300), w


def _identified_play(e: Effect) -> bool:
    """A play whose switch the search read off the residual, or the spring tried on that play's load."""
    return isinstance(e, (Backlash, JointCompliance)) and bool(e.load_coef)


def _basis_context(cal: Calibration, meas: Measurements) -> Context:
    """What cal's effects look at on these poses: the geometry their bases were fitted on."""
    x = cal.x if cal.x_basis is None else cal.x_basis
    return Context(cal.model, K.Chain(cal.model, x, meas.joints, cal.R0, meas.labels), meas)


def _play_readings(cal: Calibration, meas: Measurements, ctx: Context) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per gear play in cal (and spring on a play's load, by index): its joint's offset read off each pose with the
    fitted effect put back (the residual along the joint's motion) and the reading's weight (1 / variance, noise
    and robust weights in)."""
    residual = meas.points - cal.predict(meas.joints, meas)
    sigma = _robust_sigma(cal, cal.sigma_mm)
    Jq = _joint_columns(cal, meas)
    out = {}
    for i, (e, v) in enumerate(zip(cal.effects, cal.effect_values)):
        if isinstance(e, Backlash) or _identified_play(e):
            col = Jq[:, :, e.joints[0]]
            off, w = _joint_offsets(col, residual + col * (v[0] * e.basis(ctx).joint[:, e.joints[0], 0])[:, None])
            out[i] = off, w / sigma**2
    return out


def _refold_plays(meas: Measurements, cal: Calibration) -> Callable[[np.ndarray], tuple]:
    """For identify's `refold`: given the training poses of a fold (N,) bool, cal's effects with every identified
    play's switch classified again on those poses alone, from the start the search took (the model's statics, or
    the residual), on the residual with the fitted play put back. The switch was read off the residual, so a
    held-out pose must not have helped place it (started from the full-data switch instead, a fold stays in its
    basin and held-out poses still gain on pure noise). What does not depend on the fold is computed once."""
    ctx = _basis_context(cal, meas)
    plays = []  # (index in cal.effects, effect, features, offsets, weights, start of the switch)
    for i, (off, wt) in _play_readings(cal, meas, ctx).items():
        e = cal.effects[i]
        j = e.joints[0]
        feats = _LoadFeatures.of(ctx.chain, meas, j) if _identified_play(e) else None
        if feats is None:
            continue
        start = ctx.loads[:, j] if has_loads(cal.model, meas) else off
        plays.append((i, e, feats, off, wt, start))

    def effects(train: np.ndarray) -> tuple:
        out = list(cal.effects)
        for i, e, feats, off, wt, start in plays:
            Z = feats.Z[train]
            beta = _switch(Z, off[train], wt[train], np.linalg.lstsq(Z, start[train], rcond=None)[0])
            if e.fitted_softness:
                beta = _softness(Z, off[train], wt[train], beta)
            play = feats.play(e.joints[0], beta, e.fitted_softness)
            if play is not None and isinstance(e, JointCompliance):  # the spring on the load found again
                big = float(np.abs(play.load(ctx)).max())
                play = dataclasses.replace(e, load_coef=play.load_coef, load_scale=big) if big > 0 else None
            out[i] = play or e
        return tuple(out)

    return effects


SWITCH_WIDTHS = np.r_[0.0, np.logspace(-4, 0, 41)]
"""The switch widths tried, as shares of the largest |load| on the calibration poses (0: no doubt at all)."""
SWITCH_LR = 0.5 * stats.chi2.ppf(0.95, 1)
"""Log-likelihood drop that bounds the width from above (95 % profile likelihood): a few calibration poses near
the switch cannot show that none is ever on the far flank, so the widest width they allow is taken."""


def _switch_width(e: Backlash, b: float, load: np.ndarray, off: np.ndarray, weight: np.ndarray) -> float:
    """Backlash.switch_width of the play e of size b (load units): the widest doubt about the load that picks the
    flank, N(0, width^2), that the calibration poses allow (95 % profile likelihood), each pose's reading `off` of
    the joint's offset (weight 1 / variance) b/2 flank(load + doubt) plus its noise. Mass data 15 % off put a few
    poses near the switch on the far flank, and fresh poses there are off by the whole play (a spray7 twin: 0.6 mm
    at a std of 0.02 mm)."""
    half, sd = 0.5 * b, 1.0 / np.sqrt(np.maximum(weight, 1e-300))

    def loglik(width: float) -> float:
        if width == 0:
            where, weight = e.flank(load)[None], np.ones((1, 1))
        elif e.transition == 0:  # a sharp switch: this flank or the other
            P = special.ndtr(-np.abs(load) / width)
            where, weight = np.array([np.sign(load), -np.sign(load)]), np.array([1.0 - P, P])
        else:
            nodes, weight = LOAD_DOUBT
            where, weight = e.flank(load + width * nodes[:, None]), weight[:, None]
        return float(special.logsumexp(stats.norm.logpdf(off, half * where, sd), b=weight, axis=0).sum())

    widths = SWITCH_WIDTHS * np.abs(load).max()
    ll = np.array([loglik(wd) for wd in widths])
    return float(widths[ll >= ll.max() - SWITCH_LR].max())


SWITCH_DRAWS = 20
"""Resamples (63 % of the calibration poses each) an identified play's switch is found again on."""


def _with_switch_doubt(cal: Calibration, meas: Measurements) -> None:
    """Sets every gear play's switch_width in cal and, for a switch identified from the data, the switches found
    again on resampled poses (Backlash.flank_doubt): its prediction std then covers the poses near the switch."""
    plays = [i for i, e in enumerate(cal.effects) if isinstance(e, Backlash)]
    if not plays:
        return
    draws = []
    if any(_identified_play(cal.effects[i]) for i in plays):
        refold, rng = _refold_plays(meas, cal), np.random.default_rng(0)  # same data, same answer
        draws = [refold(rng.random(meas.n_poses) < 0.632) for _ in range(SWITCH_DRAWS)]
    ctx = _basis_context(cal, meas)
    effects, readings = list(cal.effects), _play_readings(cal, meas, ctx)
    for i in plays:
        e, (off, wt) = cal.effects[i], readings[i]
        found = tuple(d[i].load_coef for d in draws if d[i] is not e and d[i].load_coef)
        width = _switch_width(e, cal.effect_values[i][0], e.load(ctx), off, wt)
        effects[i] = dataclasses.replace(e, switch_width=width, switch_draws=found)
    cal.effects = tuple(effects)


def _identified_backlash(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray,
                         joints: list[int], fit: "_Fitter",
                         late: Callable[[], bool] = lambda: False) -> list[Backlash]:
    """Backlash whose switch follows the load identified from the data: per joint, a linear classifier of the
    sign of the residual along that joint's motion on the gravity regressor (started from the model's
    statics where there are masses). Its search is paid for in the F-test (`search_dof`), and each fold of the
    cross-validation finds the switch again on its own training poses (_refold_plays). Once `late()`, returns the
    plays found so far (each costs a few full fits: a minute on thousands of poses)."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    ref = K.Chain(model, x_ref, meas.joints, cal.R0, meas.labels)
    ref_ctx = Context(model, ref, meas)
    nominal = ref_ctx.loads if has_loads(model, meas) else None
    residual = meas.points - cal.predict(meas.joints, meas)
    Jq = _joint_columns(cal, meas)
    out = []
    for j in joints:
        feats = _LoadFeatures.of(ref, meas, j)
        if feats is None:
            continue
        col = Jq[:, :, j]
        e, w = _joint_offsets(col, residual)
        sharp = feats.beta(nominal[:, j] if nominal is not None else e)
        for soft in (False, True):  # a sharp play, then one whose softness is fitted
            partial, play, beta = residual, None, sharp
            for _ in range(1 + PLAY_PASSES):
                e, _ = _joint_offsets(col, partial)  # the residual as an offset of joint j, per pose
                beta = _softness(feats.Z, e, w / sigma**2, beta) if soft else _switch(feats.Z, e, w / sigma**2, beta)
                found = feats.play(j, beta, soft)
                if found is None:
                    break
                settled = play is not None and _flank_moved(play, found, ref_ctx) <= PLAY_SETTLED
                play = found
                if soft and np.abs(feats.F @ np.asarray(play.load_coef)).max() < SATURATES:
                    play = None  # it never reaches the flanks of its play: that is a spring, not a play
                    break
                if settled:
                    break
                if late():  # the joint in progress is left out
                    return out
                try:  # fit it, then find the switch again on the residual with the play put back (partial residual)
                    fitted = fit(tuple(cal.effects) + (play,), x_ref, folds=0)
                except ValueError:
                    break
                step = fitted.effect_values[-1][0] * play.basis(ref_ctx).joint[:, j, 0]
                partial = meas.points - fitted.predict(meas.joints, meas) + col * step[:, None]
            if play is not None:
                out.append(play)
                sharp = beta if not soft else sharp
    return out


def _flank_moved(a: Backlash, b: Backlash, ctx: Context) -> float:
    """The largest change of the flank factor (-1 .. 1) on these poses from play a's switch to b's."""
    return float(np.abs(a.flank(a.load(ctx)) - b.flank(b.load(ctx))).max())


def _switch(Z: np.ndarray, e: np.ndarray, weight: np.ndarray, beta0: np.ndarray) -> np.ndarray:
    """Where a play switches: the load direction beta (on unit-RMS features Z) for which b/2 tanh(Z beta / t)
    best fits the per-pose joint offsets e (weighted least squares), the transition t annealed to sharp."""
    sw = np.sqrt(weight / max(weight.mean(), 1e-300))
    beta = beta0 / max(float(np.sqrt(np.mean((Z @ beta0) ** 2))), 1e-300)
    for t in (0.5, 0.15, 0.05):
        s0 = np.tanh(Z @ beta / t)
        b = 2.0 * float((sw**2 * s0 * e).sum() / max((sw**2 * s0 * s0).sum(), 1e-300))
        def fun(p, t=t):
            return sw * (e - 0.5 * p[0] * np.tanh(Z @ p[1:] / t))

        def jac(p, t=t):
            th = np.tanh(Z @ p[1:] / t)
            return -sw[:, None] * np.column_stack([0.5 * th, (0.5 * p[0] / t) * (1.0 - th**2)[:, None] * Z])

        p = optimize.least_squares(fun, np.r_[b, beta], jac=jac, method="lm", max_nfev=50).x
        beta = p[1:] * np.sign(p[0]) / max(float(np.sqrt(np.mean((Z @ p[1:]) ** 2))), 1e-300)
    return beta


def _softness(Z: np.ndarray, e: np.ndarray, weight: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """The play's load direction with its scale free: b/2 tanh(Z beta) fitted to the offsets e, so |beta|
    says how soft the play is (started from the best of a few transitions)."""
    sw = np.sqrt(weight / max(weight.mean(), 1e-300))

    def amplitude(bz):
        s0 = np.tanh(bz)
        return 2.0 * float((sw**2 * s0 * e).sum() / max((sw**2 * s0 * s0).sum(), 1e-300))

    def cost(bz):
        return float(np.sum((sw * (e - 0.5 * amplitude(bz) * np.tanh(bz))) ** 2))

    linear = np.linalg.lstsq(Z * sw[:, None], e * sw, rcond=None)[0]  # a soft play is linear near zero load
    linear = linear / max(float(np.sqrt(np.mean((Z @ linear) ** 2))), 1e-300)
    starts = [beta / t for t in (0.05, 0.15, 0.5, 1.5)] + [linear * a for a in (0.5, 1.0, 2.0, 4.0)]
    start = min(starts, key=lambda bb: cost(Z @ bb))

    def fun(p):
        return sw * (e - 0.5 * p[0] * np.tanh(Z @ p[1:]))

    def jac(p):
        th = np.tanh(Z @ p[1:])
        return -sw[:, None] * np.column_stack([0.5 * th, 0.5 * p[0] * (1.0 - th**2)[:, None] * Z])

    p = optimize.least_squares(fun, np.r_[amplitude(Z @ start), start], jac=jac, method="lm", max_nfev=100).x
    return p[1:] * np.sign(p[0])


def _play_not_outliers(first: Calibration, meas: Measurements) -> bool:
    """The poses a robust fit flags as outliers may be the few where a joint's load changes sign, shifted by
    its gear play: then they are structure for the search, not outliers to down-weight."""
    model, out = first.model, first.solution.outliers
    if not has_loads(model, meas) or len(out) < 2:
        return False
    load = loads(K.Chain(model, first.x, meas.joints, first.R0, meas.labels), meas)
    for j in range(model.n_joints):
        sign = np.sign(load[:, j])
        minority = sign == (1.0 if (sign > 0).sum() < (sign < 0).sum() else -1.0)
        flagged = out[np.isin(out, np.flatnonzero(minority))]  # flagged poses on the minority side of the load
        both = len(flagged)
        if not 0 < minority.sum() <= 0.25 * meas.n_poses or both < 0.5 * len(out) or both < 0.5 * minority.sum():
            continue
        play = Backlash((j,), transition=float(Backlash.TRANSITION_SHARE * np.abs(load[:, j]).max()))
        with_play = identify(model, meas, effects=(play,), folds=0, x_ref=first.x)  # plain: the play must fit them
        d = np.linalg.norm(with_play.solution.residual, axis=1)
        u = d / np.sqrt(np.median(d**2) / 2.366)  # in robust sigmas of a 3-D residual (median chi2(3) = 2.366)
        if np.all(u[flagged] < OUTLIER_U):
            return True
    return False


RUNS_P = 1e-4
"""Poses a robust fit flags are structure in time, not bad readings, when they fall into so few runs of consecutive
measurements that randomly placed bad readings would do so with less than this probability..."""
SESSION_END = 0.05
"""...and reach into the first or the last 5 % of the session: a warm-up starts it, a re-homing or a moved base
lasts to its end; a burst in the middle that ends again is bad readings (6 readings 20 mm off mid-session, kept at
full weight, left a clean spray7 17x the noise off on fresh poses)..."""
ABSURD_SHARE = 0.05
"""...unless one is off by more than this share of the measured workspace's size (RMS distance of the points from
their centroid): a robot's model error (a warm-up, a re-homing by 3 deg) stays below it, a burst of readings of
something else (the beam caught elsewhere, a typo of 1000 mm) does not."""


def _pose_ids(meas: Measurements, idx: np.ndarray, most: int = 20) -> str:
    """The poses' point ids (1-based row numbers when the set has none), the first `most` of them."""
    ids = [meas.point_ids[i] if meas.point_ids else str(i + 1) for i in idx]
    return ", ".join(ids[:most]) + (" ..." if len(ids) > most else "")


def runs_probability(k: int, n: int, N: int) -> float:
    """Exact probability that n of N poses in a row, chosen at random, fall into at most k runs of consecutive
    poses: sum_{i<=k} C(n-1, i-1) C(N-n+1, i) / C(N, n)."""
    i = np.arange(1, k + 1)
    lc = lambda a, b: special.gammaln(a + 1) - special.gammaln(b + 1) - special.gammaln(a - b + 1)  # noqa: E731
    return float(min(np.exp(lc(n - 1, i - 1) + lc(N - n + 1, i) - lc(N, n)).sum(), 1.0))


def _flagged_in_runs(first: Calibration, meas: Measurements) -> str:
    """A note when the poses the robust fit `first` flags come in runs in time (or row) order and none is absurd: a
    warm-up, a re-homing, a moved base or tracker, i.e. structure for the search and the report, not outliers to
    down-weight; else ''."""
    out = first.solution.outliers
    n, N = len(out), meas.n_poses
    if n < 2 or n >= N:
        return ""
    size = np.sqrt(np.mean(np.sum((meas.points - meas.points.mean(0)) ** 2, axis=1)))
    if np.linalg.norm(first.solution.residual[out], axis=1).max() > ABSURD_SHARE * size:
        return ""
    clock, source = session_clock(meas)
    rank = np.empty(N, int)
    rank[np.argsort(clock, kind="stable")] = np.arange(N)
    at = np.sort(rank[out])
    if at[0] > SESSION_END * N and at[-1] < (1.0 - SESSION_END) * N - 1:
        return ""  # a burst mid-session that ends again (a knocked SMR re-seated): bad readings, not a step
    k = 1 + int(np.sum(np.diff(at) > 1))
    p = runs_probability(k, n, N)
    if p >= RUNS_P:
        return ""
    order = "time" if source == "time" else "row (no timestamps)"
    return (f"{n} pose(s) disagree with the rest by far more than the noise ({_pose_ids(meas, out)}), but they "
            f"are not scattered bad readings: in {order} order they come in {k} run(s) of consecutive measurements "
            f"({_p(p)} for bad readings placed at random). Something happened then (a warm-up, a re-homing, the "
            f"base or the tracker moved) or in the part of the workspace measured then: structure, so they are kept "
            f"at full weight for the search and the report")


PLAUSIBLE_TURN_RAD = 0.1
"""A gear play, a spring or a bearing turns a joint by a fraction of a degree on an industrial robot, by a few on an
elastic humanoid (Agile Justin: up to 3 deg); a form that needs more than this (5.7 deg) stands in for something
else."""
PLAUSIBLE_TRAVEL_MM = 10.0
"""The same for a prismatic joint (a rail's or a telescope's play or spring)."""


def _judge_sizes(cal: Calibration, findings: list[dict], meas: Measurements) -> None:
    """Marks a finding whose form needs an unphysical size at a calibration pose ("physical": false, and its
    evidence says so): held-out poses confirmed it, so it stays in the model, but its values are not the joint's."""
    model, ctx = cal.model, _basis_context(cal, meas)
    for f in findings:
        names = {p["name"] for p in f.get("parameters", [])}
        sizes = []
        for e, v in zip(cal.effects, cal.effect_values):
            if names & set(e.parameter_names(model)):
                for j, t in e.turns(ctx, v):
                    big = float(np.abs(t).max())
                    if big > (PLAUSIBLE_TRAVEL_MM if model.prismatic[j] else PLAUSIBLE_TURN_RAD):
                        sizes.append(f"{model.joint_names[j]} by up to "
                                     + (f"{big:.3g} mm" if model.prismatic[j] else f"{np.degrees(big):.3g} deg"))
        plays = _plays_beyond_motion(cal, f, meas) if f.get("kind") == "backlash" else ""
        if plays and not sizes:
            f["physical"] = False
            f["bound"] = plays
            f["evidence"] += (f"; its size is not physical: {plays}. The data determine what it predicts (held-out "
                              f"poses confirm it), not this play: read it as a correction, not as the joint's")
        if sizes:
            f["physical"] = False
            limits = sorted({f"{PLAUSIBLE_TRAVEL_MM:g} mm" if "mm" in x else
                             f"{np.degrees(PLAUSIBLE_TURN_RAD):.3g} deg" for x in sizes})
            f["bound"] = (f"it would move {', '.join(sizes)} at a calibration pose, beyond the "
                          f"{' or '.join(limits)} a real play, spring or bearing moves a joint")
            if plays:
                f["bound"] += "; " + plays
            f["evidence"] += (f"; its size is not physical: it would move {', '.join(sizes)} at a calibration pose, "
                              f"where a real play, spring or bearing turns a joint by a fraction of a degree. The "
                              f"data determine what it predicts (held-out poses confirm it), not these values: it "
                              f"stands in for structure with no name here, or trades one joint's share against "
                              f"another's, so read it as a correction, not as the joint's")


def _plays_beyond_motion(cal: Calibration, f: dict, meas: Measurements) -> str:
    """A gear play shows as the joint sitting on one flank or the other; one wider than the joint's own travel over
    the calibration poses cannot be told from the data (the iiwa: a 0.41 deg play named on A6, which moves less than
    0.12 deg). Says which plays break that bound, with both sizes; "" when none does."""
    model, out = cal.model, []
    table = {p["name"]: p for p in cal.parameters()}
    for name in f.get("joints") or []:
        j = model.joint_names.index(name)
        p = table.get(f"{name}.backlash")
        if p is None or p.get("value") is None:
            continue
        play, travel = abs(float(p["value"])), float(np.ptp(meas.joints[:, j]))
        if play > travel:
            out.append(f"a play of {play:.3g} mm on {name}, which moves {travel:.3g} mm" if model.prismatic[j] else
                       f"a play of {np.degrees(play):.3g} deg on {name}, which turns {np.degrees(travel):.3g} deg")
    if not out:
        return ""
    return (f"{'; '.join(out)} over the calibration poses: no play wider than the joint's own motion can be "
            f"revealed by it")


SIGNIFICANT_STD = 2.0
"""A parameter's value is beyond its noise when it is more than this many std from zero: a joint of a finding on
several joints carries a share only then, and a compliance below -SIGNIFICANT_STD std is negative for sure."""
FOLLOWS = {"joint_compliance": "the load on {j}", "backlash": "the sign of the load on {j}",
           "link_deflection": "the bending load on {j}", "cyclic_joint_error": "the angle of {j}",
           "joint_scale": "the travel of {j}", "axis_straightness": "the travel of {j}",
           "thermal_drift": "time or temperature"}
"""What a correction follows, in words, by the kind it was fitted as."""


def follows_what(f: dict) -> str:
    """What a finding's form follows, in words ('the load on R6'), by the kind it was fitted as."""
    kind = f["follows"] if f.get("kind") == "correction" else f.get("kind", "")
    j = ", ".join(f.get("joints") or [])
    return FOLLOWS.get(kind, kind.replace("_", " ") + (" on {j}" if j else "")).format(j=j or "the robot")


def named_joints(f: dict) -> tuple[list[str], str]:
    """The joints a finding is named for, and a remark on the others: its `significant_joints` where some of its
    joints carry no share beyond SIGNIFICANT_STD std (compliance on two joints is not named as that of five)."""
    joints, sig = list(f.get("joints") or []), f.get("significant_joints")
    if not sig or len(sig) == len(joints):
        return joints, ""
    return list(sig), f"{len(sig)} of {len(joints)} joints fitted carry a share"


def _beyond(p: dict, k: float = SIGNIFICANT_STD) -> float:
    """value / std of a parameter (0 where its std is undetermined)."""
    std = p.get("std")
    if std is None or not np.isfinite(std) or std <= 0 or p.get("value") is None:
        return 0.0
    return float(p["value"]) / float(std)


def present_findings(cal: Calibration, findings: list[dict]) -> None:
    """How the answer presents each finding, from the final model's parameter table (what is fitted is not touched):
    its parameters and the values its evidence quotes are the table's (a later refit moves them).
    A finding on several joints lists in `significant_joints` the joints whose own parameters are beyond
    SIGNIFICANT_STD std of zero, and its evidence names the others. A finding that breaks its physical bound (a size
    no real joint has, `_judge_sizes`; a joint compliance below -SIGNIFICANT_STD std: a spring never pushes back the
    wrong way) is not presented under a physical name: its kind becomes "correction", with `follows` (the kind it
    was fitted as), `physical` false, `bound` (the bound it breaks, with the numbers) and one plain sentence first
    in its evidence: what it follows, what it gains held out, and why it is not a physical cause. A compliance whose
    negative joints are all within SIGNIFICANT_STD std of zero stays physical."""
    table = {p["name"]: p for p in cal.parameters()}
    for f in findings:
        if f.get("kind") in ("unexplained", "correction") or not f.get("parameters"):
            continue
        params = f["parameters"] = [{**p, **table.get(p["name"], {})} for p in f["parameters"]]
        f["evidence"] += "; in the final model " + ", ".join(
            f"{p['name']} = {p['value']:.4g} +/- {'(undetermined)' if p['std'] is None else format(p['std'], '.2g')}"
            f"{' ' + p['unit'] if p.get('unit') not in (None, '', '1') else ''}" for p in params[:4])
        joints = list(f.get("joints") or [])
        mine = {j: [p for p in params if p["name"].startswith(j + ".")] for j in joints}
        if len(joints) > 1:
            f["significant_joints"] = [j for j in joints if any(abs(_beyond(p)) > SIGNIFICANT_STD for p in mine[j])]
            weak = [j for j in joints if j not in f["significant_joints"]]
            if weak:
                f["evidence"] += (f"; of its {len(joints)} joints only "
                                  f"{', '.join(f['significant_joints']) or 'none'} carr"
                                  f"{'ies' if len(f['significant_joints']) == 1 else 'y'} a share beyond "
                                  f"{SIGNIFICANT_STD:g} std of zero ({', '.join(weak)} not)")
        negative = [p for p in params if f["kind"] == "joint_compliance" and p["name"].endswith(".compliance")
                    and _beyond(p) < -SIGNIFICANT_STD]
        if negative:
            who = [j for j in joints if any(p in negative for p in mine[j])] or [p["name"].split(".")[0]
                                                                                 for p in negative]
            said = ", ".join(f"{p['name']} = {p['value']:.3g} +/- {p['std']:.2g}"
                             f"{' ' + p['unit'] if p.get('unit') else ''}" for p in negative)
            neg = (f"the compliance of {' and '.join(who)} is negative by more than {SIGNIFICANT_STD:g} std "
                   f"({said}), and a spring never pushes back the wrong way")
            springs = [j for j in joints if j not in who and any(
                p["name"].endswith(".compliance") and _beyond(p) > SIGNIFICANT_STD for p in mine[j])]
            if springs:  # the cause stays named for the joints that give as springs do; the rest is a correction
                f["significant_joints"] = springs
                f["negative_joints"] = who
                f["evidence"] += (f"; {neg}: that share is a correction within this cause, not "
                                  f"{'their' if len(who) > 1 else 'its'} spring, and the cause is named for "
                                  f"{', '.join(springs)}")
            else:
                f["bound"] = neg + ("; " + f["bound"] if f.get("bound") else "")
                f["physical"] = False
        if f.get("physical") is not False:
            continue
        f["follows"], f["kind"] = f["kind"], "correction"
        gain = ""
        if f.get("holdout_rms_before_mm") is not None and f.get("holdout_rms_after_mm") is not None:
            gain = (f"held out it takes the error from {f['holdout_rms_before_mm']:.3f} to "
                    f"{f['holdout_rms_after_mm']:.3f} mm ({f.get('gain_pct', 0.0):.0f} % better), but ")
        f["evidence"] = (f"This is a correction that follows {follows_what(f)}, not a physical cause: {gain}"
                         f"{f.get('bound', 'its size is not physical')}. Fitted as "
                         f"{f['follows'].replace('_', ' ')}: " + f["evidence"])


def _chain(findings: list[dict], geo: Calibration, named: Calibration, fit: _Fitter, x_ref: np.ndarray,
           floor: float, model: RobotModel | None) -> None:
    """Per-cause figures that chain: finding k is judged as added to the findings before it, its held-out error
    before being the one its predecessor ends at (the geometric model's for the first, the named causes' model for
    the last, where `unexplained` starts). The search judged each cause against the model of its moment, and a
    revisit against the final model without it, so its figures did not chain (the Motoman: cause 1 ended at 1.438
    mm, cause 2 started at 1.527). Costs one refit per named cause but the last; with `model` None (the time budget
    is spent) the search's own figures stay. Appends the held-out sentence to each finding's evidence."""
    named_f = [f for f in findings if f.get("kind") != "unexplained"]
    steps = None
    if model is not None and named_f:
        effects, used, steps = list(named.effects), set(), [geo]
        try:
            for f in named_f[:-1]:
                names = {p["name"] for p in f.get("parameters", [])}
                used |= {i for i, e in enumerate(effects) if names & set(e.parameter_names(model))}
                steps.append(fit(tuple(effects[i] for i in sorted(used)), x_ref))
        except (ValueError, np.linalg.LinAlgError):
            steps = None
        else:
            steps.append(named)
    for k, f in enumerate(named_f):
        if steps is not None:
            before, after = steps[k], steps[k + 1]
            hb, ha = before.metrics()["holdout_rms_mm"], after.metrics()["holdout_rms_mm"]
            f.update(holdout_rms_before_mm=hb, holdout_rms_after_mm=ha, gain_pct=100.0 * (hb - ha) / hb,
                     model_error_before_mm=model_error_mm(before, floor),
                     model_error_after_mm=model_error_mm(after, floor), holdout_p_value=holdout_gain(before, after)[0])
        added = "added to the geometric model" if k == 0 else "added to the causes above"
        f["evidence"] += (f"; {added}, it takes the held-out error from {f['holdout_rms_before_mm']:.3f} to "
                          f"{f['holdout_rms_after_mm']:.3f} mm (paired {_p(f['holdout_p_value'])}) and the model "
                          f"error beyond the noise floor ({floor:.3f} mm) from {f['model_error_before_mm']:.3f} to "
                          f"{f['model_error_after_mm']:.3f} mm")


def _outlier_note(meas: Measurements, first: np.ndarray, final: np.ndarray) -> str:
    """Why the fits use the Huber loss, naming the outliers of the final model (those metrics.outliers lists) and
    the poses the first robust fit of the geometry flagged that the causes found explain."""
    explained = np.setdiff1d(first, final)
    text = (f"{len(final)} pose(s) disagree with the model by far more than the noise and were down-weighted as "
            f"outliers (Huber loss): {_pose_ids(meas, final)}" if len(final) else
            "the fits use the Huber loss because a robust fit of the geometry alone flagged outliers; no pose is an "
            "outlier of the final model")
    if len(explained):
        text += (f"; the geometric fit had flagged {_pose_ids(meas, explained)} too, which the causes found "
                 f"explain")
    return text


def _holdout_inflation(cal: Calibration, n_poses: int) -> float:
    """Held-out mean square over the floor's that counts as a right model: held-out poses carry the error of the
    p parameters fitted without them too. The exact share is p / (3 n_train - p) (6 spray7 twins with no effect,
    p = 27: held-out / true noise 1.03-1.10, this 1.08); this takes about three times it (1.19), which also covers
    an assumed floor some 10 % low. With the exact share, floor error was read as model error: prediction z on
    twins the model describes exactly fell to 0.70-0.77 (gear error, joint spring; RESULTS 3.2)."""
    p = len(cal.solution.x)
    return 1.0 + p / max(n_poses - p / 3.0, 1.0)


def _unmodelled_mm(cal: Calibration, floor: float, structure_left: bool) -> float:
    """Per-axis std (mm) of the held-out error beyond the floor, which predictions carry in their std: its
    unbiased estimate whenever positive. Adding it only when significant left the std too small where a cause was
    explained all but a little (a tilted base taken up by the rail's straightness: 0.077 mm held out against a
    0.063 mm floor, fresh poses off by twice their std). With structure left, over every held-out pose, since the
    poses a robust loss set aside are then mostly that structure."""
    h = cal.holdout_residual_mm if structure_left else cal.holdout_residual_mm[cal.inliers()]
    ms = float(np.mean(h**2)) / _holdout_inflation(cal, len(h))  # the parameters' own error is in cov already
    return float(np.sqrt(max(ms - floor**2, 0.0) / 3.0))


def _excess(cal: Calibration, floor: float) -> float:
    """p-value that the held-out residual is no larger than the noise floor (chi-square on 3N)."""
    h = cal.holdout_residual_mm[cal.inliers()]
    N = len(h)
    T = float((h**2).sum() / (floor**2 / 3.0) / _holdout_inflation(cal, N))
    return float(stats.chi2.sf(T, 3 * N))


def _follows(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray, alpha: float,
             load_pool: dict[int, LoadCompliance]) -> list[dict]:
    """What the residual left follows: time order (a step or a drift), one joint, the load, a workspace
    region, each a family tested with the same F-test; with several targets per pose, whether they move together
    (shared_motion's rank test); Bonferroni over the families."""
    model = cal.model
    fams = probes(model, meas)
    fams += _distributed(load_pool) if load_pool else []
    if has_loads(model, meas):
        loaded = [j for j in range(model.n_joints) if j in load_pool] or list(np.flatnonzero(model.moving))
        fams.append(JointCompliance(tuple(loaded)))
    # the whole robot shifted, or one joint's zero (a re-homing: a joint offset moves each pose differently, which
    # a rigid shift of the late poses hardly follows)
    steps = step_candidates(meas, list(np.flatnonzero(model.moving)))
    ranked, _ = screen(cal, meas, sigma, fams + steps, x_ref, alpha)
    shared = _shared_motion(cal, meas, sigma, x_ref)
    n_tests = len(fams) + 1 + (shared is not None)
    together = next((s for s in shared or [] if s.p_value < alpha / n_tests), None)  # the largest significant
    out, seen_step = [], False
    for c in ranked:
        is_step = isinstance(c.effect, SessionStep)
        limit = np.log(alpha / n_tests / (len(steps) if is_step else 1))
        if c.log_p > limit or (is_step and seen_step):
            continue
        seen_step |= is_step
        if is_step:
            what = "time order: a step " + _when(c.effect, meas)
            if c.effect.source == "row":
                what = "row order (no timestamps): a step " + _when(c.effect, meas) + "; were the rows measured in this order?"
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
                 "family": "shared_by_targets", "effect": together}
        out.insert(next((i for i, f in enumerate(out) if f["p_value"] > together.p_value), len(out)), entry)
    return out


def _shared_motion(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray
                   ) -> list[shared_motion.SharedMotion] | None:
    """shared_motion.shared_motion on the calibration's residual (None with one target per pose)."""
    if not shared_motion.pose_groups(meas, cal.model):
        return None
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    return shared_motion.shared_motion(chain, meas, r.reshape(-1, 3) * sigma[:, None], sigma, Q)


def _cause(e: Effect):
    """What a candidate is a form of: a joint's play or compliance is one cause whatever its form (sharp or soft, on
    the mass data or the identified load, linear or stiffening), so its forms replace each other (_refine), never add
    up (a soft play beside a sharp one passed the held-out test on one arm6 world and doubled the error on fresh
    poses); any other cause is itself on the model's mass data."""
    if isinstance(e, (Backlash, JointCompliance, LoadCompliance)) and len(e.joints) == 1:
        return e.kind, e.joints
    identified = getattr(e, "masses", ()) or getattr(e, "gravity", ())
    return dataclasses.replace(e, masses=(), gravity=()) if identified else e


@dataclass
class _Search:
    """The greedy search for causes: the model with the causes chosen so far, what was found and what was turned
    down and why. It can resume from a changed model (the mass data identified under the causes found)."""

    model: RobotModel
    meas: Measurements
    sigma: np.ndarray
    alpha: float
    fit: _Fitter
    floor: float
    pool: list[Effect]  # named causes and steps in time order
    load_pool: dict[int, LoadCompliance]
    current: Calibration
    x_ref: np.ndarray
    chosen: list[Effect] = field(default_factory=list)
    findings: list[dict] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    deadline: float | None = None  # time.monotonic() after which no further model is fitted (the job's time budget)
    untested: str | None = None  # what the deadline left untested, once it has passed

    def late(self, what: str) -> bool:
        """True once the deadline has passed; the first call after it records `what` was left untested."""
        if self.deadline is None or time.monotonic() < self.deadline:
            return False
        self.untested = self.untested or what
        return True

    def run(self, report: Callable[[float, str], None]) -> bool:
        """Add the best candidate held-out poses confirm, round after round, until none is or MAX_FINDINGS are
        in the model; True if any was added."""
        added = False
        while len(self.chosen) < MAX_FINDINGS and not self.late("the next round of candidates"):
            at, head = 0.1 + 0.6 * len(self.chosen) / MAX_FINDINGS, f"testing {len(self.pool)} candidate causes"
            report(at, head)
            if not self._round(lambda step: report(at, f"{head}: {step}")):
                break
            added = True
        return added

    def _round(self, say: Callable[[str], None] = lambda step: None) -> bool:
        """One round: screen every candidate not in the model, accept the first (by BIC) held-out poses confirm.
        `say` hears each step that fits models (minutes each on thousands of poses)."""
        model, meas, sigma, alpha, fit, x_ref = self.model, self.meas, self.sigma, self.alpha, self.fit, self.x_ref
        taken = {_cause(e) for e in self.chosen}
        pool = _on_carried_masses([e for e in self.pool if _cause(e) not in taken], self.chosen)
        ranked, field_share = screen(self.current, meas, sigma, pool, x_ref, alpha)
        thresholds = _thresholds(pool, alpha)
        # a play whose switch follows the identified load, on the joints where a load-driven cause shows
        active = {c.effect.joints[0] for c in ranked if len(c.effect.joints) == 1
                  and c.effect.joints[0] in self.load_pool
                  and isinstance(c.effect, (JointCompliance, LoadCompliance, Backlash))
                  and c.log_p <= thresholds[id(c.effect)]}
        play_joints = sorted(j for j in active if ("backlash", (j,)) not in taken)
        if play_joints:
            say(f"finding where a play would switch on {', '.join(model.joint_names[j] for j in play_joints)}")
        plays = _identified_backlash(self.current, meas, sigma, x_ref, play_joints, fit,
                                     lambda: self.late("where a play would switch on the joints whose load shows"))
        play_pool: dict[int, list[Backlash]] = {}
        for b in plays:
            play_pool.setdefault(b.joints[0], []).append(b)
        if plays:
            pool += plays
            thresholds = _thresholds(pool, alpha)
            ranked = sorted(ranked + screen(self.current, meas, sigma, plays, x_ref, alpha)[0], key=lambda c: c.bic)
        significant = np.array([c.log_p <= thresholds[id(c.effect)] for c in ranked], bool)
        untested = np.cumsum(significant[::-1])[::-1]  # significant candidates from each rank on
        for k, c in enumerate(ranked):
            if not significant[k]:
                continue
            if self.late(f"{untested[k]} candidate(s) significant in the fit, not yet tested on held-out poses"):
                return False
            who = _who(c.effect, model)
            broad = isinstance(c.effect, SessionStep) or len(c.effect.joints) > 1  # spread over the arm already
            if c.beyond_chance < NAMED_SHARE * field_share and not broad:
                self.rejected.append({**who, "why": f"explains {100 * c.beyond_chance:.0f} % of the residual beyond "
                                                    f"chance where a smooth field explains {100 * field_share:.0f} %: "
                                                    f"part of a broader structure"})
                continue
            say(f"{c.effect.label(model)} on held-out poses")
            mine = [i for i, e in enumerate(self.chosen) if not _subsumed(e, c.effect)]  # a spread form replaces
            others = [self.chosen[i] for i in mine]  # its joints' own
            try:
                trial = fit(others + [c.effect], x_ref)
            except ValueError as exc:
                self.rejected.append({**who, "why": str(exc)})
                continue
            p_gain, drop = holdout_gain(self.current, trial)
            excess = holdout_ms(self.current) - self.floor**2
            if p_gain > HOLDOUT_ALPHA or drop < MIN_EXCESS_FRACTION * max(excess, 0.0):
                hb, ha = self.current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
                self.rejected.append({**who, "why": f"significant in the fit ({_p(c.p_value)}), but held-out "
                                                    f"poses do not confirm it ({hb:.3f} -> {ha:.3f} mm, paired p = "
                                                    f"{p_gain:.1e})"})
                continue
            c, trial, alike = _best_of_lookalikes(c, trial, ranked, thresholds, model, fit, others, x_ref)
            c, trial, forms = _refine(c, trial, others, self.load_pool, play_pool, model, fit, x_ref)
            alike = _merge_alike(alike, forms)
            if isinstance(c.effect, SessionStep):
                c, trial = _refine_step(c, trial, others, model, meas, fit, x_ref)
            elif isinstance(c.effect, LoadCompliance) and len(c.effect.joints) > 1 and self._sparser(c, trial):
                return True
            keep = [i for i in mine if _cause(self.chosen[i]) != _cause(c.effect)]  # without the form it replaced
            self.chosen, self.findings = [self.chosen[i] for i in keep], [self.findings[i] for i in keep]
            self.findings.append(_finding(c, model, self.current, trial, self.floor, alike, meas))
            self.chosen.append(c.effect)
            self.current = trial
            self.x_ref = trial.x  # later bases (loads, frames) on the better geometry
            return True
        return False

    def _sparser(self, c: Candidate, trial: Calibration) -> bool:
        """Search on without causes spread over several joints, for at most MAX_SPARSE rounds (and fewer parameters
        than the spread cause); take what it finds instead of the spread cause when it is better on held-out poses.
        True if it was taken. Asked of the compliance of several joints on loads identified from the data, whose
        per-joint loads are free enough to take up causes of other kinds; a compliance on the mass data, or the
        lateral one, has its loads fixed by the statics (asked of those too, Agile Justin's compliance of every joint
        went for T4c's alone, which the mass data identified later did not favour: 3.33 -> 4.05 mm held out; once
        they are identified, `spread` asks the reverse)."""
        n_spread = len(c.effect.parameter_names(self.model))
        sub = dataclasses.replace(
            self, pool=[e for e in self.pool if len(e.joints) <= 1 or isinstance(e, SessionStep)],
            chosen=list(self.chosen), findings=list(self.findings), rejected=[])
        for _ in range(MAX_SPARSE):
            if not sub._round():
                break
        self.untested = self.untested or sub.untested
        new = sub.chosen[len(self.chosen):]
        if not new or sum(len(e.parameter_names(self.model)) for e in new) >= n_spread:
            return False
        hs, ht = sub.current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
        if hs >= ht:
            return False
        p, _ = holdout_gain(trial, sub.current)
        names = ", ".join(e.label(self.model) for e in new)
        self.rejected.append({**_who(c.effect, self.model), "why": f"{len(new)} cause(s) on single joints do better "
                                                                   f"on held-out poses ({names}: {hs:.3f} mm against "
                                                                   f"{ht:.3f} mm, paired p = {p:.2g})"})
        self.rejected += sub.rejected
        self.chosen, self.findings, self.current, self.x_ref = sub.chosen, sub.findings, sub.current, sub.x_ref
        return True

    def revisit(self, report: Callable[[float, str], None]) -> None:
        """Test each finding again with the others in the model (_revisit), until nothing changes (3 passes)."""
        for _ in range(3 if len(self.chosen) > 1 else 0):
            if self.late("each finding tested again with the others in the model"):
                break
            report(0.75, "revisiting each finding with the others in the model")
            before = list(self.chosen)
            self.current = _revisit(self.findings, self.chosen, self.current, self.pool, self.model, self.meas,
                                    self.sigma, self.alpha, self.fit, self.floor, self.rejected, self.load_pool)
            if self.chosen == before:
                break

    def masses_identified(self) -> bool:
        """A chosen compliance carries mass data identified from these poses."""
        return any(_mass_driven(e) and e.masses for e in self.chosen)

    def spread(self, notes: list[str], report: Callable[[float, str], None]) -> bool:
        """Once the mass data are identified, the compliance of several joints in place of the single joints' own
        that it covers, with the mass data identified again under everything. The greedy search can take one joint's
        compliance on the guessed masses before identified ones show the rest, and a candidate tried beside masses
        identified without it is judged on loads fitted to another model (Agile Justin, split 0: T4c's alone, then
        every joint's refused, 3.771 -> 3.849 mm held out). Kept when held-out poses find it better; True if it was."""
        taken = {_cause(e) for e in self.chosen}
        for e in self.pool:
            covered = [i for i, c in enumerate(self.chosen) if _subsumed(c, e)]
            if not covered or _cause(e) in taken or self.late("a spread compliance in place of single joints'"):
                continue
            report(0.82, f"{e.label(self.model)} in place of {len(covered)} single joint(s)")
            keep = [i for i in range(len(self.chosen)) if i not in covered]
            # every compliance on the model's mass data again, then those identified under them all (from the ones
            # identified without it, the steps stay near a model that lacked it)
            chosen = [_on_model_masses(self.chosen[i]) for i in keep] + [e]
            findings, said = [dict(self.findings[i]) for i in keep], list(notes)
            trial = _identify_masses(self.fit(chosen, self.current.x), chosen, findings, self.model, self.meas,
                                     self.fit, said)
            hb, ht = self.current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
            if not (_better(self.current, trial, HOLDOUT_ALPHA) and ht < hb):
                p, _ = holdout_gain(self.current, trial)
                self.rejected.append({**_who(e, self.model), "why": f"in place of {len(covered)} single joint(s), "
                                      f"the mass data identified again: held-out poses do not confirm it ({hb:.3f} -> "
                                      f"{ht:.3f} mm, paired p = {p:.1e})"})
                continue
            base = self.fit(chosen[:-1], trial.x)  # what the spread form adds, for its finding's figures
            ranked, _ = screen(base, self.meas, self.sigma, [chosen[-1]], base.x, self.alpha)
            if not ranked:
                continue
            self.rejected += [{**_who(self.chosen[i], self.model), "why": f"part of {e.label(self.model)}, which "
                               f"does better on held-out poses ({hb:.3f} -> {ht:.3f} mm)"} for i in covered]
            self.chosen, self.current, self.x_ref = chosen, trial, trial.x
            self.findings = findings + [_finding(ranked[0], self.model, base, trial, self.floor, [], self.meas)]
            notes[:] = said
            return True
        return False

    def identify_masses(self, notes: list[str], report: Callable[[float, str], None]) -> bool:
        """One joint fit on the final geometry, then the mass data under the compliances found
        (_identify_masses); True if identified masses replaced the model's. Only when a compliance needs mass data:
        the refit's bases (loads, a play's switch) follow the final geometry, which can undo a found play (a soft
        play's switch moved: 0.176 -> 0.267 mm held out). Keeping the refit only when held-out poses did not find
        it worse cost Agile Justin 3.33 -> 3.84 mm on split 0 (the masses are identified from it), so it stays."""
        if not any(_mass_driven(e) for e in self.chosen) or self.late("the mass data under the compliances found"):
            return False
        self.current = self.fit(self.current.effects, self.current.x)
        report(0.8, "identifying the mass data under the compliances found")
        before = self.current
        self.current = _identify_masses(self.current, self.chosen, self.findings, self.model, self.meas, self.fit,
                                        notes)
        return self.current is not before


def diagnose(model: RobotModel, meas: Measurements, *, alpha: float = ALPHA, repeatability_mm: float | None = None,
             loss: str | None = "auto", folds: int = 5, unexplained: bool = True,
             progress: Callable[[float, str], None] | None = None, deadline: float | None = None) -> Diagnosis:
    """Geometric fit, then the greedy search for causes; returns the extended calibration and the findings.
    When mass data are identified under the compliances found, the search resumes on them once; then each finding
    is tested again on them, and the compliance of several joints in place of the single joints' own it covers.

    deadline: a time.monotonic() value after which the search fits no further model and the answer is finished
    with what it has confirmed so far (`Diagnosis.untested` says what was left; thousands of poses can take longer
    than a job may run).

    loss 'auto' fits with the Huber loss when a first robust fit names outliers (the final model's are listed), else
    with plain least squares; poses flagged in runs of consecutive measurements, none absurdly far off, are
    structure (a warm-up, a re-homing) and stay at full weight (the notes say so)."""
    report = progress or (lambda f, msg: None)
    sigma = meas.noise_sigma_mm()
    report(0.05, "identifying the geometric model")
    notes: list[str] = []
    first = None
    if loss == "auto":
        first = identify(model, meas, loss="huber", folds=0)
        runs = _flagged_in_runs(first, meas)
        loss = "huber" if len(first.solution.outliers) and not runs and not _play_not_outliers(first, meas) else None
        if runs:
            notes.append(runs)
    selection = select_geometry(model, meas, loss=loss, folds=folds)
    geo = selection.calibration
    fit = _Fitter(model, meas, loss, folds, selection.free, selection.prior_scale)
    if not selection.helps:
        notes.append(selection.note)
    floor, note, basis = noise_floor_mm(meas, sigma, repeatability_mm)
    sigma = geo.sigma_mm  # screen with the weights of the fit: noise plus what the geometry leaves
    named, more = candidates(model, meas)
    notes += more
    x_ref = geo.x
    load_pool = _load_pool(geo, meas, sigma, x_ref)
    named += list(load_pool.values()) + _distributed(load_pool) + _lateral(geo, meas, sigma, x_ref)
    moving = [j for j in range(model.n_joints) if np.ptp(meas.joints[:, j]) > 1e-3]
    # a step is a model extension only where the data say when each pose was measured; row order is a guess
    steps = step_candidates(meas, moving) if meas.timestamp is not None else []
    search = _Search(model, meas, sigma, alpha, fit, floor, named + steps, load_pool, geo, geo.x, deadline=deadline)
    search.run(report)
    search.revisit(report)
    if search.chosen and search.identify_masses(notes, report) and search.run(report):
        # the guessed mass data hid causes a load closer to the real one shows (an elastic humanoid: the joints'
        # compliance is confirmed only once the lateral compliance's masses are identified): search on from there
        search.revisit(report)
        search.identify_masses(notes, report)
    if search.masses_identified():  # what the causes did on the guessed masses, on the identified ones
        search.revisit(report)
        search.spread(notes, report)
    found = {(f["kind"], tuple(f["joints"])) for f in search.findings}
    rejected = [r for r in search.rejected if (r["kind"], tuple(r["joints"])) not in found]
    current, chosen, findings, x_ref = search.current, search.chosen, search.findings, search.x_ref
    structure_left = _excess(current, floor) < alpha
    named = current  # the model of the named causes (what `unexplained` starts from)
    if unexplained and structure_left:
        report(0.85, "looking at what the residual left follows")
        follows = _follows(current, meas, sigma, x_ref, alpha, load_pool)
        held_out_rms = np.sqrt(holdout_ms(current))
        if follows or basis != "assumed" or held_out_rms / floor > NOISE_LIKE:
            trial = None
            fitted = [] if search.late("a smooth correction of what is left") else [
                fit_residual_field(fit, current, chosen, x_ref), _drive_field(fit, chosen, x_ref, follows)]
            for t, rf in sorted([f for f in fitted if f], key=lambda f: f[0].metrics()["holdout_rms_mm"]):
                if _better(current, t, HOLDOUT_ALPHA):
                    trial = (t, rf)
                    break
            before = current
            if trial is not None:
                current = trial[0]
            weighted = _with_pose_noise(current, fit, meas, next(
                (f["effect"] for f in follows if f.get("family") == "shared_by_targets"), None))
            said = ""
            if weighted is not None:
                current, said = weighted
                notes.append("what the targets of a pose share: " + said)
            findings.append(_unexplained_finding(model, before, trial, floor, follows, basis, current, said))
        else:
            new_floor = float(held_out_rms)
            notes.append(f"the residual ({new_floor:.3f} mm RMS held out) is above the assumed noise floor "
                         f"({floor:.3f} mm) but follows nothing: not time order, no joint, not the load, no region "
                         f"of the workspace; it looks like noise, so the robot's repeatability (or the instrument's "
                         f"noise) is probably worse than assumed. Measure some poses twice to know the floor.")
            note = f"estimated from the structure-free held-out residual (assumed floor was {floor:.3f} mm)"
            floor, basis = new_floor, "residual"
        structure_left = _excess(current, floor) < alpha  # current or floor has changed
    _chain(findings, geo, named, fit, search.x_ref, floor,
           None if deadline is not None and time.monotonic() > deadline else model)
    _with_switch_doubt(current, meas)
    _with_mass_doubt(current, fit, model)
    _judge_sizes(current, findings, meas)
    present_findings(current, findings)
    current.unmodelled_mm = _unmodelled_mm(current, floor, structure_left)
    if loss == "huber" and first is not None:
        notes.insert(0, _outlier_note(meas, first.solution.outliers, current.solution.outliers))
    nominal = selection.calibrations.get("registration") \
        or identify(model, meas, free=("base", "tool"), loss=loss, folds=folds)
    d = Diagnosis(calibration=current, geometric=geo, nominal=nominal, noise_floor_mm=floor, noise_note=note,
                  floor_basis=basis, findings=findings, rejected=rejected, notes=notes, loss=loss,
                  selection=selection.to_dict(), noise_model=meas.noise_source(), untested=search.untested)
    if search.untested:
        notes.insert(0, f"the search for causes stopped at its time budget; left untested: {search.untested}. What "
                        f"is named was confirmed on held-out poses, but causes not reached were never tested: this "
                        f"is not a complete answer (fewer poses, or a longer time budget, let it finish)")
    d.explanation = explain(d, model)
    report(1.0, "diagnosis done")
    return d


MASS_STEPS = 12
"""At most this many Gauss-Newton steps of the mass data under the compliances found (each a joint fit of both).
A base 20-30 mrad off level, with first moments that trade with the tilt, took 9-12 on the test tree (8 left 0.55
of the tilt on one draw in 15); most stop after 2-5 (MASS_TOL, TILT_TOL_RAD)."""
MASS_TOL = 0.01
"""The steps stop when no body's mass moves by more than this share of the mean body mass..."""
TILT_TOL_RAD = 1e-4
"""...and gravity's direction by less than this."""


def _subsumed(e: Effect, spread: Effect) -> bool:
    """`e` is one joint's linear compliance on the mass data and `spread` that of several joints, that one among
    them: the spread form has e's column, so it replaces e instead of doubling it (Agile Justin: the compliance of
    every joint beside T4c's own was judged with T4c's column twice)."""
    def linear(c: Effect) -> bool:
        return type(c) is JointCompliance and not c.stiffening and not c.load_coef
    return (linear(spread) and len(spread.joints) > 1 and linear(e) and len(e.joints) == 1
            and e.joints[0] in spread.joints)


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
    """A linear compliance driven by mass data (the model's or identified): its load is bilinear in compliance and
    mass."""
    return isinstance(e, LateralJointCompliance) or (type(e) is JointCompliance and not e.stiffening)


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
    try:  # two starts: from a tilt that trades with the first moments the steps can stop in a local minimum
        paths = [_mass_steps(chosen, idx, effects, t, phi, g, phi_model, model, fit, tilt_first)
                 for tilt_first in (False, True)]
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
    notes.append(f"{MASS_NOTE} (held-out {hb:.3f} -> {ha:.3f} mm, paired {_p(p_gain)}): "
                 + (shown or "no mass moved by more than 10 %")
                 + f"; gravity {off_mrad:.1f} mrad off the model's base z (the base frame the geometry defines is not "
                 "exactly level); the compliances' std are conditional on these masses and this gravity (the "
                 "prediction std carry their doubt)")
    return trial


def _mass_steps(chosen, idx, effects, t, phi, g, phi_model, model, fit, tilt_first: bool) -> tuple:
    """Gauss-Newton steps of the mass data and gravity's direction from (phi, g) under the compliances `idx` of
    `chosen`: (misfit, effects, x) of the step whose refit leaves the least on the calibration poses (a tilt that
    trades with the first moments can swing from step to step: Agile Justin). With `tilt_first` the first step
    moves gravity's direction alone (a base 25 mrad off level otherwise went into the first moments and stopped
    there: 0.090 mm against the truth where the noise gives 0.009, one test draw in about 30)."""
    phi, best = phi.copy(), None
    for k in range(MASS_STEPS):
        values = t.effect_values  # the compliances where the step linearises (fitted at the last masses)
        step = mass_step([(effects[i], values[i]) for i in idx], model, g)
        if tilt_first and k == 0:
            step = dataclasses.replace(step, bodies=(), prior=step.prior[-2:])
        t = fit(effects + [step], t.x, folds=0)
        delta, tilt = t.effect_values[-1][:-2].reshape(-1, 4), t.effect_values[-1][-2:]
        phi[list(step.bodies)] += delta
        phi[:, 0] = np.maximum(phi[:, 0], 0.0)
        g = tilted(g, tilt)
        masses = tuple(tuple(float(v) for v in row) for row in phi)
        effects = [dataclasses.replace(e, masses=masses, gravity=tuple(float(v) for v in g)) if i in idx else e
                   for i, e in enumerate(chosen)]
        refit = fit(effects, t.x, folds=0)
        misfit = float(np.sum(refit.solution.weights[:, None] * refit.solution.residual**2))
        if best is None or misfit < best[0]:
            best = (misfit, effects, refit.x)
        if step.bodies and np.abs(delta[:, 0]).max() < MASS_TOL * phi_model[list(step.bodies), 0].mean() and \
                np.abs(tilt).max() < TILT_TOL_RAD:
            break
    return best


def _p(p: float) -> str:
    """A p-value as prose: below double precision it is a bound, never 'p = 0.0e+00'."""
    return "p < 1e-300" if p < 1e-300 else f"p = {p:.1e}"


POSE_NOISE_MAX_POSES = 1000
"""The shared motion is weighted as noise of each pose up to this many poses: one nuisance column per pose, dense in
the fit's Jacobian (1000 poses of two targets: 6000 rows x 1000 columns more)."""


def _with_pose_noise(current: Calibration, fit: _Fitter, meas: Measurements, s: shared_motion.SharedMotion | None
                     ) -> tuple[Calibration, str] | None:
    """The motion the targets of a pose share, weighted as noise of each pose in the fit (generalised least squares,
    identify's `pose_noise`): what no function of the joint values predicts then pulls the parameters less toward
    the poses it happened to hit. The refit and a sentence saying so, if held-out poses find it better; else None
    (Agile Justin: 0.03 mm held out, RESULTS 3.10)."""
    if s is None or not s.size > 0 or len(np.unique(meas.pose_index())) > POSE_NOISE_MAX_POSES:
        return None  # no size: nothing to weigh (and a prior std of 0)
    chain = current.robot.chain(meas.joints, meas)[0]
    trial = fit(current.effects, current.x_basis, pose_noise=shared_motion.pose_noise(chain, meas, s))
    p, _ = holdout_gain(current, trial)
    hb, ha = current.metrics()["holdout_rms_mm"], trial.metrics()["holdout_rms_mm"]
    if not (_better(current, trial, HOLDOUT_ALPHA) and ha < hb):  # both: fewer outliers can raise the RMS shown
        return None
    size = f"{1e3 * s.size:.2f} mrad" if s.unit == "rad" else f"{s.size:.2f} mm"
    return trial, (f"the fit weights it as noise of each pose ({s.motion}, {size} RMS per pose; generalised least "
                   f"squares): held-out {hb:.3f} -> {ha:.3f} mm, paired {_p(p)}")


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
            "follows": [{k: v for k, v in f.items() if k != "effect"} for f in follows],
            "evidence": (f"after the named causes the held-out error ({hb:.3f} mm) is still {hb / floor:.1f}x the "
                         f"noise floor ({floor:.3f} mm) and no named cause explains it; {what}; {fix}"),
            "parameters": []}


def explain(d: Diagnosis, model: RobotModel) -> str:
    """One paragraph a process engineer can read; it says what the JSON says."""
    g = d.geometric.metrics()
    n_out = len(g["outliers"])
    out = f" (the {n_out} outlier{'s' if n_out > 1 else ''} left out)" if n_out else ""
    head = (f"After the geometric calibration the robot's held-out error is {g['holdout_rms_mm']:.3f} mm RMS{out} "
            f"against a noise floor of {d.noise_floor_mm:.3f} mm (what a perfect model would leave: {d.noise_note}).")
    gaps = d.gaps()
    caveat = (f" This pose set cannot identify {len(gaps)} parameter(s) ({', '.join(gaps[:6])}"
              f"{', ...' if len(gaps) > 6 else ''}): the model is valid only near the measured poses."
              if gaps else "")
    tail = (" " + " ".join(n if n.endswith(".") else n + "." for n in d.notes)) if d.notes else ""
    if not d.findings and d.untested:
        return head + " No cause was confirmed before the search stopped." + caveat + tail
    if not d.findings:
        if d.floor_basis == "residual":
            return head + " No cause was found and the residual follows nothing." + caveat + tail
        complete = "" if gaps else ", so the geometric model is complete"
        return head + f" No cause was found: the residual is at the noise floor{complete}." + caveat + tail
    parts = []
    for f in d.findings:
        joints, others = named_joints(f)
        who = (f" on {', '.join(joints)}" if joints else "") + (f" ({others})" if others else "")
        odd = ", a size no real joint has: a correction, not the cause" if f.get("physical") is False else ""
        name = f"{f['kind'].replace('_', ' ')}{who}"
        if f["kind"] == "correction":
            odd = f"; not a physical cause: {f.get('bound', 'its size is not physical')}"
            name = f"a correction that follows {follows_what(f)}"
        parts.append(f"{name} (held-out {f['holdout_rms_before_mm']:.3f} -> "
                     f"{f['holdout_rms_after_mm']:.3f} mm, {f['gain_pct']:.0f} % better{odd})")
    final = d.calibration.metrics()["holdout_rms_mm"]
    left = ""
    if any(f["kind"] == "unexplained" for f in d.findings):
        left = " Structure no named cause explains is left: see the unexplained finding for what it follows."
    return (head + " The residual still had structure. Found, in order: " + "; ".join(parts) +
            f". With these in the model the held-out error is {final:.3f} mm, "
            f"{final / d.noise_floor_mm:.2f}x the noise floor, a model error of {d.model_error_mm(d.calibration):.3f} mm "
            "beyond it." + left + caveat + tail)
