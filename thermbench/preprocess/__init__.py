"""Temperature preprocessing (seed 002 §2.3.1): limit + Kalman filtering of the temperature
channels, and selection of temperature-sensitive points by clustering and grey relational analysis."""

from .filters import KalmanFilter, LimitFilter, PreprocessError, default_steps, filter_process, resolve_steps
from .selection import (
    METHODS,
    Selection,
    cluster_sensors,
    grey_relational_grade,
    select_sensitive_points,
)

__all__ = [
    "METHODS",
    "KalmanFilter",
    "LimitFilter",
    "PreprocessError",
    "Selection",
    "cluster_sensors",
    "default_steps",
    "filter_process",
    "grey_relational_grade",
    "resolve_steps",
    "select_sensitive_points",
]
