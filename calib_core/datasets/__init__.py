"""Readers that turn third-party *real* calibration datasets into our contract formats.

The raw files live outside the repository (licences unclear or non-commercial, see each NOTES.md under
``SHARED_DATASETS``); nothing here copies them. One module per dataset, the shared helpers in ``_common``.
Each reader returns a :class:`Dataset` holding

* ``model``: the robot model JSON dict of the contract (sections 1 and 5), and
* ``csv_text``: the measurement CSV of the contract (sections 2 and 5), in the model's units,

exactly what a user would ``POST`` (``calib convert-dataset NAME OUTDIR`` writes them), so they exercise the
service on measured data instead of simulation. Only numpy, pyyaml and the stdlib are used.

=====================  ==============================================================================
reader                 what it writes
=====================  ==============================================================================
motoman_leica          Motoman MA1400 right arm, standard DH mm/deg, 586 Leica points, ``sigma``
iiwa7_payload          KUKA iiwa 7, standard DH mm/deg with masses, 4 payload runs (``payload``); optional
                       6-D rows (``qw,qx,qy,qz``) and measured torques (``tau_A1..tau_A7``)
iiwa7_run              the iiwa's other runs (exp1, exp2, 20161118: every joint moves), 6-D rows + torques
agile_justin_tree      DLR Agile Justin as ONE robot: torso with the coupled passive joint, two arms as
                       branches (``parent``), mount frames as ``fixed`` xyz/rpy rows, two ``targets``
hilti_trailblazer      Hilti lifting column + Doosan arm from its URDF (fixed, xyz/rpy/axis, mimic as
                       ``coupled`` rows), 7 recordings as ``setup`` s, ``timestamp``, ``temperature``
agile_justin           (older) torso + one arm folded into a serial MD-H chain, coupled joint as a column
=====================  ==============================================================================

Joint limits: where the robot really went beyond the published limits, a reader widens them to the data (padded)
and says so in ``notes`` rather than have the default upload (``?limits=reject``) refuse rows.
"""
from __future__ import annotations

from ._common import (IIWA_DIR, IIWA_JOINTS, IIWA_RUNS, MOTOMAN_DIR, MOTOMAN_JOINTS, SHARED_DATASETS, Dataset,
                      available, quaternion_wxyz)
from .hilti import (HILTI_DEFAULT_TEMPERATURE_C, HILTI_DIR, HILTI_FILES, HILTI_LIMIT_PAD_RAD, HILTI_SIGMA_MM,
                    HILTI_TEMPERATURE_C, hilti_available, hilti_trailblazer)
from .iiwa import IIWA_OTHER_RUNS, IIWA_TAU_SIGN, iiwa7_payload, iiwa7_run
from .justin import (JUSTIN_ARM_LINK_KG, JUSTIN_ARMS, JUSTIN_DIR, JUSTIN_FIXED, JUSTIN_HAND_KG, JUSTIN_LIMIT_PAD_DEG,
                     JUSTIN_MARKER_M, JUSTIN_Q, JUSTIN_SIGMA_MM, JUSTIN_TORSO, JUSTIN_TORSO_MASS,
                     JUSTIN_VENDOR_LIMITS_NOTE, agile_justin, agile_justin_links, agile_justin_tree, justin_available)
from .motoman import motoman_leica

__all__ = ["HILTI_DEFAULT_TEMPERATURE_C", "HILTI_DIR", "HILTI_FILES", "HILTI_LIMIT_PAD_RAD", "HILTI_SIGMA_MM",
           "HILTI_TEMPERATURE_C", "IIWA_DIR", "IIWA_JOINTS", "IIWA_OTHER_RUNS", "IIWA_RUNS", "IIWA_TAU_SIGN",
           "JUSTIN_ARM_LINK_KG", "JUSTIN_ARMS", "JUSTIN_DIR", "JUSTIN_FIXED", "JUSTIN_HAND_KG", "JUSTIN_LIMIT_PAD_DEG",
           "JUSTIN_MARKER_M", "JUSTIN_Q", "JUSTIN_SIGMA_MM", "JUSTIN_TORSO", "JUSTIN_TORSO_MASS",
           "JUSTIN_VENDOR_LIMITS_NOTE", "MOTOMAN_DIR", "MOTOMAN_JOINTS", "SHARED_DATASETS", "Dataset",
           "agile_justin", "agile_justin_links", "agile_justin_tree", "available", "hilti_available",
           "hilti_trailblazer", "iiwa7_payload", "iiwa7_run", "justin_available", "motoman_leica", "quaternion_wxyz"]
