"""Gear plays whose switch is read off the residual: the switch search on the identified load, found again on each
fold and on resampled poses (its doubt), and flagged poses that are a play's switch, not outliers."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import special

from .. import kinematics as K
from ..effects import Backlash, Context, Effect, JointCompliance, has_loads, loads
from ..effects.gravity import carried_columns, drive_payload_load, drive_regressor
from ..effects.joint_effects import LOAD_DOUBT
from ..identify import Calibration, identify
from ..io import Measurements
from ..parallel import pmap
from ..solve import OUTLIER_U
from .screening import _robust_sigma, _weighted_columns, _weighted_system


PLAY_PASSES = 6
"""Times the play's switch is classified again on the residual with the fitted play put back."""
PLAY_SETTLED = 0.002
"""The switch has settled when no calibration pose's flank factor (-1 .. 1) moved by more than this in a pass:
fitting it again would give back nearly the same fit, so the passes stop there. On 80 drawn spray7 plays it fits
46 % fewer models than every pass, and the plays found fit the poses within 0.2 % of theirs (0.01 saved 56 % but
was 5 % worse on one draw: the soft play's search starts from the sharp one's switch)."""
SATURATES = 1.5
"""A play with fitted softness must reach tanh(1.5) = 0.9 of its flanks somewhere, else it is a spring."""
SHARPEST = 20.0
"""RMS of the fitted softness's argument Z beta at which a soft play is as sharp as the sharp one (transition 0.05
of a unit-RMS load)..."""
SHARPNESS_RIDGE = 0.001
"""...and the share of the offsets' weighted sum of squares a ridge on beta costs there. Without it a play that is
sharp on the data has no sharpest softness: the fit ran on along a flat valley (RMS 200-1200) to its evaluation cap,
and where it stopped (and the switch between the poses) followed rounding, by memory layout: arm6 play 2x #0 predicted
new poses at 0.51, 0.62 or 0.88x the noise from run to run."""


@dataclass(frozen=True)
class _LoadFeatures:
    """Joint j's identified-load regressor F (N, k): gravity regressor and payload columns, as Backlash.load_coef
    weighs them; Z (N, rank) the same span as unit-RMS orthogonal features, load = F @ (to_coef @ beta). Poses with
    equal rows of F (the targets of one pose: Agile Justin's two markers) get equal rows of Z, to the bit (the SVD's
    differ in the last bits), so the switch fits take them as one (_tied)."""

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
        first, twin = np.unique(F, axis=0, return_index=True, return_inverse=True)[1:]
        return cls(F, (U[:, :rank] * root_n)[first[twin.ravel()]], to_coef)

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
    return Context.at(cal.model, cal.basis_x, meas, cal.R0)


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
            off, w = _joint_offsets(col, residual + col * (v[0] * ctx.basis(e).joint[:, e.joints[0], 0])[:, None])
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
            out[i] = _found_again(e, feats, off, wt, start, train, ctx)
        return tuple(out)

    return effects


def _found_again(e: Effect, feats: _LoadFeatures, off: np.ndarray, wt: np.ndarray, start: np.ndarray,
                 train: np.ndarray, ctx: Context) -> Effect:
    """The identified play (or spring on a play's load) e with its switch classified again on the training poses
    alone, from `start` (a load, per pose) on the joint's offsets `off` (weights `wt`); e itself if that load never
    changes sign there."""
    Z = feats.Z[train]
    beta = _switch(Z, off[train], wt[train], np.linalg.lstsq(Z, start[train], rcond=None)[0])
    if e.fitted_softness:
        beta = _softness(Z, off[train], wt[train], beta)
    play = feats.play(e.joints[0], beta, e.fitted_softness)
    if play is not None and isinstance(e, JointCompliance):  # the spring on the load found again
        big = float(np.abs(play.load(ctx)).max())
        play = dataclasses.replace(e, load_coef=play.load_coef, load_scale=big) if big > 0 else None
    return play or e


def _refold_candidate(cal: Calibration, meas: Measurements, e: Effect, ctx: Context
                      ) -> Callable[[np.ndarray], Effect] | None:
    """For linear_holdout: a candidate identified play, not yet in cal, found again on each fold's training poses
    as _refold_plays finds a fitted one (its own part of the residual is zero here); None for other candidates. The
    switch found on every pose flatters the held-out figures of a play: on Agile Justin four plays looked confirmed
    (paired p < 1e-6) that the full refit, found per fold, put at p = 1."""
    if not _identified_play(e):
        return None
    j = e.joints[0]
    feats = _LoadFeatures.of(ctx.chain, meas, j)
    if feats is None:
        return None
    off, w = _joint_offsets(_joint_columns(cal, meas)[:, :, j], meas.points - cal.predict(meas.joints, meas))
    wt = w / _robust_sigma(cal, cal.sigma_mm) ** 2
    start = ctx.loads[:, j] if has_loads(cal.model, meas) else off
    return lambda train: _found_again(e, feats, off, wt, start, train, ctx)


SWITCH_WIDTHS = np.r_[0.0, np.logspace(-4, 0, 41)]
"""The switch widths tried, as shares of the largest |load| on the calibration poses (0: no doubt at all)."""
SWITCH_LR = 0.5 * (2.0 * special.gammaincinv(0.5, 0.95))  # chi2.ppf(0.95, 1), scipy.stats' arithmetic
"""Log-likelihood drop that bounds the width from above (95 % profile likelihood): a few calibration poses near
the switch cannot show that none is ever on the far flank, so the widest width they allow is taken."""


def _switch_width(e: Backlash, b: float, load: np.ndarray, off: np.ndarray, weight: np.ndarray) -> float:
    """Backlash.switch_width of the play e of size b (load units): the widest doubt about the load that picks the
    flank, N(0, width^2), that the calibration poses allow (95 % profile likelihood), each pose's reading `off` of
    the joint's offset (weight 1 / variance) b/2 flank(load + doubt) plus its noise. Mass data 15 % off put a few
    poses near the switch on the far flank, and fresh poses there are off by the whole play (a spray7 twin: 0.6 mm
    at a std of 0.02 mm)."""
    from scipy import stats  # here: scipy.stats is 0.5 s of import that the API process (no diagnosis) skips

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
    again on resampled poses (Backlash.flank_doubt): its prediction std then covers the poses near the switch. An
    identified switch's width is also judged held out (each resampled switch on the poses it was not found on; the
    median, where wider): in-sample, the poses that placed a switch always allow it narrow (arm6 hard plays held as
    soft ones: RMS z 2.3-3.8 over the fresh poses nearest the switch)."""
    plays = [i for i, e in enumerate(cal.effects) if isinstance(e, Backlash)]
    if not plays:
        return
    draws, masks = [], []
    if any(_identified_play(cal.effects[i]) for i in plays):
        refold, rng = _refold_plays(meas, cal), np.random.default_rng(0)  # same data, same answer
        masks = [rng.random(meas.n_poses) < 0.632 for _ in range(SWITCH_DRAWS)]
        draws = [refold(m) for m in masks]
    ctx = _basis_context(cal, meas)
    effects, readings = list(cal.effects), _play_readings(cal, meas, ctx)
    for i in plays:
        e, (off, wt), b = cal.effects[i], readings[i], cal.effect_values[i][0]
        again = [(d[i].load_coef, m) for d, m in zip(draws, masks) if d[i] is not e and d[i].load_coef]
        width = _switch_width(e, b, e.load(ctx), off, wt)
        if again:  # each switch found again judged on the poses it was not found on: a doubt not taken in-sample
            held = [_switch_width(e, b, e.load(ctx, c)[~m], off[~m], wt[~m]) for c, m in again]
            width = max(width, float(np.median(held)))
        effects[i] = dataclasses.replace(e, switch_width=width, switch_draws=tuple(c for c, _ in again))
    cal.effects = tuple(effects)


def _identified_backlash(cal: Calibration, meas: Measurements, sigma: np.ndarray, x_ref: np.ndarray,
                         joints: list[int], late: Callable[[], bool] = lambda: False, workers: int = 1
                         ) -> list[Backlash]:
    """Backlash whose switch follows the load identified from the data: per joint, a linear classifier of the
    sign of the residual along that joint's motion on the gravity regressor (started from the model's
    statics where there are masses). Its search is paid for in the F-test (`search_dof`), and each fold of the
    cross-validation finds the switch again on its own training poses (_refold_plays). Each pass refits the play
    with everything else at the current linearisation (_with_play_refitted). The joints are searched apart
    (`workers` processes, parallel.pmap); once `late()`, returns the plays of the joints before the one it cut."""
    model = cal.model
    sigma = _robust_sigma(cal, sigma)
    ref_ctx = Context.at(model, x_ref, meas, cal.R0)
    ref = ref_ctx.chain
    nominal = ref_ctx.loads if has_loads(model, meas) else None
    residual = meas.points - cal.predict(meas.joints, meas)
    Jq = _joint_columns(cal, meas)
    r, Q, chain = _weighted_system(cal, meas, sigma, x_ref)
    system = (r, Q, chain.joint_jacobian())

    def search(j: int) -> tuple[list[Backlash], bool]:
        """Joint j's plays (a sharp one, then one whose softness is fitted) and whether `late()` cut it short."""
        feats = _LoadFeatures.of(ref, meas, j)
        if feats is None:
            return [], False
        col = Jq[:, :, j]
        e, w = _joint_offsets(col, residual)
        sharp = feats.beta(nominal[:, j] if nominal is not None else e)
        out = []
        for soft in (False, True):
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
                if late():
                    return out, True
                # fit it, then find the switch again on the residual with the play put back (partial residual)
                partial = _with_play_refitted(system, play, ref_ctx, sigma)
            if play is not None:
                out.append(play)
                sharp = beta if not soft else sharp
        return out, False

    out = []
    for plays, cut in pmap(search, joints, workers):
        if cut:
            late()  # records what was left untested, here (a worker's record stays in the worker)
            break
        out += plays
    return out


def _with_play_refitted(system: tuple, play: Backlash, ctx: Context, sigma: np.ndarray) -> np.ndarray:
    """The residual (N, 3) mm with `play` fitted jointly with everything the current model fits, and the play's own
    part put back: at the current model's linearisation (one Gauss-Newton step on its weighted system (r, Q, joint
    Jacobian), Q an orthonormal basis of its columns). With c the play's weighted column and c' its part outside Q,
    the joint fit gives the play b = c'.r / c'.c' and leaves r - QQ'r - b c'; its part b c put back, r - QQ'r + b QQ'c.
    A full refit of every parameter per pass cost the play search hundreds of fits (Agile Justin: 620 s of 990)
    for the same switch."""
    r, Q, Jq = system
    c = _weighted_columns(play, ctx, Jq, sigma)[0][:, 0]
    inside = Q @ (Q.T @ c)
    outside = c - inside
    b = float(outside @ r) / max(float(outside @ outside), 1e-300)
    return (r - Q @ (Q.T @ r) + b * inside).reshape(-1, 3) * sigma[:, None]


def _flank_moved(a: Backlash, b: Backlash, ctx: Context) -> float:
    """The largest change of the flank factor (-1 .. 1) on these poses from play a's switch to b's."""
    return float(np.abs(a.flank(a.load(ctx)) - b.flank(b.load(ctx))).max())


def _minpack_lm(fun: Callable, jac: Callable, p0: np.ndarray, max_nfev: int) -> np.ndarray:
    """MINPACK's Levenberg-Marquardt (lmder) from p0, as scipy's least_squares(method="lm") runs it with its default
    tolerances, without that front's per-evaluation wrappers (the play search's small fits spent 2/3 of their time
    in them). The same iterates: 321 of the Motoman's 322 fits gave identical answers."""
    from scipy import optimize  # here: scipy.optimize is 0.6 s of import that the API process skips

    return optimize.leastsq(fun, p0, Dfun=jac, full_output=True, ftol=1e-8, xtol=1e-8, gtol=1e-8, maxfev=max_nfev,
                            factor=100.0, diag=None)[0]


def _tied(Z: np.ndarray, e: np.ndarray, sw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The rows of a weighted fit of g(Z beta) to e (root weights sw) with equal rows of Z taken as one: their
    weighted mean offset at their summed weight, and the offsets' scatter about those means (a constant) as one more
    residual, so the sum of squares, its gradient and every Gauss-Newton step are those of all the rows, on half of
    them for Agile Justin's two markers per pose (MINPACK's QR is the switch search's cost); rows of no weight (a
    joint that does not move a target) drop out. (Z, e, sw, 0.0) when no two rows are equal and none is weightless."""
    w = sw**2
    if np.all(w > 0) and len(np.unique(Z[:, 0])) == len(Z):  # every row apart (one target), told by one column
        return Z, e, sw, 0.0
    rows, first, group = np.unique(Z, axis=0, return_index=True, return_inverse=True)
    group = group.ravel()
    W = np.bincount(group, weights=w, minlength=len(rows))
    mean = np.bincount(group, weights=w * e, minlength=len(rows)) / np.where(W > 0, W, 1.0)
    scatter = float(np.sqrt(np.sum(w * (e - mean[group]) ** 2)))
    keep = np.sort(first[W > 0])  # in the order the poses come
    return Z[keep], mean[group[keep]], np.sqrt(W[group[keep]]), scatter


def _switch(Z: np.ndarray, e: np.ndarray, weight: np.ndarray, beta0: np.ndarray) -> np.ndarray:
    """Where a play switches: the load direction beta (on unit-RMS features Z) for which b/2 tanh(Z beta / t)
    best fits the per-pose joint offsets e (weighted least squares), t sharp. For b > 0 that is the classifier of
    sign(e) weighted by w |e| (sum w e s is what a flank s = +-1 gains); its convex surrogate, a weighted logistic
    regression (Newton, from beta0), places it, and one fit of the tanh model finishes it."""
    sw = np.sqrt(weight / max(weight.mean(), 1e-300))
    beta = _logistic(Z, np.sign(e), sw**2 * np.abs(e), beta0)
    t = 0.05
    s0 = np.tanh(Z @ beta / t)
    b = 2.0 * float((sw**2 * s0 * e).sum() / max((sw**2 * s0 * s0).sum(), 1e-300))
    tanh = _TanhFit(*_tied(Z, e, sw), t)
    p = _minpack_lm(tanh.fun, tanh.jac, np.r_[b, beta], 50)
    return _unit_rms(Z, p[1:] * np.sign(p[0]))


class _TanhFit:
    """The weighted residual of b/2 tanh(Z beta / t) against the offsets e and its Jacobian in (b, beta), for MINPACK,
    with `_tied`'s scatter as one more row and, given `ridge`, ridge rows on beta: MINPACK asks for the Jacobian where
    it has just evaluated the residual, so tanh is computed once for both, and each array is written in place of the
    stacks built per call (a switch search's fits call these some 12,000 times on the Motoman). The same arithmetic,
    element by element, as the expressions written out (t = 1 divides exactly)."""

    def __init__(self, Zt: np.ndarray, et: np.ndarray, swt: np.ndarray, scatter: float, t: float,
                 ridge: float | None = None):
        self.Zt, self.et, self.swt, self.nsw, self.scatter, self.t = Zt, et, swt, -swt, scatter, t
        self.m, k = Zt.shape
        self.rows = self.m + (k if ridge is not None else 0) + 1
        self.ridge, self.ridge_eye = ridge, None if ridge is None else ridge * np.eye(k)
        self._at: tuple[bytes, np.ndarray] | None = None

    def _tanh(self, p: np.ndarray) -> np.ndarray:
        key = p.tobytes()
        if self._at is None or self._at[0] != key:
            self._at = (key, np.tanh(self.Zt @ p[1:] / self.t))
        return self._at[1]

    def fun(self, p: np.ndarray) -> np.ndarray:
        """swt (e - b/2 tanh(Z beta / t)), then ridge beta, then the scatter."""
        out = np.empty(self.rows)
        np.multiply(self.swt, self.et - 0.5 * p[0] * self._tanh(p), out=out[:self.m])
        if self.ridge is not None:
            out[self.m:-1] = self.ridge * p[1:]
        out[-1] = self.scatter
        return out

    def jac(self, p: np.ndarray) -> np.ndarray:
        """d fun / d (b, beta): -swt (tanh / 2, b / (2 t) (1 - tanh^2) Z), ridge I on beta, a zero row."""
        th = self._tanh(p)
        J = np.zeros((self.rows, len(p)))
        J[:self.m, 0] = self.nsw * (0.5 * th)
        J[:self.m, 1:] = self.nsw[:, None] * (((0.5 * p[0] / self.t) * (1.0 - th**2))[:, None] * self.Zt)
        if self.ridge is not None:
            J[self.m:-1, 1:] = self.ridge_eye
        return J


def _unit_rms(Z: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """beta scaled so that the load direction Z beta has unit RMS over the poses."""
    return beta / max(float(np.sqrt(np.mean((Z @ beta) ** 2))), 1e-300)


LOGISTIC_RIDGE = 1e-3
"""Ridge of the switch's logistic regression, per unit of the mean pose weight: separable poses have no finite
optimum without it."""


def _logistic(Z: np.ndarray, y: np.ndarray, c: np.ndarray, beta0: np.ndarray) -> np.ndarray:
    """The weighted logistic regression of labels y (+-1) on Z (weights c, ridge LOGISTIC_RIDGE), by Newton from
    beta0; its direction scaled to unit RMS of Z beta."""
    c = c / max(float(c.mean()), 1e-300)
    lam = LOGISTIC_RIDGE * len(y)

    def loss(beta):
        return float(c @ np.logaddexp(0.0, -y * (Z @ beta))) + 0.5 * lam * float(beta @ beta)

    beta = _unit_rms(Z, beta0)
    now = loss(beta)
    for _ in range(30):
        sig = special.expit(-y * (Z @ beta))  # d/dm log(1 + exp(-m)) = -sig
        grad = -Z.T @ (c * y * sig) + lam * beta
        H = (Z * (c * sig * (1.0 - sig))[:, None]).T @ Z + lam * np.eye(len(beta))
        step = np.linalg.solve(H, grad)
        for _ in range(30):  # halved until the loss does not rise (a start far out on the flat tails)
            trial = loss(beta - step)
            if trial <= now:
                break
            step = 0.5 * step
        beta, now = beta - step, min(trial, now)
        if float(np.abs(step).max()) < 1e-8 * max(float(np.abs(beta).max()), 1.0):
            break
    return _unit_rms(Z, beta)


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
    linear = _unit_rms(Z, linear)
    starts = [beta / t for t in (0.05, 0.15, 0.5, 1.5)] + [linear * a for a in (0.5, 1.0, 2.0, 4.0)]
    start = min(starts, key=lambda bb: cost(Z @ bb))

    ridge = np.sqrt(SHARPNESS_RIDGE * float(np.sum((sw * e) ** 2))) / SHARPEST  # see SHARPNESS_RIDGE
    tanh = _TanhFit(*_tied(Z, e, sw), 1.0, ridge)
    p = _minpack_lm(tanh.fun, tanh.jac, np.r_[amplitude(Z @ start), start], 50)
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
