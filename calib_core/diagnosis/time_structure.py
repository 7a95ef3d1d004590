"""Structure in time order: where a step sits in the session, and whether the poses a robust fit flags come in
runs (a warm-up, a re-homing) rather than scattered bad readings, and the note that names the outliers."""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
from scipy import special

from ..effects import Effect, SessionStep
from ..effects.structure import session_clock
from ..identify import Calibration
from ..io import Measurements
from .evidence import _p


def _when(e: Effect, meas: Measurements) -> str:
    """Where a step sits in the session, for people: the time and the poses on either side."""
    if not isinstance(e, SessionStep):
        return ""
    clock, source = session_clock(meas)
    if e.source == source != "row":
        order = np.argsort(clock, kind="stable")
        k = int(np.searchsorted(clock[order], e.at))
        stamp = (datetime.fromtimestamp(e.at, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC") if source == "time"
                 else f"sequence {e.at:.12g}")
    else:
        order, k, stamp = np.arange(meas.n_poses), int(e.at), f"row {int(e.at) + 1}"
    ids = meas.point_ids or [str(i + 1) for i in range(meas.n_poses)]
    before, after = ids[order[max(k - 1, 0)]], ids[order[min(k, len(order) - 1)]]
    return f"in time order between {before} and {after} ({stamp})"


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
    order = {"time": "time", "sequence": "measurement (the sequence column)"}.get(source, "row (no timestamps)")
    return (f"{n} pose(s) disagree with the rest by far more than the noise ({_pose_ids(meas, out)}), but they "
            f"are not scattered bad readings: in {order} order they come in {k} run(s) of consecutive measurements "
            f"({_p(p)} for bad readings placed at random). Something happened then (a warm-up, a re-homing, the "
            f"base or the tracker moved) or in the part of the workspace measured then: structure, so they are kept "
            f"at full weight for the search and the report")


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
