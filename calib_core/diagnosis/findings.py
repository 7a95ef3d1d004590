"""The findings of the answer: how a confirmed cause is named and written up, judged against physical sizes,
presented from the final parameter table, and given per-cause figures that chain."""
from __future__ import annotations

import numpy as np

from ..effects import Effect, SessionStep
from ..effects.structure import ORDER_NAMES
from ..identify import Calibration
from ..io import Measurements
from ..model import RobotModel
from .evidence import _p, holdout_gain, model_error_mm
from .fitter import _Fitter
from .plays import _basis_context
from .screening import Candidate
from .time_structure import _when


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
    """A cause in prose: kind, joints and harmonic ('cyclic_joint_error L1 h2'); a step by its form (its kind,
    `unexplained`, says nothing: 'step[robot @ 437]')."""
    if a["kind"] == "unexplained" and a.get("form"):
        return a["form"]
    return " ".join([a["kind"], ",".join(a["joints"])] + ([f"h{a['harmonic']}"] if "harmonic" in a else [])).strip()


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
        out["follows"] = [{"what": ORDER_NAMES[e.source], "detail": when, "joints": _names(e, model), "p_value": c.p_value}]
    if alike:
        out["indistinguishable_from"] = alike
        later = isinstance(e, SessionStep) and all(str(a.get("form", "")).startswith("step[") for a in alike)
        out["evidence"] += ("; on this pose set it cannot be told apart from " +
                            ", ".join(_said(a) for a in alike) + " (held-out within 2 %): " +
                            ("steps in the session, which no pose measured from now on can separate (it comes after "
                             "both); the session's log can" if later else "measure poses that separate them to be sure"))
    return out


PLAUSIBLE_TURN_RAD = 0.1
"""A gear play, a spring or a bearing turns a joint by a fraction of a degree on an industrial robot, by a few on an
elastic humanoid (Agile Justin: up to 3 deg); a form that needs more than this (5.7 deg) stands in for something
else."""
PLAUSIBLE_TRAVEL_MM = 10.0
"""The same for a prismatic joint (a rail's or a telescope's play or spring)."""


def _judge_sizes(cal: Calibration, findings: list[dict], meas: Measurements) -> None:
    """Marks a finding whose form needs an unphysical size at a calibration pose ("physical": false, and its
    evidence says so): held-out poses confirmed it, so it stays in the model, but its values are not the joint's.
    A step in time order has no such bound: a joint re-homed or a tracker moved can be off by any amount (the
    Motoman's T1 by 2.7 deg)."""
    model, ctx = cal.model, _basis_context(cal, meas)
    for f in findings:
        names = {p["name"] for p in f.get("parameters", [])}
        sizes = []
        for e, v in zip(cal.effects, cal.effect_values):
            if e.bounded and names & set(e.parameter_names(model)):
                for j, t in e.turns(ctx, v):
                    big, linear = float(np.abs(t).max()), j >= 0 and model.prismatic[j]
                    if big > (PLAUSIBLE_TRAVEL_MM if linear else PLAUSIBLE_TURN_RAD):
                        sizes.append(f"{model.joint_names[j] if j >= 0 else 'the robot on its mount'} by up to "
                                     + (f"{big:.3g} mm" if linear else f"{np.degrees(big):.3g} deg"))
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
                          f"{' or '.join(limits)} a real play, spring, bearing or mount moves")
            if plays:
                f["bound"] += "; " + plays
            f["evidence"] += (f"; its size is not physical: it would move {', '.join(sizes)} at a calibration pose, "
                              f"where a real play, spring, bearing or mount turns by a fraction of a degree. The "
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
LINK_COMPLIANCES = (".link_compliance", ".link_compliance_own_weight")
"""A bending link's compliances (1/(EI) times what it carries, times its own weight): no link bends up under either."""


def bent_up(params: list[dict]) -> list[dict]:
    """Of a parameter table's rows, a bending link's compliances below -SIGNIFICANT_STD std: the link bending up."""
    return [p for p in params if p["name"].endswith(LINK_COMPLIANCES) and _beyond(p) < -SIGNIFICANT_STD]
STRONG_STD = 3.0
"""A compliance of several joints is tried on its joints beyond this many std of zero before those beyond
SIGNIFICANT_STD (_Search.narrowed; kept when held-out poses do not find the wider form better), and so is a rival
one among the look-alikes (_best_of_lookalikes)."""
FOLLOWS = {"joint_compliance": "the load on {j}", "backlash": "the sign of the load on {j}",
           "link_deflection": "the bending load on {j}", "cyclic_joint_error": "the angle of {j}",
           "joint_scale": "the travel of {j}", "axis_straightness": "the travel of {j}",
           "thermal_drift": "time or temperature", "base_compliance": "the robot's overturning moment on its mount"}
"""What a correction follows, in words, by the kind it was fitted as."""


def follows_what(f: dict) -> str:
    """What a finding's form follows, in words ('the load on R6'), by the kind it was fitted as."""
    kind = f["follows"] if f.get("kind") == "correction" else f.get("kind", "")
    j = ", ".join(f.get("joints") or [])
    return FOLLOWS.get(kind, kind.replace("_", " ") + (" on {j}" if j else "")).format(j=j or "the robot")


def is_named(f: dict) -> bool:
    """A finding the answer names as a physical cause: not `unexplained`, not a correction (no physical size), and
    with a size the final model shows (`significant` not false)."""
    return f.get("kind") not in ("unexplained", "correction") and f.get("physical") is not False \
        and f.get("significant") is not False


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


def _jointly_beyond(cal: Calibration, names: list[str]) -> bool | None:
    """The parameters `names` of cal's effects, together, are beyond SIGNIFICANT_STD std of zero (the chi-square of
    the vector with its covariance against the two-sided tail of that many std); None where the covariance is not
    known. A telescopic stage's bending and its guide's turn trade (each within 2 std, the pair at p = 1e-20)."""
    from scipy import stats  # here: scipy.stats is 0.5 s of import that the API process (no diagnosis) skips

    cov = cal.solution.cov
    if cov is None:
        return None
    pos = {n: len(cal.free) + i for i, n in enumerate(n for e in cal.effects for n in e.parameter_names(cal.model))}
    idx = [pos[n] for n in names if n in pos]
    if not idx or not np.all(np.isfinite(cov[np.ix_(idx, idx)])):
        return None
    v, C = cal.solution.x[idx], cov[np.ix_(idx, idx)]
    d = np.sqrt(np.maximum(C.diagonal(), 1e-300))
    z2 = float((v / d) @ np.linalg.lstsq(C / np.outer(d, d), v / d, rcond=1e-12)[0])
    return bool(stats.chi2.sf(z2, len(idx)) < 2 * stats.norm.sf(SIGNIFICANT_STD))


def present_findings(cal: Calibration, findings: list[dict]) -> None:
    """How the answer presents each finding, from the final model's parameter table (what is fitted is not touched):
    its parameters and the values its evidence quotes are the table's (a later refit moves them).
    A finding on several joints lists in `significant_joints` the joints whose own parameters are beyond
    SIGNIFICANT_STD std of zero, and its evidence names the others. A finding that breaks its physical bound (a size
    no real joint has, `_judge_sizes`; a joint compliance below -SIGNIFICANT_STD std: a spring never pushes back the
    wrong way; a bending link whose every compliance is below it: no link bends up under a load) is not presented
    under a physical name: its kind becomes "correction", with `follows` (the kind it
    was fitted as), `physical` false, `bound` (the bound it breaks, with the numbers) and one plain sentence first
    in its evidence: what it follows, what it gains held out, and why it is not a physical cause. A compliance whose
    negative joints are all within SIGNIFICANT_STD std of zero stays physical; a bending link with one share below
    it and one not stays named, that share said as a correction within it (`negative_parameters`)."""
    table = {p["name"]: p for p in cal.parameters()}
    for f in findings:
        if f.get("kind") == "correction" or "correction" in f or not f.get("parameters"):
            continue  # the residual's `unexplained` (with the correction it kept); a step is presented as a cause
        params = f["parameters"] = [{**p, **table.get(p["name"], {})} for p in f["parameters"]]
        sized = all(p.get("std") is not None and np.isfinite(p["std"]) and p["std"] > 0 for p in params)
        if params and sized and not any(abs(_beyond(p)) > SIGNIFICANT_STD for p in params) \
                and not _jointly_beyond(cal, [p["name"] for p in params]):
            # what it explained when it was found, the causes found after it explain: no size the final model shows
            f["significant"] = False
            f["evidence"] += (f"; in the final model none of its parameters is beyond {SIGNIFICANT_STD:g} std of "
                              f"zero, alone or together: the causes found after it explain what it explained, so it "
                              f"is not named as a cause of its own (the model keeps it; its size there is not known)")
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
        wrong = bent_up(params) if f["kind"] == "link_deflection" else []
        if wrong:
            f["negative_parameters"] = [p["name"] for p in wrong]
            said = ", ".join(f"{p['name']} = {p['value']:.3g} +/- {p['std']:.2g}"
                             f"{' ' + p['unit'] if p.get('unit') else ''}" for p in wrong)
            why = (f"{said} {'is' if len(wrong) == 1 else 'are'} negative by more than {SIGNIFICANT_STD:g} std, and "
                   f"no link bends up under a load")
            if len(wrong) < sum(p["name"].endswith(LINK_COMPLIANCES) for p in params):  # named: its other share
                f["evidence"] += (f"; {why}: that share is a correction within this cause (the mass data's split "
                                  f"between what the link carries and its own weight is off), not a bending")
            else:
                f["bound"] = why + ("; " + f["bound"] if f.get("bound") else "")
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
    mm, cause 2 started at 1.527). A step in time order is in the model like a named cause and chains too (only the
    residual's `unexplained`, which carries `correction`, starts from the named causes' model). Costs one refit per
    finding but the last; with `model` None (the time budget is spent) the search's own figures stay. Appends the
    held-out sentence to each finding's evidence."""
    named_f = [f for f in findings if f.get("kind") != "unexplained" or "correction" not in f]
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
