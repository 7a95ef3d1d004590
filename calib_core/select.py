"""Choose the model's size on held-out evidence (cross-validated model selection, as in FIGAROH).

Nested candidates, simplest first:
  registration  the nominal geometry placed in the tracker frame: base pose + tool point only;
  offsets       + the joint zero offsets (theta of a revolute joint, d of a prismatic one);
  full          + every geometric parameter the pose set identifies;
the last two each with Tikhonov priors toward nominal of increasing strength (`PRIOR_SCALES` multiplies the
default prior precision of the joint parameters: 1 = today's weak prior, 1e4 = 100x smaller prior std).

Each candidate is scored by the k-fold held-out RMS that `identify(..., folds=k)` computes (the same fold
assignment for all). The best score wins, but with the one-standard-error rule: the simplest candidate whose
held-out RMS is within the fold-to-fold standard error of the best is chosen. Registration is always a
candidate, so the chosen model's held-out RMS is never worse than registration alone; when registration is
chosen, calibrating the geometry does not help on this data and `helps` is False.

Speed (a 150-pose job is meant to answer in well under 150 ms): every candidate is exactly
`identify(model, meas, free=..., prior_scale=..., folds=k)`, but the candidates share what does not depend on
them: the pre-alignment, the identifiability analysis of the pose set and a memo of chain evaluations
(point and Jacobian at every pose, per parameter vector). Each candidate's fit begins at the previous
candidate's solution (the neighbouring prior strength or the next smaller model), and every fold at the
candidate's full-data solution, so LM takes a step or two to the same convergence test instead of the
whole way from nominal; the answers agree with separate identify() calls to the convergence tolerance.
The folds of all candidates are solved together once every candidate is fitted (identify.held_out): each
round evaluates the chain once for all of them, a batch of parameter vectors in one pass, and every fold
takes exactly the steps it would take alone (the answer is the same to the bit).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import kinematics as K
from .identify import (DISTINCT_DECIMALS, Calibration, ChainEvaluations, Folds, _calibrate, _select, assess,
                       held_out, identify, measured_targets, pose_folds, prealign)
from .io import Measurements
from .model import RobotModel
from .parallel import pmap

PRIOR_SCALES = (1e4, 1e2, 1.0)
"""Prior strengths tried for the richer candidates, strongest (simplest) first."""
REGISTRATION = ("base", "tool")


def joint_offsets(model: RobotModel) -> tuple[str, ...]:
    """Names of the joint zero offsets: theta of every revolute joint, d of every prismatic one."""
    return tuple(f"{j}.{'d' if p else 'theta'}" for j, p in zip(model.joint_names, model.prismatic))


@dataclass
class GeometrySelection:
    free: tuple[str, ...] | None  # names / prefixes for identify(free=...) of the chosen model; None = all
    prior_scale: float  # identify(prior_scale=...) of the chosen model
    chosen_label: str
    table: list[dict]  # every candidate: label, free, prior_scale, n_parameters, holdout_rms_mm, fold_se_mm
    registration_holdout_rms_mm: float
    calibration: Calibration  # the chosen model, identified on all the data
    helps: bool  # the chosen model predicts held-out poses better than registration alone
    note: str = ""
    folds: int = 5
    best_label: str = ""  # the candidate with the smallest held-out RMS (before the one-SE rule)
    calibrations: dict[str, Calibration] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {"chosen": self.chosen_label, "best": self.best_label, "prior_scale": self.prior_scale,
                "free": list(self.free) if self.free is not None else None, "folds": self.folds,
                "helps": self.helps, "note": self.note,
                "registration_holdout_rms_mm": self.registration_holdout_rms_mm,
                "candidates": [{k: v for k, v in row.items() if k != "free"} for row in self.table]}


def _shares(cvs: list, n: int) -> list[list]:
    """The candidates' folds dealt to n processes by their cost (free parameters), largest first, each to the share
    with the least so far: the Motoman's two shares by turns took 0.16 and 0.10 s. Each fold's fit takes its own
    steps, so the shares do not change the answer."""
    parts, load = [[] for _ in range(n)], [0] * n
    for i in sorted(range(len(cvs)), key=lambda i: -len(cvs[i][1].idx)):
        w = load.index(min(load))
        parts[w].append(cvs[i])
        load[w] += len(cvs[i][1].idx)
    return parts


def _fold_stats(d: np.ndarray, assign: np.ndarray, folds: int, keep: np.ndarray | None = None
                ) -> tuple[float, float]:
    """Held-out RMS over the poses `keep` (default all) and the standard error of the per-fold RMS values; assign:
    the fold of every pose (identify.pose_folds)."""
    keep = np.ones(len(d), bool) if keep is None else keep
    parts = [keep & (assign == k) for k in range(folds)]
    per = np.array([np.sqrt(np.mean(d[part] ** 2)) for part in parts if part.any()])
    return float(np.sqrt(np.mean(d[keep] ** 2))), float(per.std(ddof=1) / np.sqrt(len(per))) if len(per) > 1 else 0.0


def _not_outliers(cals: list[Calibration], n: int) -> np.ndarray:
    """(n,) the poses the robust fit of the candidate that fits its poses tightest (median distance) does not name
    an outlier: readings of something else are out of the comparison (25 of 150 readings 5-1000 mm off made
    registration alone, 20 mm off on the rest, look as good as the full model's 0.15 mm), and a pose a simpler
    model's error pushes past the outlier bound stays in it. A simpler model's own flags miss small bad readings
    (its robust scale carries its model error: 21 of 25 flagged, and the other 4 chose a model 3 mm off)."""
    keep = np.ones(n, bool)
    if cals:
        tight = min(cals, key=lambda c: float(np.median(np.linalg.norm(c.solution.residual, axis=1))))
        keep[tight.solution.outliers] = False
    return keep if keep.sum() >= 2 else np.ones(n, bool)


def candidates(model: RobotModel) -> list[tuple[str, tuple[str, ...] | None, float]]:
    """(label, free, prior_scale) from the simplest to the richest."""
    out = [("registration", REGISTRATION, 1.0)]
    for label, free in (("offsets", REGISTRATION + joint_offsets(model)), ("full", None)):
        for s in PRIOR_SCALES:
            out.append((f"{label}, prior x{s:g}" if s != 1.0 else label, free, s))
    return out


class _Shared:
    """What every candidate of one pose set shares: noise weights, pre-alignment, identifiability analysis and
    the memo of chain evaluations; `identify` is identify(model, meas, free=..., ...) on them."""

    def __init__(self, model: RobotModel, meas: Measurements):
        self.model, self.meas = model, meas
        self.ident = None
        self.last_fit = None  # the last candidate's first fit (noise weights alone), full vector: the next one's start
        n_distinct = len(np.unique(np.round(meas.joints, DISTINCT_DECIMALS), axis=0))
        if meas.n_poses < 3 or n_distinct < 3:
            return  # identify() refuses such a pose set and says why
        self.sigma = meas.noise_sigma_mm()
        self.x0, self.R0 = prealign(model, meas)
        self.names = K.parameter_names(model, meas.setup_names)
        self.evals = ChainEvaluations(model, meas.joints, self.R0, labels=meas.labels)
        x_at, judged = measured_targets(model, meas, self.sigma, self.x0, self.R0)
        J = self.evals(x_at)[1].reshape(-1, len(self.x0))
        self.ident = assess(judged, meas.joints, J, self.names, meas.setup_names)

    def identify(self, free, idx, *, loss, folds, prior_scale, start=None) -> tuple[Calibration, Folds | None]:
        """The candidate identified on all the data, and its cross-validation still to be solved (held_out, with
        the other candidates'); None when the calibration already carries it."""
        model, meas = self.model, self.meas
        if self.ident is None or 3 * meas.n_poses <= len(idx):  # refused: identify() says why
            return identify(model, meas, free=free, loss=loss, folds=folds, prior_scale=prior_scale), None
        cal, first = _calibrate(model, meas, self.sigma, self.x0, self.R0, self.ident, idx, loss=loss, folds=1,
                                prior_scale=prior_scale, start=None if start is None else start[idx],
                                evals=self.evals)
        self.last_fit = self.x0.copy()
        self.last_fit[idx] = first.x
        return cal, Folds(cal.sigma_mm, idx, loss, True, prior_scale, cal.solution.x)


def select_geometry(model: RobotModel, meas: Measurements, *, loss: str | None = None,
                    folds: int = 5, workers: int = 1) -> GeometrySelection:
    """Pick the geometric model's size (and prior strength) by k-fold held-out RMS with the one-SE rule; the
    candidates' folds are solved in `workers` processes (the same answer: each fold's fit takes its own steps).

    Raises ValueError when the data cannot be cross-validated (fewer than 4 poses) or even registration
    cannot be identified."""
    k = min(folds, meas.n_poses // 2)
    if k < 2:
        raise ValueError(f"{meas.n_poses} poses are too few to judge a model on held-out poses")
    shared = _Shared(model, meas)
    table, cals, seen, cvs = [], {}, [], []
    for label, free, scale in candidates(model):
        idx = _select(shared.names, shared.ident, free) if shared.ident is not None else None
        if idx is not None and any(np.array_equal(idx, i) and scale == s for i, s in seen):
            continue  # the same model as a simpler candidate (e.g. no offset is identifiable)
        try:
            cal, cv = shared.identify(free, idx, loss=loss, folds=k, prior_scale=scale, start=shared.last_fit)
        except ValueError as e:
            if label == "registration":
                raise
            table.append({"label": label, "free": free, "prior_scale": scale, "n_parameters": None,
                          "holdout_rms_mm": None, "fold_se_mm": None, "skipped": str(e)})
            continue
        seen.append((cal.free, scale))
        table.append({"label": label, "free": free, "prior_scale": scale, "n_parameters": int(len(cal.free))})
        cals[label] = cal
        if cv is not None:
            cvs.append((cal, cv))
    if cvs:  # every candidate's folds solved together (in each process, its share of the candidates)
        parts = _shares(cvs, min(workers, len(cvs)))
        solved = pmap(lambda part: held_out(model, meas, shared.x0, shared.evals, [cv for _, cv in part], k), parts,
                      workers)
        for part, distances in zip(parts, solved):
            for (cal, _), d in zip(part, distances):
                cal.holdout_residual_mm = d
    keep = _not_outliers(list(cals.values()), meas.n_poses)
    assign = pose_folds(meas, k)
    for row in table:
        if row["label"] in cals:
            row["holdout_rms_mm"], row["fold_se_mm"] = _fold_stats(cals[row["label"]].holdout_residual_mm, assign,
                                                                   k, keep)
    scored = [r for r in table if r["holdout_rms_mm"] is not None]
    best = min(scored, key=lambda r: r["holdout_rms_mm"])
    limit = best["holdout_rms_mm"] + best["fold_se_mm"]
    chosen = next(r for r in scored if r["holdout_rms_mm"] <= limit)  # scored is simplest first
    reg = scored[0]["holdout_rms_mm"]
    helps = chosen["label"] != "registration" and chosen["holdout_rms_mm"] < reg
    out = f" (the {meas.n_poses - int(keep.sum())} outliers left out)" if not keep.all() else ""
    if helps:
        note = (f"the {chosen['label']} model predicts held-out poses at {chosen['holdout_rms_mm']:.3f} mm RMS "
                f"against {reg:.3f} mm with registration alone (base and tool only){out}")
    else:
        note = (f"calibrating the geometry does not help on this data: no richer model beats registration "
                f"alone (base and tool only, {reg:.3f} mm held-out RMS{out}) by more than the fold-to-fold "
                f"standard error; keep the nominal geometry")
    return GeometrySelection(free=chosen["free"], prior_scale=chosen["prior_scale"], chosen_label=chosen["label"],
                             table=table, registration_holdout_rms_mm=reg, calibration=cals[chosen["label"]],
                             helps=helps, note=note, folds=k, best_label=best["label"], calibrations=cals)
