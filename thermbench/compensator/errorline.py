"""The error line: the compensation as a straight line over the axis travel, for controllers
that take one.

The error line (SINUMERIK 840D SD43900 / SD43910 / SD43920, Beckhoff TwinCAT CNC
P-AXIS-00273 / 00274 / 00272) is the least-squares straight line through the
compensation predicted at ``n_points`` positions over the travel:
``comp(x) = offset + slope * (x - ref)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Line:
    offset_um: float  # compensation at ref_mm
    slope_um_per_m: float
    ref_mm: float

    def at(self, x_mm) -> np.ndarray:
        return self.offset_um + self.slope_um_per_m * 1e-3 * (np.asarray(x_mm, dtype=float) - self.ref_mm)


def fit_line(x_mm: np.ndarray, comp_um: np.ndarray, ref_mm: float) -> Line:
    """Least-squares line ``comp = offset + slope (x - ref)`` (numpy.polyfit, degree 1)."""
    slope_um_per_mm, offset_um = np.polyfit(np.asarray(x_mm, dtype=float) - ref_mm, np.asarray(comp_um, dtype=float), 1)
    return Line(float(offset_um), float(slope_um_per_mm) * 1e3, float(ref_mm))
