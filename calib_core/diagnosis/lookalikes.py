"""Which form of a confirmed cause is kept: rivals that explain nearly as much (look-alikes), richer forms of it
(refinements), a step's exact place, and each finding tested again with the others in the model."""
from __future__ import annotations

import dataclasses

import numpy as np

from ..effects import (Backlash, Context, Effect, JointCompliance, LinkDeflection, LoadCompliance, RootTurnLinkDeflection,
                       TiltedLinkDeflection, has_loads, loads, on_joints)
from ..effects.structure import STEP_WINDOW, at_gap, session_clock
from ..parallel import pmap
from .evidence import HOLDOUT_ALPHA, REFINE_ALPHA, _better, _holdout_rms_every_pose, holdout_gain
from .findings import STRONG_STD, _beyond, _finding, _who, bent_up
from .screening import Candidate, _thresholds, screen

LOOKALIKE = 0.8
MAX_LOOKALIKES = 4
INDISTINGUISHABLE = 1.02
"""Rivals explaining at least LOOKALIKE of the winner's share are refitted and judged on held-out poses."""


def _best_of_lookalikes(c, trial, ranked, thresholds, model, fit, chosen, x_ref, share=None):
    """Some causes look alike over a limited range (a scale error and a first harmonic, a short link's
    bending and the compliance of the joint before it): among the significant candidates that explain
    nearly as much as the winner, keep the best on held-out poses and name the ones it cannot beat."""
    tried = [(c, trial)]
    share = LOOKALIKE if share is None else share
    rivals = [a for a in ranked if a is not c and a.log_p <= thresholds.get(id(a.effect), -np.inf)
              and a.explained >= share * c.explained]
    rivals = rivals[:MAX_LOOKALIKES]
    tried += zip(rivals, pmap(fit.apart(lambda a: fit(chosen + [a.effect], x_ref)), rivals, fit.workers, fit.shared))
    tried = _simplest_first(tried, model)
    # a compliance of several joints that the simpler pick passed over, on its strong joints: springs on two joints
    # of five are as few parameters as a link's bending (only then: each is a fit of the whole model)
    h = tried[0][1].metrics()["holdout_rms_mm"]
    narrowed = [(Candidate(**{**a.__dict__, "effect": n, "label": n.label(model)}), n) for a, t in tried[1:]
                if t.metrics()["holdout_rms_mm"] < h and (n := _on_strong_joints(a.effect, t, model)) is not None]
    if narrowed:
        fits = pmap(fit.apart(lambda an: fit(chosen + [an[1]], x_ref)), narrowed, fit.workers, fit.shared)
        tried = _simplest_first(tried + [(a, t) for (a, _), t in zip(narrowed, fits)], model)
    best = tried[0][1].metrics()["holdout_rms_mm"]
    same = lambda e: (e.kind, e.joints, e.harmonic)  # noqa: E731
    alike = _merge_alike([{**_who(a.effect, model), "holdout_rms_after_mm": t.metrics()["holdout_rms_mm"]}
                          for a, t in tried[1:] if t.metrics()["holdout_rms_mm"] <= INDISTINGUISHABLE * best
                          and same(a.effect) != same(tried[0][0].effect)])
    return tried[0][0], tried[0][1], alike


def _simplest_first(tried: list, model) -> list:
    """(candidate, fit) pairs by held-out error, the pick first: the simplest form that held-out poses cannot show to
    be worse than the best one (parsimony); a bending link that bends the wrong way (_bends_up) gives way to the
    simplest bending link among them that does not. Only to a link: a link fitted the wrong way can still be the
    right kind in the wrong shape (the world's elastic bearings, taken by a joint's spring instead in 2 of 760
    detection draws when any form came first)."""
    tried = sorted(tried, key=lambda t: t[1].metrics()["holdout_rms_mm"])
    best_fit = tried[0][1]
    by_size = sorted(tried, key=lambda t: (len(t[0].effect.parameter_names(model)), t[1].metrics()["holdout_rms_mm"]))
    fair = [t for t in by_size if t is tried[0] or not _better(t[1], best_fit, 0.05)]
    pick = fair[0]
    if _bends_up(pick[0].effect, pick[1]):
        pick = next((t for t in fair if isinstance(t[0].effect, LinkDeflection) and not _bends_up(t[0].effect, t[1])),
                    pick)
    return [pick] + [t for t in tried if t is not pick]


def _bends_up(e: Effect, cal) -> bool:
    """A link's bending in `cal` with a compliance (of its carried load or of its own weight, 1/(EI) times mass data
    that are off by some per cent) below -SIGNIFICANT_STD std: the link would bend up under its weight, which no beam
    does. Such a fit is a look-alike taking another cause's shape: spray7's telescopic stage sagging as its tube
    comes out, named as the link before it with its own weight at -9.5 std (seed 983100358), the stage's own form
    as good on held-out poses."""
    if not isinstance(e, LinkDeflection):
        return False
    mine = set(e.parameter_names(cal.model))
    return bool(bent_up([p for p in cal.parameters() if p["name"] in mine]))


def _on_strong_joints(e: Effect, cal, model) -> Effect | None:
    """A plain compliance of several joints on those of its joints beyond STRONG_STD std of zero in `cal` (None if
    all or none are): the look-alikes judge a rival spread over the arm in the form the search would narrow it to,
    not by its count of parameters (arm6, springs on A2 and A3 at 1x: A3's bending kept over the compliance of
    A2-A6 as the simpler form)."""
    if not (type(e) is JointCompliance and not e.stiffening and not e.load_coef and len(e.joints) > 2):
        return None
    table = {p["name"]: p for p in cal.parameters()}
    strong = tuple(j for j in e.joints if _beyond(table.get(f"{model.joint_names[j]}.compliance", {})) > STRONG_STD)
    return on_joints(e, strong) if 0 < len(strong) < len(e.joints) else None


STIFFENING = (0.5, 1.5, 4.0, 12.0, 30.0)
"""Stiffening ratios (cubic over linear stiffness at the largest load) tried for a found spring."""
SOFT_PLAY = (0.002, 0.07, 0.15, 0.3, 0.5)
"""Transitions (share of the largest model load) of a sharper or a soft gear play, tried when a play on the
model's statics is found (the default is 0.02); a play on the identified load has its softness fitted."""


def _refinements(e: Effect, load_pool: dict[int, LoadCompliance], play_pool: dict[int, list[Backlash]],
                 ctx: Context, rivals: tuple = ()) -> list[Effect]:
    """Richer forms of an accepted cause, kept only if held-out poses prefer them: a stiffening spring, the
    load identified from the data instead of the mass data, a play whose switch follows the identified load,
    a soft play (the joint moves through its play elastically near zero load), a bending link whose root turns
    under its bending moment (RootTurnLinkDeflection: a revolute link's; a telescopic stage's guide is a candidate of
    its own), a bending link on a tilted base,
    also where the link is a look-alike among `rivals` (a spring the same poses cannot tell from it was kept as the
    simpler form: spray7's J3 link under a tilt, named J3's spring at 2x). ctx: the poses at the reference."""
    out: list[Effect] = [TiltedLinkDeflection(r.joints) for r in rivals
                         if type(r) is LinkDeflection and type(e) is not LinkDeflection]
    if len(e.joints) != 1:
        return out
    j = e.joints[0]
    spring_or_play = isinstance(e, (JointCompliance, Backlash)) and not getattr(e, "stiffening", 0)
    if spring_or_play and has_loads(ctx.model, ctx.meas):
        # a soft play and a stiffening spring both deflect less and less as the load grows: try both, on the mass
        # data the spring carries (identified under it, or the model's)
        mass = {"masses": getattr(e, "masses", ()), "gravity": getattr(e, "gravity", ())}
        load = ctx.loads if not any(mass.values()) else loads(
            ctx.chain, ctx.meas, np.asarray(mass["masses"], float) if mass["masses"] else None,
            np.asarray(mass["gravity"], float) if mass["gravity"] else None)
        big = float(np.abs(load[:, j]).max())
        out += [JointCompliance(e.joints, stiffening=r, load_scale=big, **mass) for r in STIFFENING]
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
    if type(e) is LinkDeflection:  # part of its sag turned sideways by a base that is not level; its root giving
        out.append(TiltedLinkDeflection(e.joints))  # (a telescopic stage's guide is a candidate of its own)
        if not ctx.model.prismatic[j]:
            out.append(RootTurnLinkDeflection(e.joints))
    return out


def _merge_alike(alike: list[dict], more: list[dict] = ()) -> list[dict]:
    """Look-alikes `alike` and `more`, one per cause (kind, joints, harmonic): the form of it that did best on held-out
    poses, where the prose named a bent link and its tilted form as "link_deflection J6, link_deflection J6"."""
    best: dict = {}
    for a in [*alike, *more]:
        key = (a["kind"], tuple(a["joints"]), a.get("harmonic"))
        if key not in best or a.get("holdout_rms_after_mm", np.inf) < best[key].get("holdout_rms_after_mm", np.inf):
            best[key] = a
    return list(best.values())


def _refine(c, trial, chosen, load_pool, play_pool, model, fit, x_ref, rivals=()):
    """Swap the accepted cause for a richer form of it when held-out poses say so: among the forms that are
    significantly better than it (paired test), the best on held-out poses; the other forms within 2 % of it,
    or not significantly worse, are look-alikes (a stiffening spring and a soft play both bend less and less
    as the load grows)."""
    ctx = Context.at(model, x_ref, fit.meas)

    def refit(alt: Effect):
        try:  # a form of a cause already found replaces it (a play refined into the spring found before)
            return fit([e for e in chosen if _cause(e) != _cause(alt)] + [alt], x_ref)
        except ValueError:
            return None

    forms = _refinements(c.effect, load_pool, play_pool, ctx, rivals)
    tried = [(alt, t) for alt, t in zip(forms, pmap(fit.apart(refit), forms, fit.workers, fit.shared)) if t is not None]
    better = [(alt, t) for alt, t in tried if _better(trial, t, REFINE_ALPHA)]
    best, t = min(better, key=lambda at: at[1].metrics()["holdout_rms_mm"]) if better else (c.effect, trial)
    h = t.metrics()["holdout_rms_mm"]
    alike = [{**_who(a, model), "holdout_rms_after_mm": ta.metrics()["holdout_rms_mm"]}
             for a, ta in tried if a is not best and a.kind != best.kind
             and (ta.metrics()["holdout_rms_mm"] <= INDISTINGUISHABLE * h or not _better(ta, t, 0.05))]
    alike = _merge_alike(alike)
    if best is c.effect:
        return c, trial, alike
    return Candidate(**{**c.__dict__, "effect": best, "label": best.label(model)}), t, alike


def _refine_step(c, trial, chosen, current, sigma, model, meas, fit, x_ref):
    """Place an accepted step exactly: every gap between consecutive poses in time order near the searched
    one is scored by how much of the current model's weighted residual it removes at its linearisation (screen;
    a nonlinear fit per gap cost Hilti 17 fits per step), the best is fitted and kept if
    held-out poses do not object."""
    clock, _ = session_clock(meas)
    order = np.sort(clock)
    k = int(np.searchsorted(order, c.effect.at))
    gaps = range(max(k - STEP_WINDOW, 1), min(k + STEP_WINDOW, len(order) - 1) + 1)
    ranked = screen(current, meas, sigma, [dataclasses.replace(c.effect, **at_gap(order, i, c.effect.source))
                                           for i in gaps], x_ref)
    best = max(ranked, key=lambda a: a.explained, default=None)
    if best is None or best.effect == c.effect:
        return c, trial
    t = fit(chosen + [best.effect], x_ref)
    if _holdout_rms_every_pose(t) > _holdout_rms_every_pose(trial):
        return c, trial
    return Candidate(**{**c.__dict__, "effect": best.effect, "label": best.label}), t


def _revisit(findings, chosen, current, pool, model, meas, sigma, alpha, fit, floor, rejected, load_pool):
    """Greedy order can mislead when causes overlap: test each finding again against its look-alikes with
    every other finding in the model; swap it for a better one, or name the ones it cannot beat. A form swapped in
    gets its richer forms tried (_refine), as a form the search accepted does. A finding the others explain goes to
    `rejected`, with the figures."""
    k, without = 0, {}  # the model without finding i, each from the same start (fit.apart), while nothing changed
    while k < len(chosen):
        if k not in without:  # with several processes, every finding's at once (one is wasted if one goes)
            rest = list(range(k, len(chosen) if fit.workers > 1 else k + 1))
            without = dict(zip(rest, pmap(fit.apart(lambda i: fit(chosen[:i] + chosen[i + 1:], current.x)), rest,
                                          fit.workers, fit.shared)))
        others = chosen[:k] + chosen[k + 1:]
        base = without[k]
        if not _better(base, current, HOLDOUT_ALPHA):  # the others explain what it did: it goes
            p, _ = holdout_gain(base, current)
            hb, hc = base.metrics()["holdout_rms_mm"], current.metrics()["holdout_rms_mm"]
            rejected.append({**_who(chosen[k], model), "why": f"found earlier, but with the other findings in the "
                             f"model held-out poses no longer confirm it ({hb:.3f} mm without it, {hc:.3f} mm with "
                             f"it, paired p = {p:.1e})"})
            del chosen[k], findings[k]
            current, without = base, {}
            continue
        k += 1
        taken = {_cause(e) for e in others}  # one form per cause (_cause)
        rest = [e for e in pool if _cause(e) not in taken]
        if chosen[k - 1] not in rest:
            rest.append(chosen[k - 1])
        ranked = screen(base, meas, sigma, rest, current.x, fit.workers)
        mine = next((c for c in ranked if c.effect == chosen[k - 1]), None)
        if mine is None:
            continue
        thresholds = _thresholds(rest, alpha)
        c, _, alike = _best_of_lookalikes(mine, current, ranked, thresholds, model, fit, others, current.x,
                                          share=0.5)
        if c is not mine:
            chosen[k - 1] = c.effect
            current, without = fit(chosen, current.x), {}
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


def _cause(e: Effect):
    """What a candidate is a form of: a joint's play or compliance is one cause whatever its form (sharp or soft, on
    the mass data or the identified load, linear or stiffening), so its forms replace each other (_refine), never add
    up (a soft play beside a sharp one passed the held-out test on one arm6 world and doubled the error on fresh
    poses); any other cause is itself on the model's mass data."""
    if isinstance(e, (Backlash, JointCompliance, LoadCompliance)) and len(e.joints) == 1:
        return e.kind, e.joints
    identified = getattr(e, "masses", ()) or getattr(e, "gravity", ())
    return dataclasses.replace(e, masses=(), gravity=()) if identified else e
