"""The plan processes (CALIB_PLAN_PROCESSES): a plan is computed there, not on the API's route threads.

Issue 33: plans ran in the API process, so 16 concurrent 1000-pose plans held every route thread and a GET waited
48 s. Here at most `size` plans run at once, each in its own process, and at most `size` more wait for one; any
further plan is a 503 with Retry-After at once. A plan running longer than CALIB_PLAN_TIMEOUT_S is stopped: its
process is killed and replaced, and the request gets a 503 naming the bound. The machinery is a lane
(service/lanes.py), shared with predict, compensate and the CSV checks.
"""
from __future__ import annotations

from ..lanes import Lane, Words

PLANNERS = Lane("plan", __package__ + ".service", Words(
    "plan", "CALIB_PLAN_TIMEOUT_S", advice="fewer poses, or a retry when the server is less busy, plan faster"))


def configure(processes: int, timeout_s: float) -> Lane:
    """The plan lane: `processes` processes, as many plans waiting, the time bound."""
    PLANNERS.configure(processes, processes, timeout_s)
    return PLANNERS
