"""Find what the geometric model gets wrong, name the cause, extend the model, prove the gain held out.

Greedy and repeated: at the current model (geometry + effects found so far) every candidate cause is
scored by the linearised F-test of adding its columns to the coupled Jacobian (Bonferroni within its
family: named causes, steps in time order) and ranked by BIC; the best significant one is refitted jointly
with everything else and kept on evidence, not on its size against one measurement: its k-fold held-out
error must drop significantly (paired test over poses) and lower the de-noised model error (held-out mean
square minus the noise variance). Load-driven causes are also tried with the gravity load identified from
the data, so wrong or missing mass data do not hide them; the mass data shared by the compliances found are
then identified (bilinear, Gauss-Newton) and kept on held-out evidence. When the residual left is significantly above
the floor, the answer says what it follows (time order, a joint, the load, a workspace region): never silent.

One concept per module, each importing only those above it in this list (search drives them all; plays names
fitter's _Fitter for type checking only):
    noise           the noise floor a perfect model would leave, and how far the residual stands above it
    evidence        the held-out tests that keep a cause, the de-noised model error
    screening       the F-test of every candidate at the current model, the Bonferroni thresholds, the share a
                    smooth field explains beyond chance
    time_structure  where a step sits in time, flagged poses that come in runs
    plays           a gear play's switch read off the residual, and its doubt
    fitter          the one fit the diagnosis uses (_Fitter)
    findings        a confirmed cause written up, judged against physical sizes, presented, chained
    lookalikes      which form of a cause is kept: look-alikes, richer forms, a step's place, the revisit
    masses          loads identified from the data, the mass data identified under the compliances found
    residual        what the residual left follows, and the `unexplained` finding
    result          the Diagnosis record and its paragraph (explain)
    search          the greedy search (_Search) and diagnose()
"""
from .evidence import holdout_gain, holdout_ms
from .findings import (PLAUSIBLE_TRAVEL_MM, PLAUSIBLE_TURN_RAD, SIGNIFICANT_STD, follows_what, is_named,
                       named_joints, present_findings)
from .lookalikes import INDISTINGUISHABLE
from .noise import noise_floor_mm
from .result import Diagnosis, explain
from .screening import field_share, screen
from .search import ALPHA, NAMED_SHARE, diagnose
from .time_structure import runs_probability

__all__ = ["ALPHA", "INDISTINGUISHABLE", "NAMED_SHARE", "PLAUSIBLE_TRAVEL_MM", "PLAUSIBLE_TURN_RAD", "SIGNIFICANT_STD",
           "Diagnosis", "diagnose", "explain", "field_share", "follows_what", "is_named", "holdout_gain", "holdout_ms", "named_joints",
           "noise_floor_mm", "present_findings", "runs_probability", "screen"]
