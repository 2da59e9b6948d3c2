"""Control design: linearization and the LQR family."""

from ._lqr import LQRResult, linearize, lqr
from ._riccati import solve_continuous_are, solve_discrete_are

__all__ = ["LQRResult", "linearize", "lqr", "solve_continuous_are", "solve_discrete_are"]
