"""What identify() reuses between fits of one pose set: the pre-alignment and identifiability analysis (they depend
only on the model and the poses), and where LM starts when causes are added to a fitted model."""
from __future__ import annotations

from typing import Callable

import numpy as np

from . import kinematics as K
from .effects import Effect
from .identifiability import assess
from .io import Measurements
from .model import RobotModel


_PREPARED: list[tuple] = []
PREPARED_SIZE = 4
"""Pose sets whose pre-alignment and identifiability analysis identify() keeps (the most recent last)."""


def prepared(model: RobotModel, meas: Measurements, sigma: np.ndarray, prealign: Callable,
             measured_targets: Callable) -> tuple:
    """identify()'s work that depends only on the model and the poses, not on the effects or options: the rigid
    pre-alignment (x0, R0), the parameter names and the identifiability analysis (at the targets placed from the
    data). A diagnosis identifies one pose set hundreds of times (the analysis cost Agile Justin 97 s of 990), so
    the last PREPARED_SIZE are kept, keyed by the objects themselves (held, so their ids stay theirs) and checked
    against their arrays' contents. x0 is returned as a copy (callers may write into it). identify's `prealign` and
    `measured_targets` are passed in (this module sits below identify.py)."""
    key = (meas.points.tobytes(), meas.joints.tobytes(), sigma.tobytes())
    for k, (m, ms, kk, out) in enumerate(_PREPARED):
        if m is model and ms is meas and kk == key:
            _PREPARED.append(_PREPARED.pop(k))
            x0, *rest = out
            return (x0.copy(), *rest)
    x0, R0 = prealign(model, meas)
    names = K.parameter_names(model, meas.setup_names)
    x_at, judged = measured_targets(model, meas, sigma, x0, R0)
    J = K.Chain(model, x_at, meas.joints, R0, meas.labels).jacobian().reshape(-1, len(x0))
    ident = assess(judged, meas.joints, J, names, meas.setup_names)
    _PREPARED.append((model, meas, key, (x0.copy(), R0, names, ident)))
    del _PREPARED[:-PREPARED_SIZE]
    return x0, R0, names, ident


def start_at(cal, model: RobotModel, x0: np.ndarray, idx: np.ndarray,
              effects: tuple[Effect, ...]) -> np.ndarray | None:
    """LM's start [x[idx], effect parameters] from a calibration of the same model and parameter layout whose
    effects are among `effects` (a fitted model one or more causes are added to) or differ from them only by
    effects on no mass data (a rival form tried in place of one, a finding left out to test it again): its
    geometry, the values of the effects both hold, 0 for the new ones. None (nominal) otherwise: values of another
    form (a mass step on other mass data, a play with another switch) are no start at all (one elastic tree's mass
    identification stalled from them)."""
    if cal is None or cal.model is not model or len(cal.x) != len(x0):
        return None
    try:
        have = {e: np.asarray(v, float) for e, v in zip(cal.effects, cal.effect_values)}
        if not all(_on_no_mass_data(e) for e in set(have) - set(effects)):
            return None
    except TypeError:  # an effect holding arrays: not comparable, not reused
        return None
    if any(not _on_no_mass_data(e) for e in effects if e not in have) and not set(have) <= set(effects):
        return None
    theta = [have[e] if e in have else np.zeros(len(e.parameter_names(model))) for e in effects]
    return np.concatenate([cal.x[idx], *theta])


def _on_no_mass_data(e: Effect) -> bool:
    """An effect that carries no identified mass data or gravity of its own."""
    return not getattr(e, "masses", ()) and not getattr(e, "gravity", ())
