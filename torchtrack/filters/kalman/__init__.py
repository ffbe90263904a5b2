"""Kalman, extended and unscented Kalman filters, batched over any batch shape, and maneuver detection by the
chi-square test on the normalised innovation."""

from torchtrack.filters.kalman.filter import (
    ExtendedKalmanFilter,
    FilterResult,
    GaussianState,
    KalmanFilter,
    UnscentedKalmanFilter,
    UpdateInfo,
    chi2_bounds,
    nees,
)
from torchtrack.filters.kalman.maneuver import ManeuverDetectingKalmanFilter, ManeuverResult, two_point_init

__all__ = [
    "ExtendedKalmanFilter", "FilterResult", "GaussianState", "KalmanFilter", "ManeuverDetectingKalmanFilter",
    "ManeuverResult", "UnscentedKalmanFilter", "UpdateInfo", "chi2_bounds", "nees", "two_point_init",
]
