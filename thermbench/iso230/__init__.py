"""ISO 230-2 and ISO 230-3 for thermbench: the standards' figures computed from tables
(:mod:`.standards`: pure numpy and pandas) and ``thermbench iso230``'s report of a dataset
(:mod:`.report`: report.md, figures.json and the drift figures). The figures' names are importable
from the package itself (``from thermbench.iso230 import drift_summary``), as before it was one.
"""

from .standards import (  # noqa: F401
    POSITIONING_COLUMNS,
    drift_summary,
    environmental_variation_error,
    error_line,
    error_lines,
    positioning_statistics,
    positioning_statistics_by,
    tilt,
)

__all__ = ["POSITIONING_COLUMNS", "drift_summary", "environmental_variation_error", "error_line", "error_lines", "positioning_statistics", "positioning_statistics_by", "tilt"]
