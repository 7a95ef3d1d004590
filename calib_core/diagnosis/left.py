"""What the named causes leave: what it follows and its correction (an `unexplained` finding), or, where it is
noise-like, the noise floor re-estimated. Driven by the search (search.py), which begins the smooth correction ahead."""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from ..effects import Effect, LoadCompliance
from ..effects.residual import LENGTH_SCALES, fit_residual_field
from ..identify import Calibration
from ..io import Measurements
from ..parallel import pmap
from .evidence import HOLDOUT_ALPHA, _better, _p, holdout_ms
from .fitter import _Fitter
from .noise import _excess
from .residual import _drive_field, _follows, _unexplained_finding, _with_pose_noise, field_scale

if TYPE_CHECKING:
    from .search import _Search

NOISE_LIKE = 3.0
"""A residual that follows nothing is taken for noise (the floor re-estimated) only below this multiple of
the assumed floor; beyond it, it is reported as unexplained. So is one that follows something when no cause was
named and no correction predicts it on held-out poses (the note says what it follows), unless it is what the targets
of a pose share (a torso landing differently at each pose: no function of the joints predicts it, a reference target
would): the one false finding left in 1400 no-effect worlds of issue 34 (1.2x the floor, 6 % explained by J1's
angle, p = 2.2e-4)."""


def _left(search: _Search, notes: list[str], floor: float, note: str, basis: str, unexplained: bool,
          report: Callable[[float, str], None]) -> tuple:
    """What the search's causes leave, and its correction (an `unexplained` finding) or, where it is noise-like, the
    floor re-estimated (said in `notes`): (current, findings, rejected, named, floor, note, basis, structure_left),
    named the model of the named causes."""
    model, meas, fit, alpha, load_pool = search.model, search.meas, search.fit, search.alpha, search.load_pool
    found = {(f["kind"], tuple(f["joints"])) for f in search.findings}
    rejected = [r for r in search.rejected if (r["kind"], tuple(r["joints"])) not in found]
    current, chosen, findings, x_ref = search.current, search.chosen, search.findings, search.x_ref
    structure_left = _excess(current, floor) < alpha
    named = current  # the model of the named causes (what `unexplained` starts from)
    if unexplained and structure_left:
        report(0.85, "looking at what the residual left follows")
        held_out_rms = np.sqrt(holdout_ms(current))
        noise_like = basis == "assumed" and held_out_rms / floor <= NOISE_LIKE
        follows, fitted = _follows_and_corrections(search, current, chosen, x_ref, load_pool, noise_like)
        shared = next((f["effects"] for f in follows if f.get("family") == "shared_by_targets"), [])  # no correction
        trial = weighted = None  # can predict what the targets of a pose share
        if follows or not noise_like:
            for t, rf in sorted([f for f in fitted if f], key=lambda f: f[0].metrics()["holdout_rms_mm"]):
                if _better(current, t, HOLDOUT_ALPHA):
                    trial = (t, rf)
                    break
            weighted = _with_pose_noise(trial[0] if trial else current, fit, meas, shared)
        if noise_like and (not follows or (not chosen and trial is None and weighted is None and not shared)):
            new_floor = float(held_out_rms)
            after = f" left after {', '.join(e.label(model) for e in chosen)}" if chosen else ""
            what = ("follows nothing" + (" more" if chosen else "") + ": not time order, no joint, not the load, no "
                    "region of the workspace") if not follows else (
                f"follows {follows[0]['what']} (explains {follows[0]['share_pct']:.0f} %, "
                f"{_p(follows[0]['p_value'])}) and no correction predicts it on held-out poses")
            notes.append(f"the residual{after} ({new_floor:.3f} mm RMS held out) is above the assumed noise floor "
                         f"({floor:.3f} mm) but {what}; it looks like noise, so the robot's repeatability (or the "
                         f"instrument's noise) is probably worse than assumed. Measure some poses twice to know the "
                         f"floor.")
            note = f"estimated from the structure-free held-out residual (assumed floor was {floor:.3f} mm)"
            floor, basis = new_floor, "residual"
        else:
            before = current
            if trial is not None:
                current = trial[0]
            said = ""
            if weighted is not None:
                current, said = weighted
                notes.append("what the targets of a pose share: " + said)
            findings.append(_unexplained_finding(model, before, trial, floor, follows, basis, current, said))
        structure_left = _excess(current, floor) < alpha  # current or floor has changed
    return current, findings, rejected, named, floor, note, basis, structure_left


def _follows_and_corrections(search: _Search, current: Calibration, chosen: list[Effect], x_ref: np.ndarray,
                             load_pool: dict[int, LoadCompliance], noise_like: bool) -> tuple[list[dict], list]:
    """What the residual left by `chosen` follows (_follows) and, where it follows something or is not noise-like,
    the corrections tried for it: the smooth field and the joint-driven one ((calibration, correction) or None
    each; none past the deadline). Each correction starts from `current` (fit.apart). With several processes the
    smooth field, which needs nothing _follows finds, is fitted beside it (begun ahead where the model has not
    changed since: _Search.speculate; dropped when it was not needed)."""
    ready = search.speculation()  # first: it gives the search its processes back
    fit, meas, sigma = search.fit, search.meas, search.sigma
    apart = fit.apart(lambda make: make(), current)
    untested = "a smooth correction of what is left"  # what the deadline leaves, said once

    def traced():
        follows = _follows(current, meas, sigma, x_ref, search.alpha, load_pool, fit, chosen)
        due = (follows or not noise_like) and not search.late(untested)
        return follows, due, apart(lambda: _drive_field(fit, chosen, x_ref, follows)) if due else None

    if ready is not None:
        follows, due, drive = traced()
        field = ready.result() if due else ready.cancel()
    elif fit.workers > 1 and not search.late(untested):
        field, (follows, due, drive) = pmap(apart, [lambda: _smooth(fit, current, meas, chosen, x_ref), traced],
                                            fit.workers, fit.shared)
        if not due and (follows or not noise_like):  # a worker's deadline, said here
            search.late(untested)
    else:
        follows, due, drive = traced()
        field = apart(lambda: _smooth(fit, current, meas, chosen, x_ref)) if due else None
    return follows, [field, drive] if due else []


def _smooth(fit: _Fitter, current: Calibration, meas: Measurements, chosen: list[Effect], x_ref: np.ndarray):
    """The smooth field's correction of what `chosen` leave ((calibration, field) or None): its length scale by
    k-fold at the current model's linearisation (field_scale), fitted in full at that scale."""
    scales = (field_scale(current, meas, x_ref, fit.folds),) if fit.folds > 1 else LENGTH_SCALES
    return fit_residual_field(fit, current, chosen, x_ref, scales)
