"""Noise models of the measuring instruments, for data that carry no `sigma` column.

Each preset is a per-axis 1-sigma that grows with the distance from the instrument (the origin of the
measurement frame): sigma = sigma0_mm + per_m_mm * distance_m. The figures are the makers' typical
specifications, read as 1-sigma per axis; a CSV `sigma` column always wins over them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Instrument:
    name: str
    sigma0_mm: float  # per-axis 1-sigma at the instrument
    per_m_mm: float  # growth per metre of distance (angular noise)
    basis: str  # where the figures come from
    sigma_rad: float = 1.7e-4  # per-axis 1-sigma of a measured orientation (6-D rows), rad

    def sigma_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Per-pose 1-sigma (mm) per axis at points (N, 3) mm of the measurement frame."""
        d_m = np.linalg.norm(np.asarray(points_mm, float), axis=1) / 1000.0
        return self.sigma0_mm + self.per_m_mm * d_m

    def describe(self) -> str:
        return (f"{self.name} ({self.sigma0_mm * 1000:.0f} um + {self.per_m_mm * 1000:.0f} um/m per axis: "
                f"{self.basis})")


INSTRUMENTS: dict[str, Instrument] = {i.name: i for i in (
    Instrument("laser_tracker", 0.015, 0.006, "a laser tracker's MPE, e.g. Leica AT960: 15 um + 6 um/m; "
                                              "orientation with a T-Mac: 0.01 deg", 1.7e-4),
    Instrument("optical", 0.030, 0.020, "an optical CMM / photogrammetric tracker, e.g. Creaform C-Track; "
                                        "orientation 0.02 deg", 3.5e-4),
    Instrument("motion_capture", 0.200, 0.0, "a marker motion-capture system, e.g. Vicon (0.15 mm static "
                                             "mean error, Merriaux et al. 2017, rounded up for a large volume); "
                                             "orientation of a rigid marker body 0.1 deg", 1.7e-3),
    Instrument("total_station", 0.500, 0.005, "a surveying total station: 0.6 mm + 1 ppm distance, 0.5-1\" angles; "
                                              "it measures no orientation", 1e-2),
)}
DEFAULT_INSTRUMENT = "laser_tracker"


def instrument(name: str | None) -> Instrument:
    """The preset called `name` (None: the default laser tracker); ValueError naming the choices otherwise."""
    key = DEFAULT_INSTRUMENT if name is None else str(name)
    if key not in INSTRUMENTS:
        raise ValueError(f"unknown instrument {key!r}: one of {', '.join(INSTRUMENTS)}")
    return INSTRUMENTS[key]
