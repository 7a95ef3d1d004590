"""Reference robot models in contract JSON form.

`spray7` is the 7-DoF hybrid spray-painting robot of Wang et al., Machines 2023, 11(1), 20:
Table 1 (MD-H), Table 2 (a2 = 250, a3 = 1350, a4 = 246, d2 = 626 mm, rail 0-4000 mm,
telescopic forearm 1700-2300 mm).  Joint ranges, masses and centres of mass are not in the
paper; the values here are plausible for a robot of that size and are marked as assumed.
`arm6` is a generic 6R industrial arm in standard DH (PUMA-like geometry) to prove that any
serial chain works.
"""
from __future__ import annotations

import copy

_SPRAY7 = {
    "name": "spray7",
    "convention": "mdh",
    "units": {"length": "mm", "angle": "deg"},
    "joints": [
        {"name": "J1", "type": "prismatic", "a": 0, "alpha": 0, "d": 0, "theta": 0, "beta": 0,
         "limits": [0, 4000], "mass": 400.0, "com": [0, 0, 0]},
        {"name": "J2", "type": "revolute", "a": 0, "alpha": -90, "d": 626, "theta": 0, "beta": 0,
         "limits": [-60, 60], "mass": 150.0, "com": [0, 0, -150]},
        {"name": "J3", "type": "revolute", "a": 250, "alpha": -90, "d": 0, "theta": 0, "beta": 0,
         "limits": [-80, 80], "mass": 90.0, "com": [675, 0, 0]},
        {"name": "J4", "type": "revolute", "a": 1350, "alpha": 0, "d": 0, "theta": 0, "beta": 0,
         "limits": [-120, 120], "mass": 40.0, "com": [120, 0, 0]},
        {"name": "J5", "type": "revolute", "a": 246, "alpha": -90, "d": 0, "theta": 0, "beta": 0,
         "limits": [-170, 170], "mass": 25.0, "com": [0, 0, 300]},
        {"name": "J6", "type": "prismatic", "a": 0, "alpha": 0, "d": 0, "theta": 0, "beta": 0,
         "limits": [1700, 2300], "mass": 30.0, "com": [0, 0, -850]},
        {"name": "J7", "type": "revolute", "a": 0, "alpha": 90, "d": 0, "theta": 0, "beta": 0,
         "limits": [-120, 120], "mass": 8.0, "com": [60, 0, 40]},
    ],
    "tool": [250.0, 0.0, 80.0],
    "gravity": [0, -9.81, 0],
}

_ARM6 = {
    "name": "arm6",
    "convention": "dh",
    "units": {"length": "mm", "angle": "deg"},
    "joints": [
        {"name": "A1", "type": "revolute", "a": 0, "alpha": -90, "d": 670, "theta": 0, "limits": [-170, 170],
         "mass": 60.0, "com": [0, 60, 0]},
        {"name": "A2", "type": "revolute", "a": 650, "alpha": 0, "d": 0, "theta": -90, "limits": [-120, 80],
         "mass": 40.0, "com": [-325, 0, 120]},
        {"name": "A3", "type": "revolute", "a": 115, "alpha": -90, "d": 0, "theta": 0, "limits": [-150, 150],
         "mass": 25.0, "com": [0, 0, 40]},
        {"name": "A4", "type": "revolute", "a": 0, "alpha": 90, "d": 760, "theta": 0, "limits": [-180, 180],
         "mass": 10.0, "com": [0, -100, 0]},
        {"name": "A5", "type": "revolute", "a": 0, "alpha": -90, "d": 0, "theta": 0, "limits": [-120, 120],
         "mass": 4.0, "com": [0, 0, 20]},
        {"name": "A6", "type": "revolute", "a": 0, "alpha": 0, "d": 130, "theta": 0, "limits": [-350, 350],
         "mass": 1.0, "com": [0, 0, -20]},
    ],
    "tool": [40.0, 25.0, 120.0],
    "gravity": [0, 0, -9.81],
}


def spray7() -> dict:
    """The reference 7-DoF spray-painting robot (rail, waist, two parallel pitch joints,
    forearm roll, telescopic forearm, wrist) as contract model JSON."""
    return copy.deepcopy(_SPRAY7)


def arm6() -> dict:
    """A 6R industrial arm in standard DH, as contract model JSON."""
    return copy.deepcopy(_ARM6)
