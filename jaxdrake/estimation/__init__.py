"""State estimation: steady-state and time-varying Kalman filters, Luenberger observers, and the
extended and unscented Kalman filters, each an observer system whose input is the plant's
input and output $[u; y]$ and whose output is the estimate $\\hat x$."""

from ._kalman import KalmanFilterResult, kalman_filter
from ._nonlinear import ExtendedKalmanFilter, UnscentedKalmanFilter
from ._observer import LuenbergerObserver, luenberger_observer
from ._time_varying import TimeVaryingKalmanFilterResult, time_varying_kalman_filter

__all__ = ["ExtendedKalmanFilter", "KalmanFilterResult", "LuenbergerObserver", "TimeVaryingKalmanFilterResult",
           "UnscentedKalmanFilter", "kalman_filter", "luenberger_observer", "time_varying_kalman_filter"]
