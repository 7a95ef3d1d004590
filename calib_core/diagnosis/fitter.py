"""The one fit the diagnosis uses: identify() on its data with the options the geometric model was chosen with
(an identified play's switch is found again on each fold)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, TypeVar

from ..identify import FTOL, Calibration, identify
from ..io import Measurements
from ..model import RobotModel
from .plays import _identified_play, _refold_plays

MODEL_ERROR_FTOL = 1e-4
"""The test at which each fit's first solve (weighted by the noise alone, for the model error it leaves) stops: the
Motoman's residual field took 17 iterations to the full test, 9 to this one; Agile Justin's diagnosis evaluated its
chain 1379 times, 737 with this. The model error comes out within a few 1e-3 of itself (its own sampling spread is a
few per cent), and the answer, solved to the full test from there, within 1e-4 of its std of the fully converged
first solve's (3e-5 at worst over 30 seeds; tests/core/test_identify.py bounds it at 1e-3)."""

T = TypeVar("T")
R = TypeVar("R")


@dataclass(frozen=True)
class _Fitter:
    """identify() on the diagnosis's data with one set of options: the geometry chosen on held-out evidence
    (free parameters, prior strength), the loss and the folds. A fit that adds causes to the last one starts where
    that one ended (identify's `start`): LM then takes a step or two instead of the whole way from nominal, to the
    same optimum."""

    model: RobotModel
    meas: Measurements
    loss: str | None
    folds: int
    free: tuple[str, ...] | None
    prior_scale: float
    workers: int = 1  # processes for the independent parts of the search (parallel.pmap)
    last: list = field(default_factory=list, compare=False, repr=False)

    @property
    def shared(self) -> tuple:
        """What a fit made in a worker process (parallel.pmap) must come back holding as itself: the model (the search
        checks a calibration's model by identity) and the poses."""
        return (self.model, self.meas)

    def apart(self, fn: Callable[[T], R], start: Calibration | None = None) -> Callable[[T], R]:
        """fn for parallel.pmap (and Ahead): every call starts where the fit before the map ended (or from `start`),
        and leaves the fit where it was when called (fits in worker processes cannot move it; in order they would, so
        one worker and several give the same answers; an Ahead whose child died is called here later, when the
        search's fit has moved on)."""
        begin = [start] if start is not None else list(self.last)

        def run(item: T) -> R:
            was = list(self.last)
            self.last[:] = begin
            try:
                return fn(item)
            finally:
                self.last[:] = was
        return run

    def __call__(self, effects=(), x_ref=None, folds: int | None = None, pose_noise=None,
                 model_error_mm: float | None = None, ftol: float = FTOL) -> Calibration:
        """The fit; the next one starts where it ended (a comparison the search does not go on from: `apart`)."""
        refold = None
        if any(_identified_play(e) for e in effects):
            refold = lambda cal: _refold_plays(self.meas, cal)  # noqa: E731
        cal = identify(self.model, self.meas, effects=tuple(effects), loss=self.loss, x_ref=x_ref, free=self.free,
                       prior_scale=self.prior_scale, folds=self.folds if folds is None else folds, refold=refold,
                       pose_noise=pose_noise, start=self.last[0] if self.last else None,
                       model_error_mm=model_error_mm, ftol=ftol, first_ftol=MODEL_ERROR_FTOL)
        self.last[:] = [cal]
        return cal
