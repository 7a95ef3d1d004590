"""Can these measurements belong to this model at all? Unit mistakes caught before anything is calibrated (issue 33).

A measurement CSV whose x, y, z are in metres on a model in mm, or whose joint column is in rad on a model in deg,
parses cleanly and used to calibrate "perfectly" (a joint scale of -0.999 absorbs a factor of 1000). Two checks,
both judged by registering the nominal model to the measured points (a rigid fit per setup, the pre-alignment of
calib_core.identify.prealign) and comparing the residual with the spread of the points:

- the points: when the nominal model cannot come within RATIO_LIMIT of the points' spread (residual RMS over the
  RMS distance of the points from their centroid, per setup), the points are read in the other length units of
  LENGTH_UNITS_MM; one that fits BETTER times better and within RATIO_LIMIT names the likely unit;
- each joint column whose numbers could be in the other unit (a revolute column within +-RAD_BOUND on a model in
  deg whose limits span more than MIN_SPAN_DEG, a prismatic column within the model's limits / 1000 on a model in
  mm, and the converse on models in rad or m when only the converted values are within the limits): read in that
  unit, the nominal model must fit BETTER times better and within RATIO_LIMIT, or nothing is said. A joint that
  barely moves in degrees (the iiwa's A3..A7, within 0.1 deg) is no suspect: read as radians it fits no better.

`unit_problems(model, meas)` is pure: the problems as the CSV parser's errors ({row, column, value, message},
row None: a whole column), empty when nothing is wrong or nothing can be said.
"""
from __future__ import annotations

import math

import numpy as np

from . import kinematics as K
from .io import Measurements
from .model import LENGTH_TO_MM, RobotModel

RATIO_LIMIT = 1 / 3
"""The registered nominal model's residual RMS over the points' RMS spread above which the points cannot be this
model's in these units. Measured (issue 33): the four real cells 0.003 (Motoman), 0.010 (Hilti, 7 setups), 0.026
(Agile Justin, 2 markers), 0.068 (iiwa, 4 targets); points in the wrong unit 0.96 (too large) to 1000 (too
small)."""
BETTER = 4.0
"""An alternative reading (another length unit of the points, a joint column in its other unit) is named only when
its ratio is this many times smaller than the data's as written (and within RATIO_LIMIT)."""
LENGTH_UNITS_MM = {"m": 1000.0, "cm": 10.0, "mm": 1.0, "inch": 25.4}
"""The units the points may have been written in, in mm."""
RAD_BOUND = 3.2
"""A revolute column on a model in deg whose values all lie within +-this (pi and rounding) may be in rad."""
MIN_SPAN_DEG = 20.0
"""... when the joint's limits span more than this (deg): a joint that may move only a few degrees is no
evidence either way."""
MIN_SPAN_MM = 20.0
"""A prismatic column on a model in mm within the model's limits / 1000 may be in m, when the limits span more
than this (mm)."""
LIMIT_SLACK = 0.1
"""A column read in its other unit must lie within the joint's limits widened by this share of their span."""
MAX_CHECK_ROWS = 1000
"""At most this many rows (evenly spaced) take part: the verdict does not need more, and a 200 000-row CSV is
judged in milliseconds, not seconds."""
MAX_GREEDY = 4
"""The search of joint columns in their other unit adds at most this many one at a time (more: all at once)..."""
MAX_SEARCHED = 12
"""... and only among at most this many suspect columns (more suspects: all at once only). With the rows capped,
the check costs a 7-axis arm a few milliseconds and a 100-joint chain whose every column is a suspect about a
second, not tens of seconds."""
MIN_ROWS = 3
"""Fewer distinct points than this leave nothing to register."""


def fit_ratio(model: RobotModel, meas: Measurements, points: np.ndarray | None = None,
              joints: np.ndarray | None = None) -> float:
    """Residual RMS of the nominal model registered (rigid fit per setup) to the points, over the points' RMS
    distance from their setup's centroid; NaN when the points have no spread. `points` (N, 3) mm and `joints`
    (N, n) rad / mm replace the measurements' own."""
    P = meas.points if points is None else points
    q = meas.joints if joints is None else joints
    S = meas.n_setups
    x = K.nominal_vector(model, n_setups=S)
    p = K.forward(model, x, q, np.broadcast_to(np.eye(3), (S, 3, 3)) if S > 1 else None, meas.labels)
    ssr = sst = 0.0
    for s in range(S):
        rows = slice(None) if S == 1 else meas.setup == s
        src, dst = p[rows], P[rows]
        if len(dst) == 0:
            continue
        R, t = K.rigid_fit(src, dst)
        ssr += float(((dst - (src @ R.T + t)) ** 2).sum())
        sst += float(((dst - dst.mean(0)) ** 2).sum())
    if not (sst > 1e-12 * max(1.0, float(np.abs(P).max()) ** 2)) or not math.isfinite(ssr):
        return math.nan
    return math.sqrt(ssr / sst)


def _rms_spread(points: np.ndarray, meas: Measurements) -> float:
    S = meas.n_setups
    sst = 0.0
    for s in range(S):
        dst = points if S == 1 else points[meas.setup == s]
        if len(dst):
            sst += float(((dst - dst.mean(0)) ** 2).sum())
    return math.sqrt(sst / max(1, len(points)))


def _g(v: float) -> str:
    return f"{v:.4g}"


def _sample(meas: Measurements) -> Measurements:
    if meas.n_poses <= MAX_CHECK_ROWS:
        return meas
    return meas.subset(np.unique(np.linspace(0, meas.n_poses - 1, MAX_CHECK_ROWS).round().astype(int)))


def _suspects(model: RobotModel, meas: Measurements) -> list[tuple[int, float, str, str]]:
    """Actuated joints whose column may be written in the joint's other unit: (model row, the factor that turns
    the column as written into that reading, that unit, the model's unit). Rad on a model in deg: every value
    within +-RAD_BOUND; m on a model in mm: every value times 1000 within the limits (widened by LIMIT_SLACK); both
    only where the limits span more than MIN_SPAN_DEG / MIN_SPAN_MM. Deg on a model in rad, mm on a model in m
    (possible with ?limits=warn): the values as written break the limits and the converted ones do not."""
    js = model.joint_scale()
    out = []
    for j in (int(k) for k in model.actuated):
        v = meas.joints[:, j] / js[j]  # the column as written, model units
        lo, hi = (float(b) / js[j] for b in model.limits[j])
        span = hi - lo
        if model.prismatic[j]:
            f, other, here = (1000.0, "m", "mm") if model.length_unit == "mm" else (0.001, "mm", "m")
            min_span = MIN_SPAN_MM / LENGTH_TO_MM[model.length_unit]
        else:
            f, other, here = ((180 / math.pi, "rad", "deg") if model.angle_unit == "deg" else
                              (math.pi / 180, "deg", "rad"))
            min_span = MIN_SPAN_DEG if model.angle_unit == "deg" else math.radians(MIN_SPAN_DEG)
        if not span > min_span:
            continue
        slack = LIMIT_SLACK * span if math.isfinite(span) else 0.0

        def within(a: np.ndarray) -> bool:
            return bool(((lo - slack <= a) & (a <= hi + slack)).all())

        if f > 1:  # numbers smaller than the model's unit wants
            small = within(v * f) if model.prismatic[j] else float(np.abs(v).max()) <= RAD_BOUND
        else:
            small = within(v * f) and not within(v)
        if small:
            out.append((j, f, other, here))
    return out


def _with(model: RobotModel, meas: Measurements, conv: dict[int, float]) -> np.ndarray:
    act = np.asarray(model.actuated)
    q = meas.joints[:, act].copy()
    for j, f in conv.items():
        q[:, list(act).index(j)] *= f
    return model.expand_joints(q)


UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "inch": "inches", "rad": "radians",
              "deg": "degrees"}


def _joint_search(model: RobotModel, meas: Measurements, points: np.ndarray, sus, ratio: float
                  ) -> tuple[list[int], float]:
    """The suspect joints whose other unit makes the nominal model fit the points best, and that fit's ratio:
    every suspect at once (a whole export in rad) or one at a time, greedily, while each cuts the ratio by a
    quarter or more, whichever fits better; then pruned of the columns the fit does not need (one whose unit makes
    no difference: it barely moves the point). ([], ratio) when no column helps."""
    fac = {j: f for j, f, _, _ in sus}

    def r_of(cols) -> float:
        r = fit_ratio(model, meas, points=points, joints=_with(model, meas, {j: fac[j] for j in cols}))
        return r if math.isfinite(r) else math.inf

    chosen, r_cur = [], ratio
    left = list(fac) if len(fac) <= MAX_SEARCHED else []
    while left and len(chosen) < MAX_GREEDY:
        r_new, j = min((r_of(chosen + [j]), j) for j in left)
        if not r_new <= 0.75 * r_cur:
            break
        chosen.append(j)
        left.remove(j)
        r_cur = r_new
    if len(fac) > 1:
        r_all = r_of(list(fac))
        if r_all < r_cur:
            chosen, r_cur = list(fac), r_all
    for j in list(chosen) if len(chosen) <= MAX_SEARCHED else []:
        rest = [k for k in chosen if k != j]
        if r_of(rest) <= 1.1 * r_cur + 1e-12:
            chosen = rest
    return chosen, (r_of(chosen) if chosen else ratio)



def unit_problems(model: RobotModel, meas: Measurements) -> list[dict]:
    """The CSV parser's errors ({row: None, column, value, message}) for points or joint columns that look written
    in another unit than the model's; [] when the nominal model fits them as written, or no other reading fits
    clearly better (nothing can be said).

    Readings tried: the points as written and, when they do not fit within RATIO_LIMIT, in the other unit of
    LENGTH_UNITS_MM that fits them best; each with the suspect joint columns (`_suspects`) as written or in their
    other unit (`_joint_search`). A reading other than the data as written is named when it fits within RATIO_LIMIT
    and BETTER times better than the data as written."""
    m = _sample(meas)
    if len(np.unique(np.round(m.points, 6), axis=0)) < MIN_ROWS:
        return []
    ratio = fit_ratio(model, m)
    if not math.isfinite(ratio):
        return []
    ls = LENGTH_TO_MM[model.length_unit]
    units = [(ratio, model.length_unit, 1.0)]
    if ratio > RATIO_LIMIT:  # the points do not fit as written: the other unit they fit best in
        # the numbers read in `unit`: internal mm = number * mm = (internal as read now) * mm / ls
        other = [(fit_ratio(model, m, points=m.points * (mm / ls)), u, mm / ls)
                 for u, mm in LENGTH_UNITS_MM.items() if u != model.length_unit]
        other = [o for o in other if math.isfinite(o[0])]
        if other:
            units.append(min(other))
    sus = _suspects(model, m)
    readings = []  # (ratio, points unit, factor, joints read in their other unit)
    for r, unit, f in units:
        cols, r_j = (_joint_search(model, m, m.points * f, sus, r) if sus else ([], r))
        readings.append((r_j, unit, f, cols))
    best = min(readings, key=lambda t: t[0])
    r_best, unit, f, cols = best
    if (f == 1.0 and not cols) or not (r_best <= RATIO_LIMIT and r_best * BETTER <= ratio):
        return []
    return _errors(model, m, meas, ratio, best, {j: (o, h, fj) for j, fj, o, h in sus})


def _errors(model: RobotModel, m: Measurements, meas: Measurements, ratio: float, best, info) -> list[dict]:
    """The errors of the reading `best`: the figures from the rows that took part (m), each column's range from
    all of them (meas)."""
    r_best, unit, f, cols = best
    lu = model.length_unit
    ls = LENGTH_TO_MM[lu]
    spread = _rms_spread(m.points, m) / ls  # of the points as written, model units
    js = model.joint_scale()
    read = ([f"x, y, z as {unit}"] if f != 1.0 else []) + [f"{model.joint_names[j]} as {info[j][0]}" for j in cols]
    fit = (f"Registered to the nominal model (a rigid fit), the data as written leave {_g(ratio * spread)} {lu} RMS "
           f"over a spread of {_g(spread)} {lu} ({_g(ratio)} of it; a model's own data stay well within "
           f"{_g(RATIO_LIMIT)}); read with {', '.join(read)}, they fit to {_g(r_best * spread * f)} {lu} RMS "
           f"over {_g(spread * f)} {lu} ({_g(r_best)})")
    errors = []
    if f != 1.0:
        how = f"multiply them by {_g(f)}" if f >= 1 else f"divide them by {_g(1 / f)}"
        msg = (f"the points look like {UNIT_WORDS[unit]}: the model's length unit is {lu}. {fit}. Write x, y, z "
               f"in {lu} ({how}) and upload again; nothing was stored")
        for k, c in enumerate("xyz"):
            v = meas.points[:, k] / ls
            errors.append({"row": None, "column": c, "value": f"{_g(float(v.min()))} .. {_g(float(v.max()))}",
                           "message": msg})
    for j in cols:
        other, here, fj = info[j]
        name = model.joint_names[j]
        v = meas.joints[:, j] / js[j]
        lo, hi = (float(b) / js[j] for b in model.limits[j])
        how = f"multiply by {_g(fj)}" if fj > 1 else f"divide by {_g(1 / fj)}"
        msg = (f"{name} looks like {UNIT_WORDS[other]}: its values span {_g(float(v.min()))} .. {_g(float(v.max()))}"
               f" while the model's {name} is in {here}, limits [{_g(lo)}, {_g(hi)}] {here}. {fit}. Write {name} "
               f"in {here} ({how}) and upload again; nothing was stored")
        errors.append({"row": None, "column": name, "value": f"{_g(float(v.min()))} .. {_g(float(v.max()))}",
                       "message": msg})
    return errors
