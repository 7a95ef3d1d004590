"""The plan processes (CALIB_PLAN_PROCESSES): a plan is computed there, not on the API's route threads.

Issue 33: plans ran in the API process, so 16 concurrent 1000-pose plans held every route thread and a GET waited
48 s. Here at most `size` plans run at once, each in its own process, and at most CALIB_PLAN_ROOM more wait for one
(default: 4 per process); any further plan is a 503 with Retry-After at once. A plan running longer than
CALIB_PLAN_TIMEOUT_S is stopped: its process is killed and replaced, and the request gets a 503 naming the bound. The
machinery is a lane (service/lanes.py), shared with predict, compensate and the CSV checks.

The waiting room: a plan waits on the event loop, holding no route thread (service.make_plan_async), and each plan
ahead of it ends within CALIB_PLAN_TIMEOUT_S, so four waiting per process are safe: the last one waits at most about
4 x the time bound (a 50-pose plan on a 7-joint arm takes about 0.8 s on one core, a 1000-pose one 2.5 s), and a
waiting plan holds its model and, for a diagnosis, its measurement set's bytes (at most CALIB_MAX_UPLOAD_BYTES).
Before (issue 33's red-team load), one plan waiting per process refused 2 of the mix's 50-pose plans with 503; 16
concurrent 1000-pose plans still meet the room: 5 run or wait, 11 get 503 at once.
"""
from __future__ import annotations

from ..config import PLAN_ROOM_PER_PROCESS
from ..lanes import Lane, Words

PLANNERS = Lane("plan", __package__ + ".service", Words(
    "plan", "CALIB_PLAN_TIMEOUT_S", room_env="CALIB_PLAN_ROOM",
    advice="fewer poses, or a retry when the server is less busy, plan faster"))


def configure(processes: int, timeout_s: float, room: int | None = None) -> Lane:
    """The plan lane: `processes` processes, `room` plans waiting (default PLAN_ROOM_PER_PROCESS per process), the
    time bound."""
    PLANNERS.configure(processes, PLAN_ROOM_PER_PROCESS * processes if room is None else room, timeout_s)
    return PLANNERS
